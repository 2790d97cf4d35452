/* lotters_chain: core.fastdetect.lotters_still on the block means, Lötters 1998 eq. 1-2 with the per-axis
 * chains, the same float64 operations in the same order as the numpy/SciPy form it replaces (where the CPU
 * has AVX2: four blocks, or the four channels' filters, per vector). Part of the _blockkernels extension
 * (core/_blockkernels.c). */
#include "_blockkernels.h"

typedef struct {
    const double *mean, *o, *K, *sos_hp, *sos_lp, *rest;
    const float *scatter;
    const char *usable;
    char *still;
    double *trace; /* NULL, or (7, nb): each channel's detection signal, the per-axis scatter [g²] */
    Py_ssize_t nb, b0;
    double thr, var_limit;
} Chain;

#define CHAIN_CHUNK 1024 /* blocks per pass of chain_run (its signals stay in the L1 cache) */

/* What each block decides on its own: u[1..3] = K⁻¹ (mean - o) (fastdetect._in_g: column by column from
 * +0.0), an unusable block held at the last usable one (`last`); u[0] = |a| (eq. 1) when lo == 0; the
 * block's still flag: usable and, with `gate`, the within-block std gate (what the block means cannot see):
 * per axis Σ_p c_ip W_p from +0.0 in p order (_axis_var_g and _in_g skip zero coefficients; adding their ±0
 * products instead gives the same bits: a sum started at +0.0 never becomes -0.0, and x + ±0 = x otherwise,
 * for the finite means and scatters of usable blocks). */
static inline __attribute__((always_inline)) void block_in_g(const Chain *a, Py_ssize_t b, double g[3])
{
    const double *K = a->K;
    double g0 = 0.0, g1 = 0.0, g2 = 0.0; /* in registers, not an array the loop reloads */
#pragma GCC unroll 3
    for (int j = 0; j < 3; j++) {
        double d = a->mean[j * a->nb + b] - a->o[j];
        g0 += K[j] * d, g1 += K[3 + j] * d, g2 += K[6 + j] * d;
    }
    g[0] = g0, g[1] = g1, g[2] = g2;
}

static inline __attribute__((always_inline)) double block_norm(double u1, double u2, double u3)
{
    double v = u1 * u1;
    v += u2 * u2;
    v += u3 * u3;
    return sqrt(v);
}

static inline __attribute__((always_inline)) int block_gate(const Chain *a, Py_ssize_t b, const double cv[3][6])
{
    const Py_ssize_t nb = a->nb;
    double w[3] = {0.0, 0.0, 0.0}; /* the three axes' sums side by side (their additions overlap) */
    for (int p = 0; p < 6; p++) {
        const double sp = (double)a->scatter[p * nb + b];
        w[0] += cv[0][p] * sp, w[1] += cv[1][p] * sp, w[2] += cv[2][p] * sp;
    }
    if (a->trace)
        for (int i = 0; i < 3; i++)
            a->trace[(4 + i) * nb + b] = w[i];
    return w[0] < a->var_limit && w[1] < a->var_limit && w[2] < a->var_limit;
}

/* blocks [b_lo, b_lo + n) one at a time */
static inline __attribute__((always_inline)) void chain_blocks(const Chain *a, Py_ssize_t b_lo, Py_ssize_t n, int lo,
                                                               int gate, const double cv[3][6],
                                                               double u[4][CHAIN_CHUNK], double last[3])
{
    for (Py_ssize_t k = 0; k < n; k++) {
        const Py_ssize_t b = b_lo + k;
        int ok = a->usable[b] != 0;
        if (ok || b == a->b0)
            block_in_g(a, b, last);
        u[1][k] = last[0], u[2][k] = last[1], u[3][k] = last[2];
        if (lo == 0)
            u[0][k] = block_norm(u[1][k], u[2][k], u[3][k]);
        if (gate)
            ok &= block_gate(a, b, cv);
        a->still[b] = (char)ok;
    }
}

