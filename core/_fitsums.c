/* Per-window sums of products of the Lötters batch fit (core/crlb.py, core/estimators/).
 *
 * Each function is one numpy einsum contraction over thousands of windows whose summed axis has 3 to 15
 * terms: numpy's einsum adds the products one after another into a zeroed output, and so do these loops
 * (compiled with -ffp-contract=off: no fused multiply-add), so the results equal numpy's bit for bit
 * (tests/core/test_fitsums.py checks it against einsum). Every buffer must be C-contiguous float64 of
 * the length the given dimensions imply; anything else is a ValueError/TypeError, never an access out
 * of bounds.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

#include "_buffers.h"

/* m x max(p, 1) x max(k, 1) doubles must be addressable: every count the functions form is at most that. */
static int dims_ok(Py_ssize_t m, Py_ssize_t p, Py_ssize_t k)
{
    if (m < 0 || p < 0 || k < 0) {
        PyErr_SetString(PyExc_ValueError, "dimensions must be >= 0");
        return 0;
    }
    if (m > PY_SSIZE_T_MAX / 8 / (p ? p : 1) / (k ? k : 1)) {
        PyErr_SetString(PyExc_ValueError, "dimensions too large");
        return 0;
    }
    return 1;
}

/* combine(coef (P,), rows (M, P, K), out (M, K)): out[m, j] = sum_p coef[p] rows[m, p, j],
 * numpy's einsum("p,mpk->mk") (extended.py rows_K_o: K(c), o(c) of every window, module docstring). */
static PyObject *combine(PyObject *self, PyObject *args)
{
    PyObject *oc, *orows, *oout;
    Py_ssize_t m, p, k;
    if (!PyArg_ParseTuple(args, "OOOnnn", &oc, &orows, &oout, &m, &p, &k) || !dims_ok(m, p, k))
        return NULL;
    Py_buffer v[3] = {{0}}, *bc = v, *br = v + 1, *bo = v + 2;
    if (get_doubles(oc, bc, p, 0, "coef") < 0 || get_doubles(orows, br, m * p * k, 0, "rows") < 0 ||
        get_doubles(oout, bo, m * k, 1, "out") < 0) {
        release_all(v, 3);
        return NULL;
    }
    const double *c = bc->buf, *r = br->buf;
    double *o = bo->buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < m; i++) {
        const double *ri = r + i * p * k;
        double *oi = o + i * k;
        for (Py_ssize_t j = 0; j < k; j++)
            oi[j] = 0.0;
        for (Py_ssize_t q = 0; q < p; q++) {
            const double cq = c[q], *rq = ri + q * k;
            for (Py_ssize_t j = 0; j < k; j++)
                oi[j] += cq * rq[j];
        }
    }
    Py_END_ALLOW_THREADS
    release_all(v, 3);
    Py_RETURN_NONE;
}

/* norm_project(a (M, 3), J (M, 3, P), h (M,), B (M, P)): h[m] = |a_m| and B[m, q] = sum_i (a[m, i] / h[m]) J[m, i, q]:
 * h = |a| (Lötters eq. 8) as np.linalg.norm(a, axis=1) (sqrt of a0² + a1², plus a2²) and dh/dp = (a / |a|)^T da/dp
 * (eq. 13a, parameterization.py) as numpy's einsum("mi,mip->mp", a / h[:, None], J). */
static PyObject *norm_project(PyObject *self, PyObject *args)
{
    PyObject *oa, *oj, *oh, *ob;
    Py_ssize_t m, p;
    if (!PyArg_ParseTuple(args, "OOOOnn", &oa, &oj, &oh, &ob, &m, &p) || !dims_ok(m, p, 3))
        return NULL;
    Py_buffer v[4] = {{0}}, *ba = v, *bj = v + 1, *bh = v + 2, *bb = v + 3;
    if (get_doubles(oa, ba, m * 3, 0, "a") < 0 || get_doubles(oj, bj, m * 3 * p, 0, "J") < 0 ||
        get_doubles(oh, bh, m, 1, "h") < 0 || get_doubles(ob, bb, m * p, 1, "B") < 0) {
        release_all(v, 4);
        return NULL;
    }
    const double *A = ba->buf, *J = bj->buf;
    double *H = bh->buf, *B = bb->buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < m; i++) {
        const double *ai = A + 3 * i, *Ji = J + 3 * p * i;
        double *bi = B + p * i;
        double ss = ai[0] * ai[0] + ai[1] * ai[1];
        const double h = sqrt(ss + ai[2] * ai[2]);
        H[i] = h;
        for (Py_ssize_t q = 0; q < p; q++)
            bi[q] = 0.0;
        for (Py_ssize_t c = 0; c < 3; c++) {
            const double uc = ai[c] / h, *Jc = Ji + c * p;
            for (Py_ssize_t q = 0; q < p; q++)
                bi[q] += uc * Jc[q];
        }
    }
    Py_END_ALLOW_THREADS
    release_all(v, 4);
    Py_RETURN_NONE;
}

/* quadratic(g (M, 3), C (M, 3, 3), out (M,)): out[m] = sum_ij (g_i C_ij) g_j,
 * numpy's einsum("mi,mij,mj->m"): the delta-method variance of h = |a| (crlb.h_variance, Lötters' C_mu). */
static PyObject *quadratic(PyObject *self, PyObject *args)
{
    PyObject *og, *oC, *oout;
    Py_ssize_t m;
    if (!PyArg_ParseTuple(args, "OOOn", &og, &oC, &oout, &m) || !dims_ok(m, 9, 1))
        return NULL;
    Py_buffer v[3] = {{0}}, *bg = v, *bC = v + 1, *bo = v + 2;
    if (get_doubles(og, bg, m * 3, 0, "g") < 0 || get_doubles(oC, bC, m * 9, 0, "C") < 0 ||
        get_doubles(oout, bo, m, 1, "out") < 0) {
        release_all(v, 3);
        return NULL;
    }
    const double *g = bg->buf, *C = bC->buf;
    double *o = bo->buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < m; i++) {
        const double *gi = g + 3 * i, *Ci = C + 9 * i;
        double s = 0.0;
        for (int a = 0; a < 3; a++)
            for (int b = 0; b < 3; b++) {
                double t = gi[a] * Ci[3 * a + b];
                s += t * gi[b];
            }
        o[i] = s;
    }
    Py_END_ALLOW_THREADS
    release_all(v, 3);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"combine", combine, METH_VARARGS, "combine(coef, rows, out, M, P, K): out[m, k] = sum_p coef[p] rows[m, p, k]"},
    {"norm_project", norm_project, METH_VARARGS,
     "norm_project(a, J, h, B, M, P): h[m] = |a[m]|, B[m, p] = sum_i a[m, i] / h[m] J[m, i, p]"},
    {"quadratic", quadratic, METH_VARARGS, "quadratic(g, C, out, M): out[m] = sum_ij g[m, i] C[m, i, j] g[m, j]"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_fitsums",
                                    "Per-window sums of products of the batch fit, as numpy's einsum adds them.", -1,
                                    methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__fitsums(void) { return PyModule_Create(&module); }
