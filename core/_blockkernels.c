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
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>

#define MAX_SECTIONS 8 /* biquads per cascade (order 16): the state lives on the stack */

#include "_buffers.h"

/* ---- block_pass -------------------------------------------------------------------------- */

static const int I6[6] = {0, 1, 2, 0, 0, 1};
static const int J6[6] = {0, 1, 2, 1, 2, 2};

/* Per-axis within-block scatter in g² from the six second moments W_q (fastdetect._axis_var_g): Σ_q c_iq W_q,
 * c_iq = K⁻¹_iI K⁻¹_iJ, twice off the diagonal. */
static void axis_scatter_coefficients(const double *K, double cv[3][6])
{
    for (int i = 0; i < 3; i++)
        for (int p = 0; p < 6; p++)
            cv[i][p] = K[3 * i + I6[p]] * K[3 * i + J6[p]] * (I6[p] == J6[p] ? 1.0 : 2.0);
}

/* One chunk of m blocks of B samples: the three channels x (strides sx), the times t (stride st,
 * t[-1] readable unless `first`: the recording's first sample has no predecessor), outputs in
 * blocks [col, col + m) of rows nb apart. */
typedef struct {
    const char *x[3], *t;
    Py_ssize_t sx[3], st, B, m, nb, col;
    int first;
    double max_step;
    double *mean;
    float *scatter;
    char *usable;
} Chunk;

/* The block's sums as fastdetect.block_stats defines them: d = x - x[first] (a nearby reference
 * keeps the float64 sums exact to rounding), s = Σ d, q = Σ d_i d_j for the pairs (0,0) (1,1) (2,2)
 * (0,1) (0,2) (1,2); mean = x[first] + s / B, scatter = q - s_i s_j / B. In the same loop, the
 * step into each sample must lie in (0, max_step] (NaN fails). A non-finite sample makes its
 * sums non-finite (x * 0 != 0 then), so the finiteness test is on the sums.
 *
 * Two forms, the same operations on each block in the same order: chunk_rows_* any strides, one
 * block at a time; chunk_pairs_* when t and the channels share one stride (the rows of a
 * structured record), two neighbouring blocks at once, one per lane of a v2d: each lane's sums run
 * over its own block's samples in order, so each block's bits are the one-block form's; the lanes
 * only let the two blocks' additions overlap (each sum is a chain of dependent adds, ~3 cycles
 * each, and one block's 13 adds a sample need more than the adder's two ports). */
typedef double v2d __attribute__((vector_size(16)));
typedef int64_t v2l __attribute__((vector_size(16))); /* the lanes' compare masks (0 or -1) */
typedef float v2f __attribute__((vector_size(8)));

#define DEFINE_CHUNK_ROWS(NAME, T)                                                                  \
    static void NAME(const Chunk *c)                                                                \
    {                                                                                               \
        const Py_ssize_t B = c->B, nb = c->nb, s0 = c->sx[0], s1 = c->sx[1], s2 = c->sx[2];           \
        const double inv_B = 1.0 / (double)B, max_step = c->max_step;                               \
        const char *p0 = c->x[0], *p1 = c->x[1], *p2 = c->x[2], *tp = c->t;                         \
        double prev = c->first ? LOAD(double, tp) - 0.5 * max_step : LOAD(double, (tp - c->st)); \
        for (Py_ssize_t b = 0; b < c->m; b++) {                                                     \
            const double r0 = LOAD(T, p0), r1 = LOAD(T, p1), r2 = LOAD(T, p2);             \
            const v2d r01 = {r0, r1};                                                               \
            /* channels 0 and 1 side by side in a v2d, each lane its own sums in order: (a0, a1),  \
             * (q00, q11), (q02, q12) = Σ (d0, d1) d2; a2, q22, q01 alone */                        \
            v2d a01 = {0, 0}, q0011 = {0, 0}, q0212 = {0, 0};                                       \
            double a2 = 0, q22 = 0, q01 = 0;                                                        \
            int ok = 1;                                                                             \
            for (Py_ssize_t k = 0; k < B; k++) {                                                    \
                const v2d d01 = (v2d){LOAD(T, p0), LOAD(T, p1)} - r01;                        \
                const double d2 = (double)LOAD(T, p2) - r2;                                      \
                const double now = LOAD(double, tp), dt = now - prev;                            \
                p0 += s0, p1 += s1, p2 += s2, tp += c->st;                                          \
                a01 += d01, a2 += d2;                                                               \
                q0011 += d01 * d01, q22 += d2 * d2;                                                 \
                q01 += d01[0] * d01[1], q0212 += d01 * (v2d){d2, d2};                               \
                ok &= (dt > 0.0) & (dt <= max_step);                                                \
                prev = now;                                                                         \
            }                                                                                       \
            const double a0 = a01[0], a1 = a01[1], q00 = q0011[0], q11 = q0011[1];                  \
            const double q02 = q0212[0], q12 = q0212[1];                                            \
            const double m0 = a0 * inv_B, m1 = a1 * inv_B, m2 = a2 * inv_B;                         \
            const double w[6] = {q00 - a0 * m0, q11 - a1 * m1, q22 - a2 * m2,                       \
                                 q01 - a0 * m1, q02 - a0 * m2, q12 - a1 * m2};                      \
            double *mo = c->mean + c->col + b;                                                      \
            float *so = c->scatter + c->col + b;                                                    \
            mo[0] = r0 + m0, mo[nb] = r1 + m1, mo[2 * nb] = r2 + m2;                                \
            double all = mo[0] + mo[nb] + mo[2 * nb];                                               \
            for (int p = 0; p < 6; p++) {                                                           \
                so[p * nb] = (float)w[p];                                                           \
                all += w[p];                                                                        \
            }                                                                                       \
            c->usable[c->col + b] = (char)(ok & (all * 0.0 == 0.0));                                \
        }                                                                                           \
    }