#if defined(__GNUC__) && defined(__x86_64__)
#include <immintrin.h>
#define CHAIN_LANES 1

/* chain_blocks on four neighbouring blocks at a time, one per lane of a 256-bit vector (means and scatters
 * are channel-major: four blocks are one load). Each lane does chain_blocks' operations in its order, so
 * every block's bits are the same: K⁻¹ (mean - o) of every block, then the hold rule block by block (an
 * unusable block's own values dropped), then |a| and the gate on the held values; the blocks past the last
 * whole four through chain_blocks' functions. */
__attribute__((target("avx2"))) static void chain_blocks_lanes(const Chain *a, Py_ssize_t b_lo, Py_ssize_t n, int lo,
                                                               int gate, const double cv[3][6],
                                                               double u[4][CHAIN_CHUNK], double last[3])
{
    const Py_ssize_t nb = a->nb, n4 = n - n % 4;
    const double *K = a->K;
    const __m256d zero = _mm256_setzero_pd(), lim = _mm256_set1_pd(a->var_limit);
    for (Py_ssize_t k = 0; k < n4; k += 4) {
        __m256d g0 = zero, g1 = zero, g2 = zero;
        for (int j = 0; j < 3; j++) {
            const __m256d d = _mm256_sub_pd(_mm256_loadu_pd(a->mean + j * nb + b_lo + k), _mm256_set1_pd(a->o[j]));
            g0 = _mm256_add_pd(g0, _mm256_mul_pd(_mm256_set1_pd(K[j]), d));
            g1 = _mm256_add_pd(g1, _mm256_mul_pd(_mm256_set1_pd(K[3 + j]), d));
            g2 = _mm256_add_pd(g2, _mm256_mul_pd(_mm256_set1_pd(K[6 + j]), d));
        }
        _mm256_storeu_pd(u[1] + k, g0), _mm256_storeu_pd(u[2] + k, g1), _mm256_storeu_pd(u[3] + k, g2);
    }
    for (Py_ssize_t k = n4; k < n; k++) {
        double g[3];
        block_in_g(a, b_lo + k, g);
        u[1][k] = g[0], u[2][k] = g[1], u[3][k] = g[2];
    }
    for (Py_ssize_t k = 0; k < n; k++) {
        if (a->usable[b_lo + k] || b_lo + k == a->b0)
            last[0] = u[1][k], last[1] = u[2][k], last[2] = u[3][k];
        else
            u[1][k] = last[0], u[2][k] = last[1], u[3][k] = last[2];
    }
    for (Py_ssize_t k = 0; k < n4; k += 4) {
        const Py_ssize_t b = b_lo + k;
        if (lo == 0) {
            const __m256d x = _mm256_loadu_pd(u[1] + k), y = _mm256_loadu_pd(u[2] + k), z = _mm256_loadu_pd(u[3] + k);
            __m256d v = _mm256_mul_pd(x, x);
            v = _mm256_add_pd(v, _mm256_mul_pd(y, y));
            v = _mm256_add_pd(v, _mm256_mul_pd(z, z));
            _mm256_storeu_pd(u[0] + k, _mm256_sqrt_pd(v));
        }
        int ok = 0xf;
        if (gate) {
            __m256d w[3] = {zero, zero, zero};
            for (int p = 0; p < 6; p++) {
                const __m256d sp = _mm256_cvtps_pd(_mm_loadu_ps(a->scatter + p * nb + b));
                for (int i = 0; i < 3; i++)
                    w[i] = _mm256_add_pd(w[i], _mm256_mul_pd(_mm256_set1_pd(cv[i][p]), sp));
            }
            for (int i = 0; i < 3; i++) {
                ok &= _mm256_movemask_pd(_mm256_cmp_pd(w[i], lim, _CMP_LT_OQ));
                if (a->trace)
                    _mm256_storeu_pd(a->trace + (4 + i) * nb + b, w[i]);
            }
        }
        for (int l = 0; l < 4; l++)
            a->still[b + l] = (char)((a->usable[b + l] != 0) & (ok >> l));
    }
    for (Py_ssize_t k = n4; k < n; k++) {
        int ok = a->usable[b_lo + k] != 0;
        if (lo == 0)
            u[0][k] = block_norm(u[1][k], u[2][k], u[3][k]);
        if (gate)
            ok &= block_gate(a, b_lo + k, cv);
        a->still[b_lo + k] = (char)ok;
    }
}

