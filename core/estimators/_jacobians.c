/* The batch fit's corrected accelerations and Jacobians, window by window (parameterization.py, extended.py).
 *
 * Both functions are one pass over the windows with no temporaries, replacing numpy forms that build
 * (M, 3, P) and (M, P, 3, 3) arrays. Built with -ffp-contract=off: every a * b + c rounds twice, as numpy's
 * elementwise operations do; the one fused multiply-add is written out (fma) where it reproduces OpenBLAS.
 * Every buffer must be C-contiguous float64 of the length the dimensions imply; anything else is a
 * TypeError/ValueError, never an access out of bounds. tests/core/test_jacobians.py holds the numpy forms.
 *
 * linear_norm_jacobian (_jacobians_linear.c): a parameterization with constant derivatives (offsets, 6, 9,
 * 12), each result numpy's bit for bit on this BLAS; extended_accel_jacobian (_jacobians_extended.c): the
 * extended models, whose derivative rows depend on the window; _jacobians_share.c: a call's windows shared
 * with a helper thread. What they share: core/estimators/_jacobians.h. This file holds the method table.
 */
#include "_jacobians.h"

static PyMethodDef methods[] = {
    {"linear_norm_jacobian", linear_norm_jacobian, METH_VARARGS,
     "linear_norm_jacobian(Kinv, o, G, C, raw, cov or None, h, B, a, var or None, M, P, threads=-1): h = |a|, B = dh/dp, a, "
     "var h; threads 1, 2 (the windows shared with a helper thread) or -1 (2 from 4096 windows on)"},
    {"extended_accel_jacobian", extended_accel_jacobian, METH_VARARGS,
     "extended_accel_jacobian(K_const, o_const, p, rows, entries, values, raw, a, J, M, P, n, threads=-1): a = K(c)^-1 "
     "(raw - o(c)), J = da/dp; threads as linear_norm_jacobian's"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_jacobians",
                                    "The batch fit's corrected accelerations and Jacobians, window by window.", -1,
                                    methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__jacobians(void)
{
    share_init();
    return PyModule_Create(&module);
}
