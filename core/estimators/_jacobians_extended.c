/* extended_accel_jacobian: the extended models (extended.py), whose derivative rows depend on the window:
 *
 *     K = K_const + sum_q p_q dK_q,   o = o_const + sum_q p_q do_q          (extended.py module docstring)
 *     a = K^-1 (raw - o),   J[:, q] = da/dp_q = -K^-1 (dK_q a + do_q)
 *
 * The sums over q start from 0.0 and add in q order, as numpy's einsum("p,mpij->mij") does; K^-1 is the
 * adjugate over the determinant, operation for operation as the numpy form in the test; the three-term
 * products add left to right (numpy's batched matmul hands those 3 x 3 products to dgemv / dgemm one window
 * at a time, whose order differs: the results agree to rounding, the test derives the bound). Where the CPU
 * has AVX2 and FMA, four windows run side by side in the lanes of a vector (ext_lanes: the same operations
 * per lane; 2.4x faster on the week's 12 000 windows).
 * Part of the _jacobians extension (core/estimators/_jacobians.c).
 */
#include "_jacobians.h"

#define N_BUF 9

/* extended_accel_jacobian(K_const (3, 3), o_const (3,), p (P,), rows (P, 12), entries (n, 2), values (M, n),
 *                         raw (M, 3), a (M, 3) out, J (M, 3, P) out, M, P, n)
 * rows: each parameter's constant dK_q (9, row-major) and do_q (3) (extended.py: the reference rows);
 * entries: (q, e) of the n entries that depend on the window (e 0-8 in dK_q, 9-11 in do_q), whose values are
 * values[w]. The window's rows are the constant ones with those entries replaced, as term_rows builds them.
 * Entries 0 in every row (constant 0, no window value) are left out of the sums: with p finite the product
 * is ±0, which added to a partial sum of the einsum order (never -0: it starts at +0.0 and rounds to
 * nearest) leaves it unchanged; a row of dK_q that is all 0 gives dK_q a + do_q = do_q exactly when a is
 * finite and do_q is not 0. Otherwise (p or a not finite, do_q 0) the full sums run. */
/* extended_accel_jacobian's loop over windows [w0, w1) (R: this lane's copy of the rows) */
typedef struct {
    const double *Kc, *oc, *c, *V, *raw;
    double *A, *J;
    const Py_ssize_t *pos, *kq, *ke, *oq, *oe;
    const char *row_zero;
    double *R[2], *RV[2];
    Py_ssize_t n, nk, no, p;
    int finite_p, lanes;
} ExtLoop;