/* chain_run for the default (order 2, norm and axes, gate) where the CPU has AVX2: the four channels'
 * filters in the four lanes of one vector, each lane cascade()'s operations on its channel in its order
 * (so each channel's signal has the same bits), one vector operation for the four channels' dependent
 * chains instead of four scalar ones. */
__attribute__((target("avx2"))) static void chain_run_lanes4(const Chain *a)
{
    const Py_ssize_t nb = a->nb;
    const double *K = a->K;
    double cv[3][6];
    axis_scatter_coefficients(K, cv);
    const double *h = a->sos_hp, *l = a->sos_lp;
    const __m256d h0 = _mm256_set1_pd(h[0]), h1 = _mm256_set1_pd(h[1]), h2 = _mm256_set1_pd(h[2]),
                  h4 = _mm256_set1_pd(h[4]), h5 = _mm256_set1_pd(h[5]);
    const __m256d l0 = _mm256_set1_pd(l[0]), l1 = _mm256_set1_pd(l[1]), l2 = _mm256_set1_pd(l[2]),
                  l4 = _mm256_set1_pd(l[4]), l5 = _mm256_set1_pd(l[5]);
    const __m256d thr = _mm256_set1_pd(a->thr), sign = _mm256_set1_pd(-0.0);
    __m256d zh0 = _mm256_setzero_pd(), zh1 = zh0, zl0 = zh0, zl1 = zh0;
    double last[3] = {0, 0, 0}, u[4][CHAIN_CHUNK], lane[4];
    for (Py_ssize_t b_lo = a->b0; b_lo < nb; b_lo += CHAIN_CHUNK) {
        const Py_ssize_t n = nb - b_lo < CHAIN_CHUNK ? nb - b_lo : CHAIN_CHUNK;
        chain_blocks_lanes(a, b_lo, n, 0, 1, cv, u, last);
        if (b_lo == a->b0) { /* the high-pass at rest on the first block (sos_rest_state x first value) */
            const __m256d x0 = _mm256_set_pd(u[3][0], u[2][0], u[1][0], u[0][0]);
            zh0 = _mm256_mul_pd(_mm256_set1_pd(a->rest[0]), x0);
            zh1 = _mm256_mul_pd(_mm256_set1_pd(a->rest[1]), x0);
        }
        for (Py_ssize_t k = 0; k < n; k++) {
            const __m256d x = _mm256_set_pd(u[3][k], u[2][k], u[1][k], u[0][k]);
            /* y = b0 x + z0;  z0 = b1 x - a1 y + z1;  z1 = b2 x - a2 y (cascade, one section) */
            __m256d y = _mm256_add_pd(_mm256_mul_pd(h0, x), zh0);
            zh0 = _mm256_add_pd(_mm256_sub_pd(_mm256_mul_pd(h1, x), _mm256_mul_pd(h4, y)), zh1);
            zh1 = _mm256_sub_pd(_mm256_mul_pd(h2, x), _mm256_mul_pd(h5, y));
            const __m256d r = _mm256_andnot_pd(sign, y); /* the rectifier: fabs */
            y = _mm256_add_pd(_mm256_mul_pd(l0, r), zl0);
            zl0 = _mm256_add_pd(_mm256_sub_pd(_mm256_mul_pd(l1, r), _mm256_mul_pd(l4, y)), zl1);
            zl1 = _mm256_sub_pd(_mm256_mul_pd(l2, r), _mm256_mul_pd(l5, y));
            const int s = _mm256_movemask_pd(_mm256_cmp_pd(y, thr, _CMP_LT_OQ)) == 0xf;
            if (a->trace) {
                _mm256_storeu_pd(lane, y);
                for (int c = 0; c < 4; c++)
                    a->trace[c * nb + b_lo + k] = lane[c];
            }
            a->still[b_lo + k] &= (char)s;
        }
    }
}

