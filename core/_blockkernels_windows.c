/* window_sums: the windows' means, scatters and aux means from the block statistics. Part of the
 * _blockkernels extension (core/_blockkernels.c). */
#include "_blockkernels.h"

/* Sums over the blocks [ps, pe) of each window (fastdetect.windows_from_still): with d = m_b - r
 * (r: the window's first block mean, near every block of a still window, so the cancellation is
 * harmless) the window mean is r + Σ d / n, its scatter Σ_b W_b + B (Σ d dᵀ - (Σ d)(Σ d)ᵀ / n)
 * (the within-block scatters plus the blocks' spread about the window mean, fastdetect's
 * docstring), the aux means Σ aux / n; n blocks, B samples each. */
BLOCKKERNELS_INTERNAL PyObject *window_sums(PyObject *self, PyObject *args)
{
    PyObject *omean, *oscat, *oaux, *ops, *ope, *owm, *ows, *owa;
    Py_ssize_t B;
    if (!PyArg_ParseTuple(args, "OOOOOnOOO:window_sums", &omean, &oscat, &oaux, &ops, &ope, &B, &owm, &ows, &owa))
        return NULL;
    Py_buffer v[8] = {{0}};
    Py_buffer *mean = v, *scat = v + 1, *aux = v + 2, *ps = v + 3, *pe = v + 4, *wm = v + 5, *ws = v + 6, *wa = v + 7;
    if (get_contiguous(ops, ps, "ps", 'q', -1, 0) < 0)
        goto fail;
    Py_ssize_t m = ps->len / 8;
    if (get_contiguous(omean, mean, "mean", 'd', -1, 0) < 0 || get_contiguous(ope, pe, "pe", 'q', m, 0) < 0)
        goto fail;
    Py_ssize_t nb = mean->len / 24;
    if (mean->len % 24 || mean->ndim != 2 || mean->shape[0] != 3) {
        PyErr_SetString(PyExc_ValueError, "mean must be (3, blocks)");
        goto fail;
    }
    if (get_contiguous(oscat, scat, "scatter", 'f', 6 * nb, 0) < 0 || get_contiguous(oaux, aux, "aux", 'd', -1, 0) < 0)
        goto fail;
    Py_ssize_t k = nb ? aux->len / 8 / nb : 0;
    if (aux->len != k * nb * 8) {
        PyErr_Format(PyExc_ValueError, "aux must be (k, %zd)", nb);
        goto fail;
    }
    if (get_contiguous(owm, wm, "window_mean", 'd', 3 * m, 1) < 0 ||
        get_contiguous(ows, ws, "window_scatter", 'd', 6 * m, 1) < 0 ||
        get_contiguous(owa, wa, "window_aux", 'd', k * m, 1) < 0)
        goto fail;
    const long long *lo = ps->buf, *hi = pe->buf;
    for (Py_ssize_t w = 0; w < m; w++)
        if (!(0 <= lo[w] && lo[w] < hi[w] && hi[w] <= nb)) {
            PyErr_Format(PyExc_ValueError, "window %zd: blocks [%lld, %lld) are not a non-empty range of the %zd blocks",
                         w, lo[w], hi[w], nb);
            goto fail;
        }
    const double *mo = mean->buf, *ao = aux->buf;
    const float *so = scat->buf;
    double *om = wm->buf, *os = ws->buf, *oa = wa->buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t w = 0; w < m; w++) {
        const Py_ssize_t b0 = (Py_ssize_t)lo[w], b1 = (Py_ssize_t)hi[w];
        const double n = (double)(b1 - b0), r0 = mo[b0], r1 = mo[nb + b0], r2 = mo[2 * nb + b0];
        double a0 = 0, a1 = 0, a2 = 0, q00 = 0, q11 = 0, q22 = 0, q01 = 0, q02 = 0, q12 = 0, W[6] = {0};
        for (Py_ssize_t b = b0; b < b1; b++) {
            const double d0 = mo[b] - r0, d1 = mo[nb + b] - r1, d2 = mo[2 * nb + b] - r2;
            a0 += d0, a1 += d1, a2 += d2;
            q00 += d0 * d0, q11 += d1 * d1, q22 += d2 * d2, q01 += d0 * d1, q02 += d0 * d2, q12 += d1 * d2;
            for (int p = 0; p < 6; p++)
                W[p] += (double)so[p * nb + b];
        }
        const double q[6] = {q00, q11, q22, q01, q02, q12}, s[3] = {a0, a1, a2};
        om[w] = r0 + a0 / n, om[m + w] = r1 + a1 / n, om[2 * m + w] = r2 + a2 / n;
        for (int p = 0; p < 6; p++)
            os[p * m + w] = W[p] + (double)B * (q[p] - s[I6[p]] * s[J6[p]] / n);
        for (Py_ssize_t j = 0; j < k; j++) {
            double sa = 0.0;
            for (Py_ssize_t b = b0; b < b1; b++)
                sa += ao[j * nb + b];
            oa[j * m + w] = sa / n;
        }
    }
    Py_END_ALLOW_THREADS
    release_all(v, 8);
    Py_RETURN_NONE;
fail:
    release_all(v, 8);
    return NULL;
}
