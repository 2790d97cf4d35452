/* The validation scan of a recording's columns (daemon/recordings.py _scan), one chunk per call.
 *
 * scan_chunk     extremes and their counts, the smallest time step, finiteness and the exactly
 *                repeated rows of t and three strided channel fields, read in place.
 *
 * Buffers come through the buffer protocol only (no numpy C API); every length, format and
 * contiguity is checked before the loop runs, which runs without the GIL.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

#include "_buffers.h"

/* ---- the reading scan ---------------------------------------------------------------------- */

/* The validation scan of one chunk (daemon/recordings.py _scan), folded into `st` (SCAN_STATE
 * doubles: per-channel minimum, maximum and the counts of samples exactly at each, the smallest
 * time step, 1 while every value is finite): what np.min / np.max, counting (x == extreme) and
 * np.diff(t).min() give over the whole recording. same[k] (optional): row k equals the row before
 * it in all three channels (core.repeats.repeated_steps); the first row is compared with `prev`
 * (t, x0, x1, x2 of the row before the chunk) when given, else same[0] = 0. */
enum { S_LO = 0, S_HI = 3, S_NLO = 6, S_NHI = 9, S_MINDT = 12, S_FINITE = 13, SCAN_STATE = 14 };

/* One pass for the chunk's extremes (branch-free min/max), then, only for a channel whose chunk
 * extreme reaches the running one (rare after the first chunks), a pass counting the samples
 * exactly at it: the counts np.count_nonzero(x == extreme) give, as _scan did per chunk. The
 * strides and bases are copied to locals: `same` is a char store, which may alias anything. */
#define DEFINE_SCAN(NAME, T)                                                                        \
    static void NAME(const Py_buffer *t, const Py_buffer *x, const double *prev, double *st, char *same) \
    {                                                                                               \
        const Py_ssize_t m = t->shape[0], ts = t->strides[0];                                       \
        const Py_ssize_t s0 = x[0].strides[0], s1 = x[1].strides[0], s2 = x[2].strides[0];          \
        const char *tp = t->buf, *p0 = x[0].buf, *p1 = x[1].buf, *p2 = x[2].buf;                    \
        double lo0 = INFINITY, lo1 = INFINITY, lo2 = INFINITY, hi0 = -INFINITY, hi1 = -INFINITY,    \
               hi2 = -INFINITY, min_dt = st[S_MINDT];                                               \
        double f = 0.0, f0 = 0.0, f1 = 0.0, f2 = 0.0; /* x - x: 0 when finite, NaN for NaN and ±inf */ \
        double tq = prev ? prev[0] : NAN, q0 = prev ? prev[1] : NAN, q1 = prev ? prev[2] : NAN,     \
               q2 = prev ? prev[3] : NAN;                                                           \
        for (Py_ssize_t k = 0; k < m; k++) {                                                        \
            const double tk = *(const double *)(tp + k * ts), v0 = *(const T *)(p0 + k * s0),        \
                         v1 = *(const T *)(p1 + k * s1), v2 = *(const T *)(p2 + k * s2);             \
            f += tk - tk, f0 += v0 - v0, f1 += v1 - v1, f2 += v2 - v2;                              \
            const double dt = tk - tq; /* NaN before the first row: never below min_dt */           \
            min_dt = dt < min_dt ? dt : min_dt;                                                     \
            lo0 = v0 < lo0 ? v0 : lo0, lo1 = v1 < lo1 ? v1 : lo1, lo2 = v2 < lo2 ? v2 : lo2;        \
            hi0 = v0 > hi0 ? v0 : hi0, hi1 = v1 > hi1 ? v1 : hi1, hi2 = v2 > hi2 ? v2 : hi2;        \
            if (same)                                                                               \
                same[k] = (char)((v0 == q0) & (v1 == q1) & (v2 == q2));                             \
            tq = tk, q0 = v0, q1 = v1, q2 = v2;                                                     \
        }                                                                                           \
        st[S_MINDT] = min_dt;                                                                       \
        if (!(f + f0 + f1 + f2 == 0.0)) {                                                          \
            st[S_FINITE] = 0.0; /* extremes of non-finite data mean nothing: _scan stops here */    \
            return;                                                                                 \
        }                                                                                           \
        const double clo[3] = {lo0, lo1, lo2}, chi[3] = {hi0, hi1, hi2};                            \
        for (int c = 0; c < 3; c++) {                                                               \
            const char *p = x[c].buf;                                                               \
            const Py_ssize_t sc = x[c].strides[0];                                                  \
            if (clo[c] <= st[S_LO + c]) {                                                           \
                double n = 0.0;                                                                     \
                for (Py_ssize_t k = 0; k < m; k++)                                                  \
                    n += *(const T *)(p + k * sc) == clo[c];                                        \
                st[S_NLO + c] = clo[c] < st[S_LO + c] ? n : st[S_NLO + c] + n;                      \
                st[S_LO + c] = clo[c];                                                              \
            }                                                                                       \
            if (chi[c] >= st[S_HI + c]) {                                                           \
                double n = 0.0;                                                                     \
                for (Py_ssize_t k = 0; k < m; k++)                                                  \
                    n += *(const T *)(p + k * sc) == chi[c];                                        \
                st[S_NHI + c] = chi[c] > st[S_HI + c] ? n : st[S_NHI + c] + n;                      \
                st[S_HI + c] = chi[c];                                                              \
            }                                                                                       \
        }                                                                                           \
    }

