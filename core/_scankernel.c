/* The validation scan of a recording's columns (core/datapass.py scan_columns), one chunk per call.
 *
 * scan_chunk     extremes and their counts, the smallest time step, finiteness and the runs of
 *                exactly repeated rows of t and three strided channel fields, read in place.
 *
 * Buffers come through the buffer protocol only (no numpy C API); every length, format and
 * contiguity is checked before the loop runs, which runs without the GIL.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "_buffers.h"

/* ---- the reading scan ---------------------------------------------------------------------- */

/* The validation scan of one chunk (core/datapass.py scan_columns), folded into `st` (SCAN_STATE
 * doubles: per-channel minimum, maximum and the counts of samples exactly at each, the smallest
 * time step, 1 while every value is finite): what np.min / np.max, counting (x == extreme) and
 * np.diff(t).min() give over the whole recording.
 *
 * Repeated rows (optional, `runs` not NULL): a step repeats when a row equals the row before it
 * in all three channels (core.repeats.repeated_steps). The chunk's steps are its rows against the
 * row before them, the first against `prev` (t, x0, x1, x2 of the row before the chunk) when
 * given; without `prev` the first row has none (q = NaN never compares equal) and step s is row
 * s + 1. The runs of repeated steps are those core.repeats.chunk_runs keeps: every run of at
 * least min_run steps and the runs touching the chunk's first or last step, as (first step,
 * steps) pairs; the other runs only add to the count of repeated steps. */
typedef struct {
    long long *runs; /* (cap, 2) */
    Py_ssize_t cap, n_runs, n_repeats, min_run;
    int overflow;
} Runs;

static inline void keep_run(Runs *r, Py_ssize_t start, Py_ssize_t len)
{
    if (r->n_runs == r->cap) {
        r->overflow = 1;
        return;
    }
    r->runs[2 * r->n_runs] = start, r->runs[2 * r->n_runs + 1] = len;
    r->n_runs++;
}

/* Row k's step s = k - first in the runs of repeated steps (`same`: the row repeats the row
 * before). brk is the last step that did not repeat (-1 before the chunk's first step), so the
 * run a non-repeating step s ends spans steps brk + 1 .. s - 1; it is kept when it has >= min_run
 * steps or starts at the chunk's first step (any length >= 1): one compare, a branch taken only
 * for kept runs (a branch on `same` would be mispredicted at every repeat). The run still open
 * after the last row touches the chunk's last step and is kept by TRACK_END. Every repeated step
 * counts once in n_same, kept or not. */
#define TRACK_STEP(same, s)                                                                         \
    do {                                                                                            \
        const int same_ = (same);                                                                   \
        const Py_ssize_t len_ = (s) - brk - 1;                                                      \
        n_same += same_;                                                                            \
        if (!same_ & (len_ >= (brk < 0 ? 1 : min_run)))                                             \
            keep_run(rr, brk + 1, len_);                                                            \
        brk ^= (brk ^ (s)) & ((Py_ssize_t)same_ - 1); /* brk = same_ ? brk : s, without a branch */ \
    } while (0)

#define TRACK_END(n_steps)                                                                          \
    do {                                                                                            \
        if ((n_steps) - brk - 1 > 0)                                                                \
            keep_run(rr, brk + 1, (n_steps) - brk - 1);                                             \
        rr->n_repeats += n_same;                                                                    \
    } while (0)

enum { S_LO = 0, S_HI = 3, S_NLO = 6, S_NHI = 9, S_MINDT = 12, S_FINITE = 13, SCAN_STATE = 14 };

/* One row k of the scan against the row before it (tq, q0, q1, q2): finiteness, the step, the
 * extremes and (TRACK) the run of repeated rows it continues or ends. */
