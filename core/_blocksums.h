/* The block statistics of one chunk of rows (core/fastdetect.py block_stats): per block of B
 * samples the mean, the 6 scatter sums, the aux means and the usable flag, read straight from
 * strided (e.g. memory-mapped record) fields, accumulated in float64. Shared by block_pass
 * (core/_blockkernels.c) and the reading scan, which runs them on the rows it has just read
 * (core/_scankernel.c scan_chunk with blocks): one source, the same bits from both.
 * Include after Python.h and _buffers.h; build with -ffp-contract=off. */
#ifndef GRAVCAL_BLOCKSUMS_H
#define GRAVCAL_BLOCKSUMS_H

#include <math.h>
#include <stdint.h>
#include <string.h>

static const int I6[6] = {0, 1, 2, 0, 0, 1};
static const int J6[6] = {0, 1, 2, 1, 2, 2};

/* One chunk of m blocks of B samples: the three channels x (strides sx), the times t (stride st;
 * t_before: the time before the chunk's first sample, t[0] - max_step / 2 for the recording's first
 * sample, which has no predecessor), the aux columns (k_aux, NULL when none), outputs in blocks
 * [col, col + m) of rows nb apart. */
typedef struct {
    const char *x[3], *t, *aux;
    Py_ssize_t sx[3], st, B, m, nb, col, k_aux, aux_s0, aux_s1;
    double max_step, t_before;
    double *mean, *aux_mean;
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

/* One block's outputs from its sums (reference r01, r2; sums (a0, a1), a2, (q00, q11), q22, q01,
 * (q02, q12); ok: every step good): the one-block forms' common end. */
static inline __attribute__((always_inline)) void block_finish(const Chunk *c, Py_ssize_t b, double inv_B, v2d r01,
                                                               double r2, v2d a01, double a2, v2d q0011, double q22,
                                                               double q01, v2d q0212, int ok)
{
    const Py_ssize_t nb = c->nb;
    const double r0 = r01[0], r1 = r01[1];
    const double a0 = a01[0], a1 = a01[1], q00 = q0011[0], q11 = q0011[1];
    const double q02 = q0212[0], q12 = q0212[1];
    const double m0 = a0 * inv_B, m1 = a1 * inv_B, m2 = a2 * inv_B;
    const double w[6] = {q00 - a0 * m0, q11 - a1 * m1, q22 - a2 * m2, q01 - a0 * m1, q02 - a0 * m2, q12 - a1 * m2};
    double *mo = c->mean + c->col + b;
    float *so = c->scatter + c->col + b;
    mo[0] = r0 + m0, mo[nb] = r1 + m1, mo[2 * nb] = r2 + m2;
    double all = mo[0] + mo[nb] + mo[2 * nb];
    for (int p = 0; p < 6; p++) {
        so[p * nb] = (float)w[p];
        all += w[p];
    }
    c->usable[c->col + b] = (char)(ok & (all * 0.0 == 0.0));
}

#define DEFINE_CHUNK_ROWS(NAME, T)                                                                  \
    static void NAME(const Chunk *c)                                                                \
    {                                                                                               \
        const Py_ssize_t B = c->B, s0 = c->sx[0], s1 = c->sx[1], s2 = c->sx[2];                       \
        const double inv_B = 1.0 / (double)B, max_step = c->max_step;                               \
        const char *p0 = c->x[0], *p1 = c->x[1], *p2 = c->x[2], *tp = c->t;                         \
        double prev = c->t_before;                                                                  \
        for (Py_ssize_t b = 0; b < c->m; b++) {                                                     \
            const double r0 = *(const T *)p0, r1 = *(const T *)p1, r2 = *(const T *)p2;             \
            const v2d r01 = {r0, r1};                                                               \
            /* channels 0 and 1 side by side in a v2d, each lane its own sums in order: (a0, a1),  \
             * (q00, q11), (q02, q12) = Σ (d0, d1) d2; a2, q22, q01 alone */                        \
            v2d a01 = {0, 0}, q0011 = {0, 0}, q0212 = {0, 0};                                       \
            double a2 = 0, q22 = 0, q01 = 0;                                                        \
            int ok = 1;                                                                             \
            for (Py_ssize_t k = 0; k < B; k++) {                                                    \
                const v2d d01 = (v2d){*(const T *)p0, *(const T *)p1} - r01;                        \
                const double d2 = (double)*(const T *)p2 - r2;                                      \
                const double now = *(const double *)tp, dt = now - prev;                            \
                p0 += s0, p1 += s1, p2 += s2, tp += c->st;                                          \
                a01 += d01, a2 += d2;                                                               \
                q0011 += d01 * d01, q22 += d2 * d2;                                                 \
                q01 += d01[0] * d01[1], q0212 += d01 * (v2d){d2, d2};                               \
                ok &= (dt > 0.0) & (dt <= max_step);                                                \
                prev = now;                                                                         \
            }                                                                                       \
            block_finish(c, b, inv_B, r01, r2, a01, a2, q0011, q22, q01, q0212, ok);                \
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
            const v2d r0 = {*(const T *)(ra + o0), *(const T *)(rb + o0)};                          \
            const v2d r1 = {*(const T *)(ra + o1), *(const T *)(rb + o1)};                          \
            const v2d r2 = {*(const T *)(ra + o2), *(const T *)(rb + o2)};                          \
            v2d prev = {b == 0 ? c->t_before : *(const double *)(ra - S), *(const double *)(rb - S)}; \
            v2d a0 = zero, a1 = zero, a2 = zero, q00 = zero, q11 = zero, q22 = zero, q01 = zero,      \
                q02 = zero, q12 = zero;                                                             \
            v2l good = {0, 0}; /* minus one per step above 0, one per step up to max_step: ok at 2 B */ \
            for (Py_ssize_t k = 0; k < B; k++, ra += S, rb += S) {                                  \
                const v2d d0 = (v2d){*(const T *)(ra + o0), *(const T *)(rb + o0)} - r0;             \
                const v2d d1 = (v2d){*(const T *)(ra + o1), *(const T *)(rb + o1)} - r1;             \
                const v2d d2 = (v2d){*(const T *)(ra + o2), *(const T *)(rb + o2)} - r2;             \
                const v2d now = {*(const double *)ra, *(const double *)rb}, dt = now - prev;        \
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

/* Blocks [b, b + m) of chunk c as a chunk of their own (the time before them: t_before, or the
 * last row of block b - 1). */
static inline Chunk sub_chunk(const Chunk *c, Py_ssize_t b, Py_ssize_t m)
{
    Chunk s = *c;
    const Py_ssize_t skip = b * c->B;
    s.t += skip * c->st, s.m = m, s.col += b;
    for (int j = 0; j < 3; j++)
        s.x[j] += skip * c->sx[j];
    if (s.aux != NULL)
        s.aux += skip * c->aux_s0;
    if (b > 0)
        s.t_before = *(const double *)(s.t - c->st);
    return s;
}

/* The chunk's blocks: in pairs when t and the channels share one stride (an odd last one alone),
 * else one at a time; then the aux block means (numpy: aux.reshape(m, B, k).mean(axis=1)), which
 * clear `usable` where non-finite. */
static void block_sums(const Chunk *c, char kind)
{
    const int one_stride = c->sx[0] == c->st && c->sx[1] == c->st && c->sx[2] == c->st;
    if (one_stride && c->m > 1) {
        const Py_ssize_t paired = c->m - c->m % 2;
        const Chunk tail = sub_chunk(c, paired, c->m - paired);
        if (kind == 'f') {
            chunk_pairs_f(c);
            chunk_rows_f(&tail);
        } else {
            chunk_pairs_d(c);
            chunk_rows_d(&tail);
        }
    } else if (kind == 'f') {
        chunk_rows_f(c);
    } else {
        chunk_rows_d(c);
    }
    for (Py_ssize_t a = 0; a < c->k_aux; a++)
        for (Py_ssize_t b = 0; b < c->m; b++) {
            double sa = 0.0;
            const char *p = c->aux + b * c->B * c->aux_s0 + a * c->aux_s1;
            for (Py_ssize_t k = 0; k < c->B; k++)
                sa += *(const double *)(p + k * c->aux_s0);
            const double ma = sa / (double)c->B;
            c->aux_mean[a * c->nb + c->col + b] = ma;
            if (!isfinite(ma))
                c->usable[c->col + b] = 0;
        }
}

/* Checks block_pass's (and scan_chunk's blocks') arguments for a chunk of `rows` rows whose first
 * m * B rows are blocks b0 .. b0 + m - 1, and fills c's aux, outputs and sizes: v[0] aux, v[1..4]
 * mean, scatter, aux_mean, usable (released by the caller). The columns' pointers and t_before are
 * the caller's. Returns -1 with an exception set on failure. */
static int block_args(PyObject *oaux, Py_ssize_t B, Py_ssize_t b0, Py_ssize_t m, Py_ssize_t rows, double max_step,
                      PyObject *omean, PyObject *oscat, PyObject *oam, PyObject *ouse, Py_buffer *v, Chunk *c)
{
    Py_buffer *aux = v, *mean = v + 1, *scat = v + 2, *am = v + 3, *use = v + 4;
    if (B < 1 || m < 0 || m > rows / B) {
        PyErr_Format(PyExc_ValueError, "%zd blocks of %zd samples do not fit the chunk's %zd rows (block_n >= 1)", m,
                     B, rows);
        return -1;
    }
    Py_ssize_t k_aux = 0, aux_s1 = 0;
    if (oaux != Py_None) {
        if (get_strided(oaux, aux, "aux", "d", 2) < 0)
            return -1;
        k_aux = aux->ndim == 2 ? aux->shape[1] : 1;
        aux_s1 = aux->ndim == 2 ? aux->strides[1] : 0;
        if (aux->shape[0] != rows) {
            PyErr_Format(PyExc_ValueError, "aux must have the chunk's %zd rows, got %zd", rows, aux->shape[0]);
            return -1;
        }
    }
    if (get_contiguous(ouse, use, "usable", '?', -1, 1) < 0)
        return -1;
    const Py_ssize_t nb = use->len;
    if (get_contiguous(omean, mean, "mean", 'd', 3 * nb, 1) < 0 ||
        get_contiguous(oscat, scat, "scatter", 'f', 6 * nb, 1) < 0 ||
        get_contiguous(oam, am, "aux_mean", 'd', k_aux * nb, 1) < 0)
        return -1;
    if (b0 < 0 || b0 > nb - m) {
        PyErr_Format(PyExc_ValueError, "blocks [%zd, %zd) lie outside the %zd output blocks", b0, b0 + m, nb);
        return -1;
    }
    c->aux = k_aux ? aux->buf : NULL, c->aux_s0 = k_aux ? aux->strides[0] : 0, c->aux_s1 = aux_s1;
    c->k_aux = k_aux, c->B = B, c->m = m, c->nb = nb, c->col = b0, c->max_step = max_step;
    c->mean = mean->buf, c->scatter = scat->buf, c->aux_mean = am->buf, c->usable = use->buf;
    return 0;
}

#endif