DEFINE_CHUNK_ROWS(chunk_rows_f, float)
DEFINE_CHUNK_ROWS(chunk_rows_d, double)


/* Blocks [0, m - m % 2) two at a time (lane 0: block b, lane 1: block b + 1), every field read at
 * its byte offset from t's in the row (one stride S). Per lane the operations of chunk_rows_*. */
#define DEFINE_CHUNK_PAIRS(NAME, T)                                                                 \
    static void NAME(const Chunk *c)                                                                \
    {                                                                                               \
        const Py_ssize_t B = c->B, nb = c->nb, S = c->st, BS = B * S;                               \
        const Py_ssize_t o0 = c->x[0] - c->t, o1 = c->x[1] - c->t, o2 = c->x[2] - c->t;             \
        const v2d inv_B = {1.0 / (double)B, 1.0 / (double)B}, max_step = {c->max_step, c->max_step}; \
        const v2d zero = {0.0, 0.0};                                                                \
        for (Py_ssize_t b = 0; b + 1 < c->m; b += 2) {                                              \
            const char *ra = c->t + b * BS, *rb = ra + BS;                                          \
            const v2d r0 = {LOAD(T, (ra + o0)), LOAD(T, (rb + o0))};                          \
            const v2d r1 = {LOAD(T, (ra + o1)), LOAD(T, (rb + o1))};                          \
            const v2d r2 = {LOAD(T, (ra + o2)), LOAD(T, (rb + o2))};                          \
            v2d prev = {b == 0 && c->first ? LOAD(double, ra) - 0.5 * c->max_step               \
                                            : LOAD(double, (ra - S)), LOAD(double, (rb - S))};  \
            v2d a0 = zero, a1 = zero, a2 = zero, q00 = zero, q11 = zero, q22 = zero, q01 = zero,      \
                q02 = zero, q12 = zero;                                                             \
            v2l good = {0, 0}; /* minus one per step above 0, one per step up to max_step: ok at 2 B */ \
            for (Py_ssize_t k = 0; k < B; k++, ra += S, rb += S) {                                  \
                const v2d d0 = (v2d){LOAD(T, (ra + o0)), LOAD(T, (rb + o0))} - r0;             \
                const v2d d1 = (v2d){LOAD(T, (ra + o1)), LOAD(T, (rb + o1))} - r1;             \
                const v2d d2 = (v2d){LOAD(T, (ra + o2)), LOAD(T, (rb + o2))} - r2;             \
                const v2d now = {LOAD(double, ra), LOAD(double, rb)}, dt = now - prev;        \
                a0 += d0, a1 += d1, a2 += d2;                                                       \
                q00 += d0 * d0, q11 += d1 * d1, q22 += d2 * d2;                                     \
                q01 += d0 * d1, q02 += d0 * d2, q12 += d1 * d2;                                     \
                good += (dt > zero) + (dt <= max_step); /* mask lanes: -1 true, 0 false (NaN) */     \
                prev = now;                                                                         \
            }                                                                                       \
            const v2d m0 = a0 * inv_B, m1 = a1 * inv_B, m2 = a2 * inv_B;                            \
            const v2d w[6] = {q00 - a0 * m0, q11 - a1 * m1, q22 - a2 * m2,                          \
                              q01 - a0 * m1, q02 - a0 * m2, q12 - a1 * m2};                         \
            const v2d mean[3] = {r0 + m0, r1 + m1, r2 + m2};                                        \
            v2d all = mean[0] + mean[1];                                                            \
            all += mean[2];                                                                         \
            for (int p = 0; p < 6; p++)                                                             \
                all += w[p];                                                                        \
            const v2l use = (good == -2 * B) & (all * zero == zero);                                \
            const Py_ssize_t at = c->col + b; /* both lanes' outputs side by side */                \
            for (int j = 0; j < 3; j++)                                                             \
                memcpy(c->mean + j * nb + at, &mean[j], sizeof(v2d));                               \
            for (int p = 0; p < 6; p++) {                                                           \
                const v2f f = __builtin_convertvector(w[p], v2f); /* (float) per lane */            \
                memcpy(c->scatter + p * nb + at, &f, sizeof(v2f));                                  \
            }                                                                                       \
            c->usable[at] = (char)(use[0] != 0), c->usable[at + 1] = (char)(use[1] != 0);           \
        }                                                                                           \
    }