#define SCAN_ROW(T, k, tq, q0, q1, q2, TRACK)                                                       \
    do {                                                                                            \
        const double tk = LOAD(double, (tp + (k) * ts)), v0 = LOAD(T, (p0 + (k) * s0)),      \
                     v1 = LOAD(T, (p1 + (k) * s1)), v2 = LOAD(T, (p2 + (k) * s2));           \
        f += (tk - tk) + ((v0 - v0) + ((v1 - v1) + (v2 - v2)));                                     \
        const double dt = tk - (tq); /* NaN before the first row: never below min_dt */            \
        min_dt = dt < min_dt ? dt : min_dt;                                                         \
        lo0 = v0 < lo0 ? v0 : lo0, lo1 = v1 < lo1 ? v1 : lo1, lo2 = v2 < lo2 ? v2 : lo2;            \
        hi0 = v0 > hi0 ? v0 : hi0, hi1 = v1 > hi1 ? v1 : hi1, hi2 = v2 > hi2 ? v2 : hi2;            \
        if (TRACK) /* a compile-time constant: the loop without runs does none of this */          \
            TRACK_STEP((v0 == (double)(q0)) & (v1 == (double)(q1)) & (v2 == (double)(q2)), (k) - first); \
    } while (0)

/* The chunk's extremes clo, chi folded into the running ones, and, only for a channel whose
 * chunk extreme reaches the running one (rare after the first chunks), a pass counting the
 * samples exactly at it: the counts np.count_nonzero(x == extreme) give, as numpy did per chunk. */
#define FOLD_EXTREMES(T, x, m, clo, chi, st)                                                        \
    for (int c = 0; c < 3; c++) {                                                                   \
        const char *p = (x)[c].buf;                                                                 \
        const Py_ssize_t sc = (x)[c].strides[0];                                                    \
        if ((clo)[c] <= (st)[S_LO + c]) {                                                           \
            double n = 0.0;                                                                         \
            for (Py_ssize_t k = 0; k < (m); k++)                                                    \
                n += LOAD(T, (p + k * sc)) == (clo)[c];                                          \
            (st)[S_NLO + c] = (clo)[c] < (st)[S_LO + c] ? n : (st)[S_NLO + c] + n;                  \
            (st)[S_LO + c] = (clo)[c];                                                              \
        }                                                                                           \
        if ((chi)[c] >= (st)[S_HI + c]) {                                                           \
            double n = 0.0;                                                                         \
            for (Py_ssize_t k = 0; k < (m); k++)                                                    \
                n += LOAD(T, (p + k * sc)) == (chi)[c];                                          \
            (st)[S_NHI + c] = (chi)[c] > (st)[S_HI + c] ? n : (st)[S_NHI + c] + n;                  \
            (st)[S_HI + c] = (chi)[c];                                                              \
        }                                                                                           \
    }

/* Any layout (each column its own stride, float32 or float64 channels): one pass for the chunk's
 * extremes (branch-free min/max), then FOLD_EXTREMES. The strides and bases are copied to locals. */
#define DEFINE_SCAN(NAME, T, TRACK)                                                                 \
    static void NAME(const Py_buffer *t, const Py_buffer *x, const double *prev, double *st, Runs *rr)   \
    {                                                                                               \
        const Py_ssize_t m = t->shape[0], ts = t->strides[0];                                       \
        const Py_ssize_t s0 = x[0].strides[0], s1 = x[1].strides[0], s2 = x[2].strides[0];          \
        const char *tp = t->buf, *p0 = x[0].buf, *p1 = x[1].buf, *p2 = x[2].buf;                    \
        double lo0 = INFINITY, lo1 = INFINITY, lo2 = INFINITY, hi0 = -INFINITY, hi1 = -INFINITY,    \
               hi2 = -INFINITY, min_dt = st[S_MINDT];                                               \
        double f = 0.0; /* Σ (x - x) over t and the channels: 0 while all are finite, NaN from a NaN or ±inf */ \
        const Py_ssize_t first = prev ? 0 : 1; /* row k is step k - first */                        \
        const Py_ssize_t min_run = TRACK ? rr->min_run : 1;                                         \
        Py_ssize_t brk = -1, n_same = 0;                                                            \
        /* the first row against `prev` (NaN without: never a step, never a repeat), the others      \
         * against the row before them, read again rather than kept (fewer registers to spill) */    \
        if (m > 0)                                                                                  \
            SCAN_ROW(T, 0, prev ? prev[0] : NAN, prev ? prev[1] : NAN, prev ? prev[2] : NAN,         \
                     prev ? prev[3] : NAN, TRACK);                                                  \
        for (Py_ssize_t k = 1; k < m; k++)                                                          \
            SCAN_ROW(T, k, LOAD(double, (tp + (k - 1) * ts)), LOAD(T, (p0 + (k - 1) * s0)),    \
                     LOAD(T, (p1 + (k - 1) * s1)), LOAD(T, (p2 + (k - 1) * s2)), TRACK);       \
        if (TRACK)                                                                                  \
            TRACK_END(m - first);                                                                   \
        st[S_MINDT] = min_dt;                                                                       \
        const double clo[3] = {lo0, lo1, lo2}, chi[3] = {hi0, hi1, hi2};                            \
        if (!(f == 0.0))                                                                            \
            st[S_FINITE] = 0.0; /* extremes of non-finite data mean nothing: _scan stops here */    \
        else                                                                                        \
            FOLD_EXTREMES(T, x, m, clo, chi, st);                                                   \
    }

