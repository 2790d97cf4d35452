/* The moving-variance detector's signal (core/detectors/variance.py MovingVarianceDetector.update).
 *
 * moving_std(ext, w, sums, det): ext (6, w + n) holds, per row, the last w values before the block and
 * the block's n values of y (rows 0-2: each axis minus the first finite sample) and y² (rows 3-5). With
 * the trailing-window sums s carried in `sums` (updated in place), for each sample j
 *
 *     s_c += ext[c, w + j] - ext[c, j]                      np.cumsum of the increments, sequential
 *     var_i = (s_{3+i} - s_i s_i / w) / (w - 1)              the sample variance (ddof=1) of axis i
 *     det[j] = sqrt(maximum(maximum(maximum(var_0, var_1), var_2), 0))
 *
 * the numpy form's operations in its order (np.cumsum adds left to right; np.maximum keeps a NaN and
 * otherwise returns its second argument unless the first is larger, so the signs of equal zeros come
 * out as numpy's; np.clip(x, 0, None) is np.maximum(x, 0)). Built with -ffp-contract=off: every
 * product and sum rounds as numpy's elementwise operations do. tests/core/test_moving_std.py keeps the
 * numpy form. Buffers are checked for format, length and contiguity before the loop; the loop runs
 * without the GIL for long blocks. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

#include "../_buffers.h"

#define NOGIL_MIN 2048 /* samples from which the loop releases the GIL */

static inline double numpy_maximum(double a, double b)
{
    return (a > b || isnan(a)) ? a : b;
}

static void moving_std_loop(const double *ext, Py_ssize_t w, Py_ssize_t n, double *s, double *det)
{
    const Py_ssize_t row = w + n;
    const double wd = (double)w, wd1 = (double)(w - 1);
    double s0 = s[0], s1 = s[1], s2 = s[2], q0 = s[3], q1 = s[4], q2 = s[5];
    const double *y0 = ext, *y1 = ext + row, *y2 = ext + 2 * row;
    const double *z0 = ext + 3 * row, *z1 = ext + 4 * row, *z2 = ext + 5 * row;
    for (Py_ssize_t j = 0; j < n; j++) {
        s0 += y0[w + j] - y0[j], s1 += y1[w + j] - y1[j], s2 += y2[w + j] - y2[j];
        q0 += z0[w + j] - z0[j], q1 += z1[w + j] - z1[j], q2 += z2[w + j] - z2[j];
        const double v0 = (q0 - s0 * s0 / wd) / wd1, v1 = (q1 - s1 * s1 / wd) / wd1, v2 = (q2 - s2 * s2 / wd) / wd1;
        det[j] = sqrt(numpy_maximum(numpy_maximum(numpy_maximum(v0, v1), v2), 0.0));
    }
    s[0] = s0, s[1] = s1, s[2] = s2, s[3] = q0, s[4] = q1, s[5] = q2;
}

static PyObject *moving_std(PyObject *self, PyObject *args)
{
    PyObject *oext, *osums, *odet;
    Py_ssize_t w;
    if (!PyArg_ParseTuple(args, "OnOO:moving_std", &oext, &w, &osums, &odet))
        return NULL;
    if (w < 2) {
        PyErr_Format(PyExc_ValueError, "window must hold at least 2 samples, got %zd", w);
        return NULL;
    }
    Py_buffer v[3] = {{0}};
    Py_buffer *ext = v, *sums = v + 1, *det = v + 2;
    if (get_contiguous(oext, ext, "ext", 'd', -1, 0) < 0)
        goto fail;
    const Py_ssize_t items = ext->len / 8;
    if (items % 6 != 0 || items / 6 < w) {
        PyErr_Format(PyExc_ValueError, "ext must be (6, %zd + n): 6 rows of the window's %zd values and the block's, got %zd "
                     "values", w, w, items);
        goto fail;
    }
    const Py_ssize_t n = items / 6 - w;
    if (get_contiguous(osums, sums, "sums", 'd', 6, 1) < 0 || get_contiguous(odet, det, "det", 'd', n, 1) < 0)
        goto fail;
    if (n >= NOGIL_MIN) {
        Py_BEGIN_ALLOW_THREADS
        moving_std_loop(ext->buf, w, n, sums->buf, det->buf);
        Py_END_ALLOW_THREADS
    } else {
        moving_std_loop(ext->buf, w, n, sums->buf, det->buf);
    }
    release_all(v, 3);
    Py_RETURN_NONE;
fail:
    release_all(v, 3);
    return NULL;
}

static PyMethodDef methods[] = {
    {"moving_std", moving_std, METH_VARARGS,
     "moving_std(ext (6, w + n), w, sums (6,) in/out, det (n,) out): the moving-variance detector's signal, the max "
     "per-axis moving std over the trailing w samples (variance.py's numpy operations, bit for bit)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_movingstd",
                                    "The moving-variance detector's signal, sample by sample.", -1, methods, NULL, NULL,
                                    NULL, NULL};

PyMODINIT_FUNC PyInit__movingstd(void)
{
    return PyModule_Create(&module);
}
