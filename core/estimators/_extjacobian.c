/* The extended models' corrected acceleration and its Jacobian, window by window (extended.py, _Bound).
 *
 * At window m with per-window derivative rows dK_q(c_m) (3 x 3) and do_q(c_m) (3,) of parameter q:
 *
 *     K = K_const + sum_q p_q dK_q,   o = o_const + sum_q p_q do_q          (extended.py module docstring)
 *     a = K^-1 (raw - o)                                                    (Lötters eq. 8, before the norm)
 *     J[:, q] = da/dp_q = -K^-1 (dK_q a + do_q)                              (parameterization.py docstring)
 *
 * One pass over the windows with no temporaries, instead of numpy's (M, P, 3, 3) sums, the adjugate inverse
 * of every K and three batched products. The sums over q start from 0.0 and add in q order, as numpy's
 * einsum("p,mpij->mij") does; K^-1 is the adjugate over the determinant operation for operation as the numpy
 * form in tests/core/test_extjacobian.py; the three-term products add left to right (numpy's batched matmul
 * hands those to OpenBLAS, whose kernels add in another order: the results agree to rounding, the test
 * derives the bound). Built with -ffp-contract=off (no fused multiply-add), so each operation rounds as
 * numpy's elementwise ops do and the numpy oracle in the test equals this bit for bit. Every buffer must be
 * C-contiguous float64 of the length the dimensions imply; anything else is a TypeError/ValueError.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

/* Get a C-contiguous float64 buffer of exactly n doubles (writable if asked); 0 on success. */
static int get_doubles(PyObject *obj, Py_buffer *view, Py_ssize_t n, int writable, const char *name)
{
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) < 0) {
        PyErr_Clear();
        PyErr_Format(PyExc_TypeError, "%s must be a C-contiguous%s float64 array", name, writable ? " writable" : "");
        return -1;
    }
    const char *f = view->format;
    if (f != NULL && (f[0] == '<' || f[0] == '=' || f[0] == '@'))
        f++;
    if (view->itemsize != 8 || f == NULL || strcmp(f, "d") != 0) {
        PyBuffer_Release(view);
        PyErr_Format(PyExc_TypeError, "%s must be float64", name);
        return -1;
    }
    if (view->len != n * 8) {
        PyBuffer_Release(view);
        PyErr_Format(PyExc_ValueError, "%s holds %zd values, expected %zd", name, view->len / 8, n);
        return -1;
    }
    return 0;
}

#define N_BUF 8

/* accel_jacobian(K_const (3, 3), o_const (3,), p (P,), dK (M, P, 3, 3), do (M, P, 3), raw (M, 3),
 *                a (M, 3) out, J (M, 3, P) out, M, P) */
static PyObject *accel_jacobian(PyObject *self, PyObject *args)
{
    PyObject *obj[N_BUF];
    Py_ssize_t m, p;
    if (!PyArg_ParseTuple(args, "OOOOOOOOnn", &obj[0], &obj[1], &obj[2], &obj[3], &obj[4], &obj[5], &obj[6],
                          &obj[7], &m, &p))
        return NULL;
    if (m < 0 || p < 1) {
        PyErr_SetString(PyExc_ValueError, "need M >= 0 windows and P >= 1 parameters");
        return NULL;
    }
    if (m > PY_SSIZE_T_MAX / 8 / 9 / p) {
        PyErr_SetString(PyExc_ValueError, "dimensions too large");
        return NULL;
    }
    static const char *names[N_BUF] = {"K_const", "o_const", "p", "dK", "do", "raw", "a", "J"};
    const Py_ssize_t len[N_BUF] = {9, 3, p, m * p * 9, m * p * 3, m * 3, m * 3, m * 3 * p};
    Py_buffer buf[N_BUF];
    int got = 0;
    for (; got < N_BUF; got++)
        if (get_doubles(obj[got], &buf[got], len[got], got >= 6, names[got]) < 0)
            break;
    if (got < N_BUF) {
        while (got-- > 0)
            PyBuffer_Release(&buf[got]);
        return NULL;
    }
    const double *Kc = buf[0].buf, *oc = buf[1].buf, *c = buf[2].buf, *dK = buf[3].buf, *dO = buf[4].buf,
                 *raw = buf[5].buf;
    double *A = buf[6].buf, *J = buf[7].buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t w = 0; w < m; w++) {
        const double *dKw = dK + w * p * 9, *dOw = dO + w * p * 3;
        double K[9], o[3], inv[9], d[3], a[3];
        /* K(c), o(c): einsum("p,mpij->mij") and ("p,mpi->mi") from 0.0 in q order, then the constant part */
        for (int j = 0; j < 9; j++)
            K[j] = 0.0;
        for (int j = 0; j < 3; j++)
            o[j] = 0.0;
        for (Py_ssize_t q = 0; q < p; q++) {
            for (int j = 0; j < 9; j++)
                K[j] += c[q] * dKw[q * 9 + j];
            for (int j = 0; j < 3; j++)
                o[j] += c[q] * dOw[q * 3 + j];
        }
        for (int j = 0; j < 9; j++)
            K[j] = Kc[j] + K[j];
        for (int j = 0; j < 3; j++)
            o[j] = oc[j] + o[j];
        /* K^-1 = adjugate / determinant (a singular K gives inf/NaN, as the numpy form does) */
        const double ka = K[0], kb = K[1], kc = K[2], kd = K[3], ke = K[4], kf = K[5], kg = K[6], kh = K[7], ki = K[8];
        inv[0] = ke * ki - kf * kh, inv[1] = kc * kh - kb * ki, inv[2] = kb * kf - kc * ke;
        inv[3] = kf * kg - kd * ki, inv[4] = ka * ki - kc * kg, inv[5] = kc * kd - ka * kf;
        inv[6] = kd * kh - ke * kg, inv[7] = kb * kg - ka * kh, inv[8] = ka * ke - kb * kd;
        const double det = ka * inv[0] + kb * inv[3] + kc * inv[6];
        for (int j = 0; j < 9; j++)
            inv[j] /= det;
        /* a = K^-1 (raw - o) */
        for (int j = 0; j < 3; j++)
            d[j] = raw[3 * w + j] - o[j];
        for (int i = 0; i < 3; i++)
            a[i] = A[3 * w + i] = inv[3 * i] * d[0] + inv[3 * i + 1] * d[1] + inv[3 * i + 2] * d[2];
        /* J[:, q] = -K^-1 (dK_q a + do_q) */
        double *Jw = J + w * 3 * p;
        for (Py_ssize_t q = 0; q < p; q++) {
            const double *G = dKw + q * 9, *g = dOw + q * 3;
            double t[3];
            for (int j = 0; j < 3; j++)
                t[j] = (G[3 * j] * a[0] + G[3 * j + 1] * a[1] + G[3 * j + 2] * a[2]) + g[j];
            for (int i = 0; i < 3; i++)
                Jw[i * p + q] = -(inv[3 * i] * t[0] + inv[3 * i + 1] * t[1] + inv[3 * i + 2] * t[2]);
        }
    }
    Py_END_ALLOW_THREADS
    for (int k = 0; k < N_BUF; k++)
        PyBuffer_Release(&buf[k]);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"accel_jacobian", accel_jacobian, METH_VARARGS,
     "accel_jacobian(K_const, o_const, p, dK, do, raw, a, J, M, P): a = K(c)^-1 (raw - o(c)) and J = da/dp per window"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_extjacobian",
                                    "The extended models' corrected acceleration and Jacobian, window by window.", -1,
                                    methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__extjacobian(void) { return PyModule_Create(&module); }