DEFINE_SCAN(scan_f, float, 0)
DEFINE_SCAN(scan_d, double, 0)
DEFINE_SCAN(scan_runs_f, float, 1)
DEFINE_SCAN(scan_runs_d, double, 1)

#if defined(__SSE2__)
#include <emmintrin.h>
#define HAVE_RECORD_SCAN 1

/* The rows of a structured record, t float64 directly followed by the three float32 channels, one
 * stride (the .npy files gravcal writes and reads in place): one 16-byte load per row gives
 * (t's high half, x0, x1, x2), bytes of t's and the channels' own elements whatever the stride.
 * Lanes 1-3 are the channels; lane 0 is never read back. Per row, what scan_f does, in other
 * instructions:
 * - extremes: minps / maxps, which are exactly `v < lo ? v : lo` and `v > hi ? v : hi` per lane
 *   (float32 compares equal (double) compares of the same values: -0.0 and NaN alike), in row order;
 * - finiteness: a NaN channel lane sets `nan` (cmpunordps); an infinite channel reaches lo or hi;
 *   a NaN or infinite t has all exponent bits set, so 2 x its bits (the sign shifted out) reach
 *   0xFFE0... (the largest kept in `tbits`). Together: the Σ (x - x) == 0 test of scan_f;
 * - the smallest step: dt = t_k - t_(k-1), min_dt = dt < min_dt ? dt : min_dt, in row order;
 * - repeated rows: the three lanes compared with the row before (cmpeqps, float equality), the
 *   first row with `prev` in float64 as scan_f does. */
#define RECORD_ROW(v, tk)                                                                           \
    do {                                                                                            \
        uint64_t tb;                                                                                \
        memcpy(&tb, &(tk), 8);                                                                      \
        tbits = tb << 1 > tbits ? tb << 1 : tbits;                                                  \
        const double dt = (tk) - tq; /* NaN before the first row without prev: never below min_dt */ \
        min_dt = dt < min_dt ? dt : min_dt;                                                         \
        tq = (tk);                                                                                  \
        lo = _mm_min_ps(v, lo), hi = _mm_max_ps(v, hi);                                             \
        nan = _mm_or_ps(nan, _mm_cmpunord_ps(v, v));                                                \
    } while (0)

/* TRACK_STEP over n <= 64 consecutive steps s0 .. s0 + n - 1 given as bits (bit j: step s0 + j
 * repeats), a run at a time instead of a step at a time: the same kept runs, brk and count. */