DEFINE_CHUNK_PAIRS(chunk_pairs_f, float)
DEFINE_CHUNK_PAIRS(chunk_pairs_d, double)

/* Rows of one stride (a structured record's fields): the blocks in pairs, an odd last one alone
 * (its rows after the paired ones, the row before them in t). */
static void record_chunk(const Chunk *c, char kind)
{
    const Py_ssize_t paired = c->m - c->m % 2, skip = paired * c->B;
    Chunk tail = *c;
    tail.t += skip * c->st, tail.first = 0, tail.m = c->m - paired, tail.col += paired;
    for (int j = 0; j < 3; j++)
        tail.x[j] += skip * c->sx[j];
    if (kind == 'f') {
        chunk_pairs_f(c);
        chunk_rows_f(&tail);
    } else {
        chunk_pairs_d(c);
        chunk_rows_d(&tail);
    }
}

static PyObject *block_pass(PyObject *self, PyObject *args)
{
    PyObject *ox[3], *ot, *oaux, *omean, *oscat, *oam, *ouse;
    Py_ssize_t B, b0;
    double max_step;
    if (!PyArg_ParseTuple(args, "OOOOOnndOOOO:block_pass", &ox[0], &ox[1], &ox[2], &ot, &oaux, &B, &b0,
                          &max_step, &omean, &oscat, &oam, &ouse))
        return NULL;
    Py_buffer v[9] = {{0}};
    Py_buffer *x = v, *t = v + 3, *aux = v + 4, *mean = v + 5, *scat = v + 6, *am = v + 7, *use = v + 8;
    static const char *xname[3] = {"channel 0", "channel 1", "channel 2"};
    for (int c = 0; c < 3; c++)
        if (get_strided(ox[c], &x[c], xname[c], "fd", 1) < 0)
            goto fail;
    char kind = kind_of(&x[0]);
    Py_ssize_t L = x[0].shape[0];
    if (kind_of(&x[1]) != kind || kind_of(&x[2]) != kind || x[1].shape[0] != L || x[2].shape[0] != L) {
        PyErr_SetString(PyExc_ValueError, "the three channels must have one length and one float type");
        goto fail;
    }
    if (B < 1 || L % B != 0) {
        PyErr_Format(PyExc_ValueError, "block_n must be >= 1 and divide the chunk length %zd, got %zd", L, B);
        goto fail;
    }
    Py_ssize_t m = L / B;
    if (get_strided(ot, t, "t", "d", 1) < 0)
        goto fail;
    Py_ssize_t t_off = t->shape[0] - L; /* 1: t starts with the sample before the chunk */
    if (t_off != 0 && t_off != 1) {
        PyErr_Format(PyExc_ValueError, "t must hold the chunk's %zd times (or one more before them), got %zd", L,
                     t->shape[0]);
        goto fail;
    }
    Py_ssize_t k_aux = 0, aux_s1 = 0;
    if (oaux != Py_None) {
        if (get_strided(oaux, aux, "aux", "d", 2) < 0)
            goto fail;
        k_aux = aux->ndim == 2 ? aux->shape[1] : 1;
        aux_s1 = aux->ndim == 2 ? aux->strides[1] : 0;
        if (aux->shape[0] != L) {
            PyErr_Format(PyExc_ValueError, "aux must have the chunk's %zd rows, got %zd", L, aux->shape[0]);
            goto fail;
        }
    }
    if (get_contiguous(ouse, use, "usable", '?', -1, 1) < 0)
        goto fail;
    Py_ssize_t nb = use->len;
    if (get_contiguous(omean, mean, "mean", 'd', 3 * nb, 1) < 0 ||
        get_contiguous(oscat, scat, "scatter", 'f', 6 * nb, 1) < 0 ||
        get_contiguous(oam, am, "aux_mean", 'd', k_aux * nb, 1) < 0)
        goto fail;
    if (b0 < 0 || b0 > nb - m) {
        PyErr_Format(PyExc_ValueError, "blocks [%zd, %zd) lie outside the %zd output blocks", b0, b0 + m, nb);
        goto fail;
    }
    if (m == 0)
        goto done;

    Chunk c = {{x[0].buf, x[1].buf, x[2].buf}, AT(*t, t_off), {x[0].strides[0], x[1].strides[0], x[2].strides[0]},
               t->strides[0], B, m, nb, b0, t_off == 0, max_step, mean->buf, scat->buf, use->buf};
    double *ao = am->buf;
    Py_BEGIN_ALLOW_THREADS
    if (x[0].strides[0] == t->strides[0] && x[1].strides[0] == t->strides[0] && x[2].strides[0] == t->strides[0] &&
        m > 1)
        record_chunk(&c, kind);
    else if (kind == 'f')
        chunk_rows_f(&c);
    else
        chunk_rows_d(&c);
    for (Py_ssize_t a = 0; a < k_aux; a++) /* aux block means (numpy: aux.reshape(m, B, k).mean(axis=1)) */
        for (Py_ssize_t b = 0; b < m; b++) {
            double sa = 0.0;
            for (Py_ssize_t k = 0; k < B; k++)
                sa += LOAD(double, (AT(*aux, b * B + k) + a * aux_s1));
            double ma = sa / (double)B;
            ao[a * nb + b0 + b] = ma;
            if (!isfinite(ma))
                c.usable[b0 + b] = 0;
        }
    Py_END_ALLOW_THREADS
done:
    release_all(v, 9);
    Py_RETURN_NONE;
fail:
    release_all(v, 9);
    return NULL;
}