static void ext_scalar(const ExtLoop *x, Py_ssize_t w0, Py_ssize_t w1, int lane)
{
    const double *Kc = x->Kc, *oc = x->oc, *c = x->c, *V = x->V, *raw = x->raw;
    double *A = x->A, *J = x->J, *R = x->R[lane];
    const Py_ssize_t *pos = x->pos, *kq = x->kq, *ke = x->ke, *oq = x->oq, *oe = x->oe;
    const char *row_zero = x->row_zero;
    const Py_ssize_t n = x->n, nk = x->nk, no = x->no, p = x->p;
    const int finite_p = x->finite_p;
    for (Py_ssize_t w = w0; w < w1; w++) {
        double K[9], o[3], inv[9], d[3], a[3];
        for (Py_ssize_t t = 0; t < n; t++)  /* the window's rows: the other entries stay the constant ones */
            R[pos[t]] = V[w * n + t];
        /* K(c), o(c): einsum("p,mpij->mij") and ("p,mpi->mi") from 0.0 in q order, then the constant part */
        for (int j = 0; j < 9; j++)
            K[j] = 0.0;
        for (int j = 0; j < 3; j++)
            o[j] = 0.0;
        if (finite_p) {
            for (Py_ssize_t t = 0; t < nk; t++)
                K[ke[t]] += c[kq[t]] * R[12 * kq[t] + ke[t]];
            for (Py_ssize_t t = 0; t < no; t++)
                o[oe[t]] += c[oq[t]] * R[12 * oq[t] + 9 + oe[t]];
        } else {
            for (Py_ssize_t q = 0; q < p; q++) {
                for (int j = 0; j < 9; j++)
                    K[j] += c[q] * R[12 * q + j];
                for (int j = 0; j < 3; j++)
                    o[j] += c[q] * R[12 * q + 9 + j];
            }
        }
        for (int j = 0; j < 9; j++)
            K[j] = Kc[j] + K[j];
        for (int j = 0; j < 3; j++)
            o[j] = oc[j] + o[j];
        /* K^-1 = adjugate / determinant (a singular K gives inf/NaN, as the numpy form does) */
        const double ka = K[0], kb = K[1], kc = K[2], kd = K[3], ke_ = K[4], kf = K[5], kg = K[6], kh = K[7],
                     ki = K[8];
        inv[0] = ke_ * ki - kf * kh, inv[1] = kc * kh - kb * ki, inv[2] = kb * kf - kc * ke_;
        inv[3] = kf * kg - kd * ki, inv[4] = ka * ki - kc * kg, inv[5] = kc * kd - ka * kf;
        inv[6] = kd * kh - ke_ * kg, inv[7] = kb * kg - ka * kh, inv[8] = ka * ke_ - kb * kd;
        const double det = ka * inv[0] + kb * inv[3] + kc * inv[6];
        for (int j = 0; j < 9; j++)
            inv[j] /= det;
        /* a = K^-1 (raw - o) */
        for (int j = 0; j < 3; j++)
            d[j] = raw[3 * w + j] - o[j];
        for (int i = 0; i < 3; i++)
            a[i] = A[3 * w + i] = inv[3 * i] * d[0] + inv[3 * i + 1] * d[1] + inv[3 * i + 2] * d[2];
        const int finite_a = isfinite(a[0]) && isfinite(a[1]) && isfinite(a[2]);
        /* J[:, q] = -K^-1 (dK_q a + do_q) */
        double *Jw = J + w * 3 * p;
        for (Py_ssize_t q = 0; q < p; q++) {
            const double *G = R + 12 * q, *g = G + 9;
            double t[3];
            for (int j = 0; j < 3; j++)
                t[j] = row_zero[3 * q + j] && finite_a && g[j] != 0.0
                           ? g[j]
                           : (G[3 * j] * a[0] + G[3 * j + 1] * a[1] + G[3 * j + 2] * a[2]) + g[j];
            for (int i = 0; i < 3; i++)
                Jw[i * p + q] = -(inv[3 * i] * t[0] + inv[3 * i + 1] * t[1] + inv[3 * i + 2] * t[2]);
        }
    }
}

#ifdef LANES_AVX2
/* ext_loop on four windows at a time (finite p), one per lane of a 256-bit vector: each lane runs ext_loop's
 * operations in its order (the sums over q from 0.0, the adjugate, the three-term products left to right, the
 * structural-zero shortcut decided per lane), so each window's bits are ext_loop's. RV: this lane's rows, four
 * copies side by side (RV[4 (12 q + e) + l]: entry e of parameter q for the group's window l), the constant
 * entries written by the caller, the window entries here. Windows [w0, w1), w1 - w0 a multiple of 4. */