static inline void track_word(uint64_t w, int n, Py_ssize_t s0, Py_ssize_t *brk_, Py_ssize_t *n_same,
                              Py_ssize_t min_run, Runs *rr)
{
    uint64_t c = w - ((w >> 1) & 0x5555555555555555u); /* popcount, portable SWAR */
    c = (c & 0x3333333333333333u) + ((c >> 2) & 0x3333333333333333u);
    *n_same += (Py_ssize_t)((((c + (c >> 4)) & 0x0F0F0F0F0F0F0F0Fu) * 0x0101010101010101u) >> 56);
    const uint64_t z = ~w & (n == 64 ? ~(uint64_t)0 : ((uint64_t)1 << n) - 1); /* steps that do not repeat */
    Py_ssize_t brk = *brk_;
    if (brk < s0 - 1 && z) { /* a run open since the last word ends at this word's first step that does not repeat */
        const int e = __builtin_ctzll(z);
        const Py_ssize_t len = s0 + e - brk - 1;
        if (len >= (brk < 0 ? 1 : min_run))
            keep_run(rr, brk + 1, len);
        brk = s0 + e;
        w &= e == 63 ? 0 : ~(uint64_t)0 << (e + 1);
    }
    while (w) {
        const int a = __builtin_ctzll(w); /* a run of repeated steps starts at bit a */
        if (a > 0)
            brk = s0 + a - 1; /* bit a - 1 does not repeat */
        const uint64_t ends = z & (~(uint64_t)0 << a);
        if (!ends)
            break; /* still open at the word's end */
        const int e = __builtin_ctzll(ends); /* the step that ends it */
        const Py_ssize_t len = s0 + e - brk - 1;
        if (len >= (brk < 0 ? 1 : min_run))
            keep_run(rr, brk + 1, len);
        brk = s0 + e;
        w &= e == 63 ? 0 : ~(uint64_t)0 << (e + 1);
    }
    if (z) { /* the last step that does not repeat */
        const Py_ssize_t last = s0 + 63 - __builtin_clzll(z);
        brk = last > brk ? last : brk;
    }
    *brk_ = brk;
}

static inline __attribute__((always_inline)) void scan_record(const Py_buffer *t, const Py_buffer *x,
                                                              const double *prev, double *st, Runs *rr,
                                                              const int track)
{
    const Py_ssize_t m = t->shape[0], S = t->strides[0];
    const char *row = t->buf;
    __m128 lo = _mm_set1_ps(INFINITY), hi = _mm_set1_ps(-INFINITY), nan = _mm_setzero_ps(), vq = nan;
    uint64_t tbits = 0;
    double min_dt = st[S_MINDT], tq = prev ? prev[0] : NAN;
    const Py_ssize_t first = prev ? 0 : 1, min_run = track ? rr->min_run : 1; /* row k is step k - first */
    Py_ssize_t brk = -1, n_same = 0;
    if (m > 0) { /* the first row, against prev in float64 as scan_f compares it */
        const __m128 v = _mm_loadu_ps((const float *)(row + 4));
        double tk;
        memcpy(&tk, row, 8);
        float v0, v1, v2;
        memcpy(&v0, row + 8, 4), memcpy(&v1, row + 12, 4), memcpy(&v2, row + 16, 4);
        RECORD_ROW(v, tk);
        if (track)
            TRACK_STEP(prev && ((v0 == prev[1]) & (v1 == prev[2]) & (v2 == prev[3])), -first);
        vq = v;
    }
    /* the other rows in words of 64: each row's repeat is one bit, the runs are found per word */
    for (Py_ssize_t k0 = 1; k0 < m; k0 += 64) {
        const Py_ssize_t k1 = m - k0 < 64 ? m : k0 + 64;
        uint64_t bits = 0;
        for (Py_ssize_t k = k0; k < k1; k++) {
            const char *r = row + k * S;
            __builtin_prefetch(r + 32 * S); /* a hint, never a fault: the rows 32 ahead (~0.3 ns a row less from RAM) */
            const __m128 v = _mm_loadu_ps((const float *)(r + 4));
            double tk;
            memcpy(&tk, r, 8);
            RECORD_ROW(v, tk);
            if (track) {
                bits |= (uint64_t)((_mm_movemask_ps(_mm_cmpeq_ps(v, vq)) & 14) == 14) << (k - k0);
                vq = v;
            }
        }
        if (track)
            track_word(bits, (int)(k1 - k0), k0 - first, &brk, &n_same, min_run, rr);
    }
    if (track)
        TRACK_END(m - first);
    st[S_MINDT] = min_dt;
    float l[4], h[4];
    _mm_storeu_ps(l, lo), _mm_storeu_ps(h, hi);
    const double clo[3] = {l[1], l[2], l[3]}, chi[3] = {h[1], h[2], h[3]};
    int finite = (_mm_movemask_ps(nan) & 14) == 0 && tbits < 0xFFE0000000000000u;
    for (int c = 0; c < 3 && m > 0; c++)
        finite &= isfinite(clo[c]) && isfinite(chi[c]);
    if (!finite)
        st[S_FINITE] = 0.0;
    else
        FOLD_EXTREMES(float, x, m, clo, chi, st);
}

