/* Compiled loops of the offline block detector (core/fastdetect.py).
 *
 * block_pass     one chunk of block_stats: per block of B samples the mean, the 6 scatter sums,
 *                the aux means and the usable flag, read straight from strided (e.g. memory-mapped
 *                record) fields, accumulated in float64.
 * lotters_chain  lotters_still on the block means: Lötters 1998 eq. 1-2 with the per-axis chains,
 *                the same float64 operations in the same order as the numpy/SciPy form it replaces
 *                (where the CPU has AVX2: four blocks, or the four channels' filters, per vector).
 * sosfilt        SciPy's sosfilt kernel (direct form II transposed), in place.
 * variance_chain variance_still on the block statistics, the numpy form's operations in order.
 * window_sums    the windows' means, scatters and aux means from the block statistics.
 *
 * Buffers come through the buffer protocol only (no numpy C API). Every length, format and
 * contiguity is checked before a loop runs; loops run without the GIL. Built with
 * -ffp-contract=off: no fused multiply-add, so every operation rounds as numpy's do.
 *
 * One extension built from one file per concern (core/_blockkernels.h: what they share):
 * _blockkernels_pass.c (block_pass), _blockkernels_lotters.c (lotters_chain, chain_lanes),
 * _blockkernels_variance.c (variance_chain), _blockkernels_windows.c (window_sums); this file holds
 * sosfilt and the module's method table.
 */
#include "_blockkernels.h"

/* ---- sosfilt ------------------------------------------------------------------------------ */

static PyObject *sosfilt(PyObject *self, PyObject *args)
{
    PyObject *osos, *ox, *ozi;
    if (!PyArg_ParseTuple(args, "OOO:sosfilt", &osos, &ox, &ozi))
        return NULL;
    Py_buffer v[3] = {{0}};
    Py_buffer *sos = v, *x = v + 1, *zi = v + 2;
    if (get_contiguous(osos, sos, "sos", 'd', -1, 0) < 0 || get_contiguous(ox, x, "x", 'd', -1, 1) < 0)
        goto fail;
    Py_ssize_t ns = sos->len / 48;
    if (sos->len % 48 || ns < 1) {
        PyErr_SetString(PyExc_ValueError, "sos must be (sections, 6) with at least one section");
        goto fail;
    }
    if (x->ndim != 2) {
        PyErr_Format(PyExc_ValueError, "x must be 2-D (signals, samples), got %d-D", x->ndim);
        goto fail;
    }
    Py_ssize_t signals = x->shape[0], n = x->shape[1];
    if (get_contiguous(ozi, zi, "zi", 'd', signals * ns * 2, 1) < 0)
        goto fail;
    double *xs = x->buf, *z = zi->buf;
    const double *c = sos->buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < signals; i++) {
        double *zs = z + i * ns * 2, *row = xs + i * n;
        for (Py_ssize_t k = 0; k < n; k++)
            row[k] = cascade(c, zs, (int)ns, row[k]);
    }
    Py_END_ALLOW_THREADS
    release_all(v, 3);
    Py_RETURN_NONE;
fail:
    release_all(v, 3);
    return NULL;
}

static PyMethodDef methods[] = {
    {"block_pass", block_pass, METH_VARARGS,
     "block_pass(x0, x1, x2, t, aux, block_n, b0, max_step, mean, scatter, aux_mean, usable)\n"
     "Block statistics of one chunk (see core.fastdetect.block_stats), written to blocks [b0, b0 + m)."},
    {"lotters_chain", lotters_chain, METH_VARARGS,
     "lotters_chain(mean, usable, scatter, offset, kinv, sos_hp, sos_lp, rest_hp, channels, threshold,\n"
     "              var_limit, b0, still, trace=None, first=0, gate=True)\nStill blocks from b0 on by Lötters' detector "
     "(core.fastdetect.lotters_still),\nfiltering channels [first, channels) of (|a|, x, y, z), the within-block std gate when gate;\n"
     "trace (7, nb) float64, optional: each channel's detection signal and the per-axis within-block scatter [g²];\n"
     "vector=False: one block and one channel at a time even where the CPU has AVX2 (the same bits)."},
    {"chain_lanes", chain_lanes, METH_NOARGS,
     "chain_lanes() -> True when lotters_chain runs the four channels of the default filters (order 2) in the\n"
     "lanes of one vector (AVX2): then one call beats two half calls on two threads."},
    {"variance_chain", variance_chain, METH_VARARGS,
     "variance_chain(mean, usable, scatter, ref, kinv, window_blocks, block_n, threshold2, still, trace=None)\n"
     "Still blocks by the per-axis moving variance (core.fastdetect.variance_still); trace (3, nb): the variances."},
    {"sosfilt", sosfilt, METH_VARARGS,
     "sosfilt(sos, x, zi)\nx (signals, n) and zi (signals, sections, 2) float64, filtered in place as scipy's sosfilt."},
    {"window_sums", window_sums, METH_VARARGS,
     "window_sums(mean, scatter, aux, ps, pe, block_n, window_mean, window_scatter, window_aux)\n"
     "Mean (3, m), scatter (6, m) and aux means (k, m) of the samples of block ranges [ps, pe) (int64)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_blockkernels",
                                    "Compiled loops of core.fastdetect (no numpy C API).", -1, methods,
                                    NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__blockkernels(void)
{
    return PyModule_Create(&module);
}