static int chain_has_lanes(void)
{
    return __builtin_cpu_supports("avx2");
}
#else
static int chain_has_lanes(void)
{
    return 0;
}
#endif

/* Two passes per chunk of blocks: first what each block decides on its own (chain_blocks, or
 * chain_blocks_lanes where the CPU has AVX2), then the filters, whose states are the only thing carried from
 * block to block (all channels interleaved, so their dependency chains overlap). Channels [lo, hi) of (|a|,
 * x, y, z) are filtered, the gate applied when `gate`: two calls on disjoint channels (e.g. [0, 2) and [2, 4)
 * with the gate) give each channel's signal and each block's decision the bits of one call on all four,
 * whose still is the AND of the two. */
static inline __attribute__((always_inline)) void chain_run(const Chain *a, int lo, int hi, int ns_hp, int ns_lp,
                                                            int gate, int lanes)
{
    const Py_ssize_t nb = a->nb;
    const double *K = a->K;
    double cv[3][6];
    axis_scatter_coefficients(K, cv);
    double zh[4][2 * MAX_SECTIONS] = {{0}}, zl[4][2 * MAX_SECTIONS] = {{0}}, last[3] = {0, 0, 0};
    double u[4][CHAIN_CHUNK];
    for (Py_ssize_t b_lo = a->b0; b_lo < nb; b_lo += CHAIN_CHUNK) {
        const Py_ssize_t n = nb - b_lo < CHAIN_CHUNK ? nb - b_lo : CHAIN_CHUNK;
#ifdef CHAIN_LANES
        if (lanes)
            chain_blocks_lanes(a, b_lo, n, lo, gate, cv, u, last);
        else
#endif
            chain_blocks(a, b_lo, n, lo, gate, cv, u, last);
        if (b_lo == a->b0) /* the high-pass at rest on the first block (sos_rest_state x first value) */
            for (int c = lo; c < hi; c++)
                for (int k = 0; k < 2 * ns_hp; k++)
                    zh[c][k] = a->rest[k] * u[c][0];
        for (Py_ssize_t k = 0; k < n; k++) {
            int s = 1;
#pragma GCC unroll 4 /* the channels' filters interleaved: their dependency chains overlap */
            for (int c = lo; c < hi; c++) { /* high-pass, rectifier, low-pass (eq. 2), per channel */
                double y = fabs(cascade(a->sos_hp, zh[c], ns_hp, u[c][k]));
                y = cascade(a->sos_lp, zl[c], ns_lp, y);
                s &= y < a->thr;
                if (a->trace)
                    a->trace[c * nb + b_lo + k] = y;
            }
            a->still[b_lo + k] &= (char)s;
        }
    }
}

BLOCKKERNELS_INTERNAL PyObject *chain_lanes(PyObject *self, PyObject *unused)
{
    return PyBool_FromLong(chain_has_lanes());
}