static void scan_record_runs(const Py_buffer *t, const Py_buffer *x, const double *prev, double *st, Runs *rr)
{
    scan_record(t, x, prev, st, rr, 1);
}

static void scan_record_only(const Py_buffer *t, const Py_buffer *x, const double *prev, double *st, Runs *rr)
{
    scan_record(t, x, prev, st, rr, 0);
}

/* t float64 then x0, x1, x2 float32 in each row, one stride: the layout scan_record reads */
static int is_record(const Py_buffer *t, const Py_buffer *x)
{
    const char *t0 = t->buf;
    const Py_ssize_t S = t->strides[0];
    return kind_of(&x[0]) == 'f' && x[0].buf == t0 + 8 && x[1].buf == t0 + 12 && x[2].buf == t0 + 16 &&
           x[0].strides[0] == S && x[1].strides[0] == S && x[2].strides[0] == S;
}
#endif

static PyObject *scan_chunk(PyObject *self, PyObject *args)
{
    PyObject *ot, *ox[3], *oprev, *ost, *oruns;
    Py_ssize_t min_run = 1;
    if (!PyArg_ParseTuple(args, "OOOOOOO|n:scan_chunk", &ot, &ox[0], &ox[1], &ox[2], &oprev, &ost, &oruns, &min_run))
        return NULL;
    Py_buffer v[7] = {{0}};
    Py_buffer *t = v, *x = v + 1, *prev = v + 4, *st = v + 5, *runs = v + 6;
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
    if (oruns != Py_None && get_contiguous(oruns, runs, "runs", 'q', -1, 1) < 0)
        goto fail;
    if (oruns != Py_None && (runs->len / runs->itemsize) % 2 != 0) {
        PyErr_SetString(PyExc_ValueError, "runs must hold (start, steps) pairs: an even number of int64");
        goto fail;
    }
    if (min_run < 1) {
        PyErr_Format(PyExc_ValueError, "min_run must be >= 1, got %zd", min_run);
        goto fail;
    }
    const double *pv = oprev != Py_None ? prev->buf : NULL;
    Runs rr = {oruns != Py_None ? runs->buf : NULL, oruns != Py_None ? runs->len / runs->itemsize / 2 : 0, 0, 0,
               min_run, 0};
    Runs *rp = oruns != Py_None ? &rr : NULL;
    Py_BEGIN_ALLOW_THREADS
    void (*scan)(const Py_buffer *, const Py_buffer *, const double *, double *, Runs *) =
        rp ? (kind == 'f' ? scan_runs_f : scan_runs_d) : (kind == 'f' ? scan_f : scan_d);
#ifdef HAVE_RECORD_SCAN
    if (is_record(t, x))
        scan = rp ? scan_record_runs : scan_record_only;
#endif
    scan(t, x, pv, st->buf, rp);
    Py_END_ALLOW_THREADS
    if (rr.overflow) {
        PyErr_Format(PyExc_ValueError, "runs holds room for %zd runs, the chunk has more: give it m // min_run + 2",
                     rr.cap);
        goto fail;
    }
    release_all(v, 7);
    return Py_BuildValue("nn", rr.n_runs, rr.n_repeats);
fail:
    release_all(v, 7);
    return NULL;
}

static PyMethodDef methods[] = {
    {"scan_chunk", scan_chunk, METH_VARARGS,
     "scan_chunk(t, x0, x1, x2, prev, state, runs, min_run=1) -> (n_runs, n_repeated_steps)\nThe reading scan of "
     "one chunk folded into state (14 float64: min[3], max[3], count at min[3], count at max[3], smallest\n"
     "step, all finite); runs (cap, 2) int64 or None: (first step, steps) of the runs of rows equal to the row\n"
     "before (prev: t, x0, x1, x2 of the row before the chunk, or None) of >= min_run steps or at the chunk's ends."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_scankernel",
                                    "The reading scan's compiled loop (no numpy C API).", -1, methods,
                                    NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__scankernel(void)
{
    return PyModule_Create(&module);
}
