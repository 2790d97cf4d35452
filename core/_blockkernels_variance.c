/* variance_chain: core.fastdetect.variance_still on the block statistics. Part of the _blockkernels
 * extension (core/_blockkernels.c). */
#include "_blockkernels.h"

/* variance_still on the block statistics, the numpy form's operations in its order: a = K⁻¹ (mean -
 * ref) and the per-axis within-block scatter w in g² (0 for an unusable block), their sums over
 * the trailing wb blocks as differences of running sums (np.cumsum from 0, kept for the last wb + 1
 * blocks only), the window's scatter s_w + B (s_aa - s_a s_a / wb), its variance / (n - 1) clipped
 * at 0, still when all three are below thr2 and no block of the window is unusable. */
#define VAR_RING 4097 /* running sums kept: windows up to 4096 blocks */

BLOCKKERNELS_INTERNAL PyObject *variance_chain(PyObject *self, PyObject *args)
{
    PyObject *omean, *ouse, *oscat, *oref, *okinv, *ostill, *otrace = Py_None;
    Py_ssize_t wb, B;
    double thr2;
    if (!PyArg_ParseTuple(args, "OOOOOnndO|O:variance_chain", &omean, &ouse, &oscat, &oref, &okinv, &wb, &B, &thr2,
                          &ostill, &otrace))
        return NULL;
    Py_buffer v[7] = {{0}};
    Py_buffer *mean = v, *use = v + 1, *scat = v + 2, *ref = v + 3, *kv = v + 4, *still = v + 5, *trace = v + 6;
    if (get_contiguous(ouse, use, "usable", '?', -1, 0) < 0)
        goto fail;
    Py_ssize_t nb = use->len;
    if (get_contiguous(omean, mean, "mean", 'd', 3 * nb, 0) < 0 ||
        get_contiguous(oscat, scat, "scatter", 'f', 6 * nb, 0) < 0 ||
        get_contiguous(oref, ref, "ref", 'd', 3, 0) < 0 || get_contiguous(okinv, kv, "kinv", 'd', 9, 0) < 0 ||
        get_contiguous(ostill, still, "still", '?', nb, 1) < 0)
        goto fail;
    if (wb < 1 || wb >= VAR_RING || B < 1) {
        PyErr_Format(PyExc_ValueError, "window of %zd blocks of %zd samples: need 1 to %d blocks", wb, B, VAR_RING - 1);
        goto fail;
    }
    if (otrace != Py_None && get_contiguous(otrace, trace, "trace", 'd', 3 * nb, 1) < 0)
        goto fail;
    const double *mo = mean->buf, *r = ref->buf, *K = kv->buf;
    const float *so = scat->buf;
    const char *uo = use->buf;
    char *out = still->buf;
    double *tr = otrace != Py_None ? trace->buf : NULL;
    double (*ring)[9] = PyMem_RawMalloc(sizeof(double[9]) * VAR_RING);
    Py_ssize_t *bad = PyMem_RawMalloc(sizeof(Py_ssize_t) * VAR_RING);
    if (ring == NULL || bad == NULL) {
        PyMem_RawFree(ring), PyMem_RawFree(bad);
        PyErr_NoMemory();
        goto fail;
    }
    Py_BEGIN_ALLOW_THREADS
    double cv[3][6]; /* as in chain_run: zero coefficients' products add nothing to a finite sum */
    axis_scatter_coefficients(K, cv);
    const Py_ssize_t R = wb + 1;
    const double n1 = (double)(wb * B - 1), Bd = (double)B, wbd = (double)wb;
    double c[9] = {0}; /* running sums of a (3), a a (3), w (3) */
    Py_ssize_t nbad = 0;
    for (int q = 0; q < 9; q++)
        ring[0][q] = 0.0;
    bad[0] = 0;
    for (Py_ssize_t b = 0; b < nb; b++) {
        double x[9] = {0};
        if (uo[b]) {
            for (int j = 0; j < 3; j++) {
                double d = mo[j * nb + b] - r[j];
                for (int i = 0; i < 3; i++)
                    x[i] += K[3 * i + j] * d;
            }
            for (int i = 0; i < 3; i++) {
                x[3 + i] = x[i] * x[i];
                for (int p = 0; p < 6; p++)
                    x[6 + i] += cv[i][p] * (double)so[p * nb + b];
            }
        } else
            nbad++;
        const Py_ssize_t at = (b + 1) % R;
        for (int q = 0; q < 9; q++)
            ring[at][q] = c[q] = c[q] + x[q];
        bad[at] = nbad;
        out[b] = 0;
        if (b + 1 < wb)
            continue;
        const Py_ssize_t from = (b + 1 - wb) % R;
        int s = bad[at] - bad[from] == 0;
        for (int i = 0; i < 3; i++) {
            const double sa = ring[at][i] - ring[from][i], saa = ring[at][3 + i] - ring[from][3 + i],
                         sw = ring[at][6 + i] - ring[from][6 + i];
            double var = (sw + Bd * (saa - sa * sa / wbd)) / n1;
            var = var < 0.0 ? 0.0 : var; /* np.clip(var, 0, None) */
            s &= var < thr2;
            if (tr)
                tr[i * nb + b] = var;
        }
        out[b] = (char)s;
    }
    Py_END_ALLOW_THREADS
    PyMem_RawFree(ring);
    PyMem_RawFree(bad);
    release_all(v, 7);
    Py_RETURN_NONE;
fail:
    release_all(v, 7);
    return NULL;
}