BLOCKKERNELS_INTERNAL PyObject *lotters_chain(PyObject *self, PyObject *args)
{
    PyObject *omean, *ouse, *oscat, *oo, *okinv, *ohp, *olp, *orest, *ostill, *otrace = Py_None;
    int chans, lo = 0, gate = 1, vector = 1;
    double thr, var_limit;
    Py_ssize_t b0;
    if (!PyArg_ParseTuple(args, "OOOOOOOOiddnO|Oipp:lotters_chain", &omean, &ouse, &oscat, &oo, &okinv, &ohp, &olp,
                          &orest, &chans, &thr, &var_limit, &b0, &ostill, &otrace, &lo, &gate, &vector))
        return NULL;
    Py_buffer v[10] = {{0}};
    Py_buffer *mean = v, *use = v + 1, *scat = v + 2, *off = v + 3, *kv = v + 4, *hp = v + 5, *lp = v + 6,
              *rest = v + 7, *still = v + 8, *trace = v + 9;
    if (get_contiguous(ouse, use, "usable", '?', -1, 0) < 0)
        goto fail;
    Py_ssize_t nb = use->len;
    if (get_contiguous(omean, mean, "mean", 'd', 3 * nb, 0) < 0 ||
        get_contiguous(oscat, scat, "scatter", 'f', 6 * nb, 0) < 0 ||
        get_contiguous(oo, off, "offset", 'd', 3, 0) < 0 || get_contiguous(okinv, kv, "kinv", 'd', 9, 0) < 0 ||
        get_contiguous(ohp, hp, "sos_hp", 'd', -1, 0) < 0 || get_contiguous(olp, lp, "sos_lp", 'd', -1, 0) < 0 ||
        get_contiguous(ostill, still, "still", '?', nb, 1) < 0)
        goto fail;
    Py_ssize_t nhp = hp->len / 48, nlp = lp->len / 48;
    if (hp->len % 48 || lp->len % 48 || nhp < 1 || nlp < 1 || nhp > MAX_SECTIONS || nlp > MAX_SECTIONS) {
        PyErr_Format(PyExc_ValueError, "sos_hp and sos_lp must be (sections, 6) with 1 to %d sections", MAX_SECTIONS);
        goto fail;
    }
    if (get_contiguous(orest, rest, "rest_hp", 'd', 2 * nhp, 0) < 0)
        goto fail;
    if (chans < 1 || chans > 4) {
        PyErr_Format(PyExc_ValueError, "channels must be 1 (the norm) to 4 (norm and axes), got %d", chans);
        goto fail;
    }
    if (lo < 0 || lo >= chans) {
        PyErr_Format(PyExc_ValueError, "first channel %d outside the %d channels", lo, chans);
        goto fail;
    }
    if (b0 < 0 || b0 > nb) {
        PyErr_Format(PyExc_ValueError, "first block %zd outside the %zd blocks", b0, nb);
        goto fail;
    }
    if (otrace != Py_None && get_contiguous(otrace, trace, "trace", 'd', 7 * nb, 1) < 0)
        goto fail;
    double *tr = otrace != Py_None ? trace->buf : NULL;

    Chain ch = {mean->buf, off->buf, kv->buf, hp->buf, lp->buf, rest->buf, scat->buf, use->buf, still->buf, tr,
                nb, b0, thr, var_limit};
    const int lanes = vector && chain_has_lanes();
    Py_BEGIN_ALLOW_THREADS
    /* the default (order 2: one biquad each; norm and axes in one call or in two halves, or the norm
     * alone) with constant trip counts, so that the filter states live in registers; the same
     * operations as the general form */
#ifdef CHAIN_LANES
    if (nhp == 1 && nlp == 1 && chans == 4 && lo == 0 && gate && lanes)
        chain_run_lanes4(&ch);
    else
#endif
    if (nhp == 1 && nlp == 1 && chans == 4 && lo == 0 && gate)
        chain_run(&ch, 0, 4, 1, 1, 1, lanes);
    else if (nhp == 1 && nlp == 1 && chans == 2 && lo == 0 && !gate)
        chain_run(&ch, 0, 2, 1, 1, 0, lanes);
    else if (nhp == 1 && nlp == 1 && chans == 4 && lo == 2 && gate)
        chain_run(&ch, 2, 4, 1, 1, 1, lanes);
    else if (nhp == 1 && nlp == 1 && chans == 1 && lo == 0 && gate)
        chain_run(&ch, 0, 1, 1, 1, 1, lanes);
    else
        chain_run(&ch, lo, chans, (int)nhp, (int)nlp, gate, lanes);
    Py_END_ALLOW_THREADS
    release_all(v, 10);
    Py_RETURN_NONE;
fail:
    release_all(v, 10);
    return NULL;
}