#define BCV(x) _mm256_set1_pd(x)
__attribute__((target("avx2"))) static void ext_lanes(const ExtLoop *x, Py_ssize_t w0, Py_ssize_t w1, int lane)
{
    const double *Kc = x->Kc, *oc = x->oc, *c = x->c, *V = x->V, *raw = x->raw;
    double *A = x->A, *J = x->J, *RV = x->RV[lane];
    const Py_ssize_t *pos = x->pos, *kq = x->kq, *ke = x->ke, *oq = x->oq, *oe = x->oe;
    const char *row_zero = x->row_zero;
    const Py_ssize_t n = x->n, nk = x->nk, no = x->no, p = x->p;
    const __m256d zero = _mm256_setzero_pd(), sign = BCV(-0.0), inf = BCV(INFINITY);
    double lane4[4];
    for (Py_ssize_t w = w0; w < w1; w += 4) {
        for (Py_ssize_t t = 0; t < n; t++)
            for (int l = 0; l < 4; l++)
                RV[4 * pos[t] + l] = V[(w + l) * n + t];
        __m256d K[9], o[3], inv[9], d[3], a[3];
        for (int j = 0; j < 9; j++)
            K[j] = zero;
        for (int j = 0; j < 3; j++)
            o[j] = zero;
        for (Py_ssize_t t = 0; t < nk; t++)
            K[ke[t]] = _mm256_add_pd(K[ke[t]], _mm256_mul_pd(BCV(c[kq[t]]), _mm256_loadu_pd(RV + 4 * (12 * kq[t] + ke[t]))));
        for (Py_ssize_t t = 0; t < no; t++)
            o[oe[t]] = _mm256_add_pd(o[oe[t]],
                                     _mm256_mul_pd(BCV(c[oq[t]]), _mm256_loadu_pd(RV + 4 * (12 * oq[t] + 9 + oe[t]))));
        for (int j = 0; j < 9; j++)
            K[j] = _mm256_add_pd(BCV(Kc[j]), K[j]);
        for (int j = 0; j < 3; j++)
            o[j] = _mm256_add_pd(BCV(oc[j]), o[j]);
#define DIFF2(u, v, s, t) _mm256_sub_pd(_mm256_mul_pd(K[u], K[v]), _mm256_mul_pd(K[s], K[t]))
        inv[0] = DIFF2(4, 8, 5, 7), inv[1] = DIFF2(2, 7, 1, 8), inv[2] = DIFF2(1, 5, 2, 4);
        inv[3] = DIFF2(5, 6, 3, 8), inv[4] = DIFF2(0, 8, 2, 6), inv[5] = DIFF2(2, 3, 0, 5);
        inv[6] = DIFF2(3, 7, 4, 6), inv[7] = DIFF2(1, 6, 0, 7), inv[8] = DIFF2(0, 4, 1, 3);
#undef DIFF2
        const __m256d det = _mm256_add_pd(_mm256_add_pd(_mm256_mul_pd(K[0], inv[0]), _mm256_mul_pd(K[1], inv[3])),
                                          _mm256_mul_pd(K[2], inv[6]));
        for (int j = 0; j < 9; j++)
            inv[j] = _mm256_div_pd(inv[j], det);
        for (int j = 0; j < 3; j++)
            d[j] = _mm256_sub_pd(_mm256_set_pd(raw[3 * (w + 3) + j], raw[3 * (w + 2) + j], raw[3 * (w + 1) + j],
                                               raw[3 * w + j]), o[j]);
        __m256d finite = _mm256_castsi256_pd(_mm256_set1_epi64x(-1));
        for (int i = 0; i < 3; i++) {
            a[i] = _mm256_add_pd(_mm256_add_pd(_mm256_mul_pd(inv[3 * i], d[0]), _mm256_mul_pd(inv[3 * i + 1], d[1])),
                                 _mm256_mul_pd(inv[3 * i + 2], d[2]));
            finite = _mm256_and_pd(finite, _mm256_cmp_pd(_mm256_andnot_pd(sign, a[i]), inf, _CMP_LT_OQ));
            _mm256_storeu_pd(lane4, a[i]);
            for (int l = 0; l < 4; l++)
                A[3 * (w + l) + i] = lane4[l];
        }
        for (Py_ssize_t q = 0; q < p; q++) {
            const double *G = RV + 4 * 12 * q, *g = G + 4 * 9;
            __m256d t[3];
            for (int j = 0; j < 3; j++) {
                const __m256d gj = _mm256_loadu_pd(g + 4 * j);
                t[j] = _mm256_add_pd(
                    _mm256_add_pd(_mm256_add_pd(_mm256_mul_pd(_mm256_loadu_pd(G + 4 * (3 * j)), a[0]),
                                                _mm256_mul_pd(_mm256_loadu_pd(G + 4 * (3 * j + 1)), a[1])),
                                  _mm256_mul_pd(_mm256_loadu_pd(G + 4 * (3 * j + 2)), a[2])),
                    gj);
                if (row_zero[3 * q + j]) /* the lanes whose a is finite and do_q[j] not 0 take do_q[j] itself */
                    t[j] = _mm256_blendv_pd(t[j], gj, _mm256_and_pd(finite, _mm256_cmp_pd(gj, zero, _CMP_NEQ_UQ)));
            }
            double *Jw = J + w * 3 * p;
            for (int i = 0; i < 3; i++) {
                const __m256d v = _mm256_xor_pd(
                    _mm256_add_pd(_mm256_add_pd(_mm256_mul_pd(inv[3 * i], t[0]), _mm256_mul_pd(inv[3 * i + 1], t[1])),
                                  _mm256_mul_pd(inv[3 * i + 2], t[2])),
                    sign);
                _mm256_storeu_pd(lane4, v);
                for (int l = 0; l < 4; l++)
                    Jw[l * 3 * p + i * p + q] = lane4[l];
            }
        }
    }
}
#endif