/* ---- the Lötters chain ------------------------------------------------------------------- */

/* One sample through a cascade of biquads in direct form II transposed, exactly as SciPy's
 * _sosfilt_float (scipy/signal/_sosfilt.pyx) writes each operation:
 *   y = b0 x + z0;  z0 = b1 x - a1 y + z1;  z1 = b2 x - a2 y   (sos rows b0 b1 b2 a0 a1 a2, a0 = 1) */
static inline __attribute__((always_inline)) double cascade(const double *sos, double *z, int ns, double x)
{
    for (int s = 0; s < ns; s++) {
        const double *c = sos + 6 * s;
        double y = c[0] * x + z[2 * s];
        z[2 * s] = c[1] * x - c[4] * y + z[2 * s + 1];
        z[2 * s + 1] = c[2] * x - c[5] * y;
        x = y;
    }
    return x;
}

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

static PyObject *chain_lanes(PyObject *self, PyObject *unused)
{
    return PyBool_FromLong(chain_has_lanes());
}

static PyObject *lotters_chain(PyObject *self, PyObject *args)
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

/* ---- the moving-variance detector ------------------------------------------------------- */

/* variance_still on the block statistics, the numpy form's operations in its order: a = K⁻¹ (mean -
 * ref) and the per-axis within-block scatter w in g² (0 for an unusable block), their sums over
 * the trailing wb blocks as differences of running sums (np.cumsum from 0, kept for the last wb + 1
 * blocks only), the window's scatter s_w + B (s_aa - s_a s_a / wb), its variance / (n - 1) clipped
 * at 0, still when all three are below thr2 and no block of the window is unusable. */
#define VAR_RING 4097 /* running sums kept: windows up to 4096 blocks */

static PyObject *variance_chain(PyObject *self, PyObject *args)
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

/* ---- window statistics ------------------------------------------------------------------- */

/* Sums over the blocks [ps, pe) of each window (fastdetect.windows_from_still): with d = m_b - r
 * (r: the window's first block mean, near every block of a still window, so the cancellation is
 * harmless) the window mean is r + Σ d / n, its scatter Σ_b W_b + B (Σ d dᵀ - (Σ d)(Σ d)ᵀ / n)
 * (the within-block scatters plus the blocks' spread about the window mean, fastdetect's
 * docstring), the aux means Σ aux / n; n blocks, B samples each. */
static PyObject *window_sums(PyObject *self, PyObject *args)
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
