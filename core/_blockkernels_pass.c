/* block_pass: one chunk of core.fastdetect.block_stats: per block of B samples the mean, the 6 scatter
 * sums, the aux means and the usable flag, read straight from strided (e.g. memory-mapped record) fields,
 * accumulated in float64. Part of the _blockkernels extension (core/_blockkernels.c). */
#include "_blockkernels.h"

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

BLOCKKERNELS_INTERNAL PyObject *block_pass(PyObject *self, PyObject *args)
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