DEFINE_SCAN(scan_f, float)
DEFINE_SCAN(scan_d, double)

static PyObject *scan_chunk(PyObject *self, PyObject *args)
{
    PyObject *ot, *ox[3], *oprev, *ost, *osame;
    if (!PyArg_ParseTuple(args, "OOOOOOO:scan_chunk", &ot, &ox[0], &ox[1], &ox[2], &oprev, &ost, &osame))
        return NULL;
    Py_buffer v[7] = {{0}};
    Py_buffer *t = v, *x = v + 1, *prev = v + 4, *st = v + 5, *same = v + 6;
    static const char *xname[3] = {"channel 0", "channel 1", "channel 2"};
    if (get_strided(ot, t, "t", "d", 1) < 0)
        goto fail;
    Py_ssize_t m = t->shape[0];
    for (int c = 0; c < 3; c++)
        if (get_strided(ox[c], &x[c], xname[c], "fd", 1) < 0)
            goto fail;
    char kind = kind_of(&x[0]);
    for (int c = 0; c < 3; c++)
        if (kind_of(&x[c]) != kind || x[c].shape[0] != m) {
            PyErr_Format(PyExc_ValueError, "t and the three channels must have one length (%zd) and the channels one "
                         "float type", m);
            goto fail;
        }
    if (oprev != Py_None && get_contiguous(oprev, prev, "prev", 'd', 4, 0) < 0)
        goto fail;
    if (get_contiguous(ost, st, "state", 'd', SCAN_STATE, 1) < 0)
        goto fail;
    if (osame != Py_None && get_contiguous(osame, same, "same", '?', m, 1) < 0)
        goto fail;
    const double *pv = oprev != Py_None ? prev->buf : NULL;
    char *sm = osame != Py_None ? same->buf : NULL;
    Py_BEGIN_ALLOW_THREADS
    if (kind == 'f')
        scan_f(t, x, pv, st->buf, sm);
    else
        scan_d(t, x, pv, st->buf, sm);
    Py_END_ALLOW_THREADS
    release_all(v, 7);
    Py_RETURN_NONE;
fail:
    release_all(v, 7);
    return NULL;
}

static PyMethodDef methods[] = {
    {"scan_chunk", scan_chunk, METH_VARARGS,
     "scan_chunk(t, x0, x1, x2, prev, state, same)\nThe reading scan of one chunk folded into state (14 float64:\n"
     "min[3], max[3], count at min[3], count at max[3], smallest step, all finite); same (m,) bool, optional:\n"
     "each row equal to the one before (prev: t, x0, x1, x2 of the row before the chunk, or None)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_scankernel",
                                    "The reading scan's compiled loop (no numpy C API).", -1, methods,
                                    NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__scankernel(void)
{
    return PyModule_Create(&module);
}