static void ext_loop(void *ctx, Py_ssize_t w0, Py_ssize_t w1, int lane)
{
    const ExtLoop *x = ctx;
#ifdef LANES_AVX2
    if (x->lanes && x->finite_p) {
        const Py_ssize_t w4 = w0 + (w1 - w0) / 4 * 4;
        ext_lanes(x, w0, w4, lane);
        w0 = w4;
    }
#endif
    ext_scalar(x, w0, w1, lane);
}

JACOBIANS_INTERNAL PyObject *extended_accel_jacobian(PyObject *self, PyObject *args)
{
    PyObject *obj[N_BUF];
    Py_ssize_t m, p, n;
    int threads = -1;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOnnn|i", &obj[0], &obj[1], &obj[2], &obj[3], &obj[4], &obj[5], &obj[6],
                          &obj[7], &obj[8], &m, &p, &n, &threads) || threads_arg(threads) < 0)
        return NULL;
    if (m < 0 || p < 1 || n < 0) {
        PyErr_SetString(PyExc_ValueError, "need M >= 0 windows, P >= 1 parameters and 0 <= n <= 12 P entries");
        return NULL;
    }
    if (p > PY_SSIZE_T_MAX / 8 / 24 || m > PY_SSIZE_T_MAX / 8 / 12 / p) {
        PyErr_SetString(PyExc_ValueError, "dimensions too large");
        return NULL;
    }
    if (n > 12 * p) {
        PyErr_SetString(PyExc_ValueError, "need M >= 0 windows, P >= 1 parameters and 0 <= n <= 12 P entries");
        return NULL;
    }
    static const char *names[N_BUF] = {"K_const", "o_const", "p", "rows", "entries", "values", "raw", "a", "J"};
    const Py_ssize_t len[N_BUF] = {9, 3, p, 12 * p, 2 * n, m * n, m * 3, m * 3, m * 3 * p};
    Py_buffer buf[N_BUF];
    int got = 0;
    for (; got < N_BUF; got++)
        if (get_doubles(obj[got], &buf[got], len[got], got >= 7, names[got]) < 0)
            break;
    if (got < N_BUF) {
        while (got-- > 0)
            PyBuffer_Release(&buf[got]);
        return NULL;
    }
    /* work: the window's rows (12 P), the positions of the window entries (n), the (q, e) pairs of dK and do
     * that may be nonzero, q-major (each entry's sum keeps q order), the dK rows that are 0 in every window */
    double *R = PyMem_Malloc(sizeof(double) * (size_t)p * 24); /* the window's rows: one copy per lane */
    double *RV = PyMem_Malloc(sizeof(double) * (size_t)p * 96); /* and four side by side per lane (ext_lanes) */
    Py_ssize_t *pos = PyMem_Malloc(sizeof(Py_ssize_t) * ((size_t)n + 24 * (size_t)p + 1));
    char *row_zero = PyMem_Malloc((size_t)p * 3);
    const double *Kc = buf[0].buf, *oc = buf[1].buf, *c = buf[2].buf, *rows = buf[3].buf, *ent = buf[4].buf,
                 *V = buf[5].buf, *raw = buf[6].buf;
    double *A = buf[7].buf, *J = buf[8].buf;
    int ok = R != NULL && RV != NULL && pos != NULL && row_zero != NULL;
    if (!ok)
        PyErr_NoMemory();
    Py_ssize_t *kq = pos + n, *ke = kq + 9 * p, *oq = kq + 18 * p, *oe = kq + 21 * p, nk = 0, no = 0;
    int finite_p = 1;
    if (ok) {
        memcpy(R, rows, sizeof(double) * (size_t)p * 12);
        memcpy(R + 12 * p, rows, sizeof(double) * (size_t)p * 12);
        for (Py_ssize_t e = 0; e < 24 * p; e++)
            for (int l = 0; l < 4; l++)
                RV[4 * e + l] = rows[e % (12 * p)];
        for (Py_ssize_t t = 0; t < n && ok; t++) {
            const double q = ent[2 * t], e = ent[2 * t + 1];
            if (!(q >= 0 && q < (double)p && e >= 0 && e < 12 && q == (Py_ssize_t)q && e == (Py_ssize_t)e)) {
                PyErr_Format(PyExc_ValueError, "entry %zd is (%g, %g): need an integer q < P and e < 12", t, q, e);
                ok = 0;
            } else {
                pos[t] = 12 * (Py_ssize_t)q + (Py_ssize_t)e;
            }
        }
    }
    if (ok) {
        for (Py_ssize_t q = 0; q < p; q++) {
            char mark[12] = {0};
            for (Py_ssize_t t = 0; t < n; t++)
                if (pos[t] / 12 == q)
                    mark[pos[t] % 12] = 1;
            finite_p &= isfinite(c[q]) != 0;
            for (int e = 0; e < 9; e++)
                if (mark[e] || rows[12 * q + e] != 0.0)
                    kq[nk] = q, ke[nk++] = e;
            for (int e = 0; e < 3; e++) {
                if (mark[9 + e] || rows[12 * q + 9 + e] != 0.0)
                    oq[no] = q, oe[no++] = e;
                int z = 1;
                for (int k = 0; k < 3; k++)
                    z &= !mark[3 * e + k] && rows[12 * q + 3 * e + k] == 0.0;
                row_zero[3 * q + e] = (char)z;
            }
        }
        ExtLoop x = {Kc, oc, c, V, raw, A, J, pos, kq, ke, oq, oe, row_zero, {R, R + 12 * p}, {RV, RV + 48 * p}, n, nk,
                     no, p, finite_p, has_lanes()};
        Py_BEGIN_ALLOW_THREADS
        share_windows(ext_loop, &x, m, threads < 0 && x.lanes && finite_p ? 1 : threads); /* as linear_norm_jacobian */
        Py_END_ALLOW_THREADS
    }
    PyMem_Free(R);
    PyMem_Free(RV);
    PyMem_Free(pos);
    PyMem_Free(row_zero);
    for (int k = 0; k < N_BUF; k++)
        PyBuffer_Release(&buf[k]);
    if (!ok)
        return NULL;
    Py_RETURN_NONE;
}
