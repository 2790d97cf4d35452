/* linear_norm_jacobian: a parameterization with constant derivatives (offsets, 6, 9, 12; parameterization.py):
 *
 *     a = K^-1 (raw - o)                      h = |a|                               (Lötters eq. 8)
 *     J[:, q] = -(K^-1 dK_q a + K^-1 do_q)    B[q] = (a / h)^T J[:, q]             (eq. 13a generalised)
 *     var = g C g^T,  g = (a / h)^T K^-1      (crlb.h_variance: the delta-method variance of h, C_mu)
 *
 * numpy computes a, J and g as (M, 3) @ (3, n) products, which OpenBLAS's dgemm kernel adds as one fused
 * chain fma(x2, y2, fma(x1, y1, x0 y0)) for M >= 2 windows (a single row goes to dgemv, which adds in
 * another order: the caller keeps numpy's form there); the norm, the projection and the quadratic form add
 * as numpy's norm and einsum do (core/_fitsums.c). So each result equals numpy's bit for bit on this BLAS.
 * Where the CPU has AVX2 and FMA, four windows run side by side in the lanes of a vector (linear_lanes:
 * the same operations per lane; 3x faster on the week's 12 000 windows).
 * Part of the _jacobians extension (core/estimators/_jacobians.c).
 */
#include "_jacobians.h"

/* fma(x2, y2, fma(x1, y1, x0 y0)): OpenBLAS dgemm's sum of a row (x0, x1, x2) times a column (y0, y1, y2).
 * On x86 compiled twice (target_clones): with FMA instructions where the CPU has them, else through libm's fma,
 * which rounds the same (correctly, once). */
#define GEMM3(x0, x1, x2, y0, y1, y2) fma((x2), (y2), fma((x1), (y1), (x0) * (y0)))

#if defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
#define FMA_CLONES __attribute__((target_clones("fma", "default")))
#else
#define FMA_CLONES /* other architectures: fma is one instruction in the base set, or libm's */
#endif

FMA_CLONES
static void linear_loop(const double *Ki, const double *o, const double *G, const double *C, const double *raw,
                        const double *cov, double *H, double *B, double *A, double *V, Py_ssize_t m, Py_ssize_t p)
{
    for (Py_ssize_t w = 0; w < m; w++) {
        const double d0 = raw[3 * w] - o[0], d1 = raw[3 * w + 1] - o[1], d2 = raw[3 * w + 2] - o[2];
        double a[3], u[3];
        /* a = (raw - o) @ K^-1.T */
        for (int i = 0; i < 3; i++)
            a[i] = A[3 * w + i] = GEMM3(d0, d1, d2, Ki[3 * i], Ki[3 * i + 1], Ki[3 * i + 2]);
        /* h = sqrt(a0² + a1² + a2²) as np.linalg.norm(a, axis=1); u = a / h */
        const double h = sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]);
        H[w] = h;
        for (int i = 0; i < 3; i++)
            u[i] = a[i] / h;
        /* B[q] = sum_i u_i J[i, q] from 0.0 in i order (einsum "mi,mip->mp"), with
         * J[i, q] = -((a @ G')[i, q] + C[i, q]), G' = G.transpose(2, 1, 0): row k, column (i, q) = G[q, i, k] */
        double *Bw = B + w * p;
        for (Py_ssize_t q = 0; q < p; q++) {
            const double *Gq = G + 9 * q;
            double b = 0.0;
            for (int i = 0; i < 3; i++) {
                const double j = -(GEMM3(a[0], a[1], a[2], Gq[3 * i], Gq[3 * i + 1], Gq[3 * i + 2]) + C[i * p + q]);
                b += u[i] * j;
            }
            Bw[q] = b;
        }
        if (V != NULL) {
            /* g = u @ K^-1, var = sum_ij (g_i C_ij) g_j from 0.0 (einsum "mi,mij,mj->m") */
            double g[3], s = 0.0;
            for (int j = 0; j < 3; j++)
                g[j] = GEMM3(u[0], u[1], u[2], Ki[j], Ki[3 + j], Ki[6 + j]);
            const double *Cw = cov + 9 * w;
            for (int i = 0; i < 3; i++)
                for (int j = 0; j < 3; j++) {
                    const double t = g[i] * Cw[3 * i + j];
                    s += t * g[j];
                }
            V[w] = s;
        }
    }
}

#ifdef LANES_AVX2

/* linear_loop on four windows at a time, one per lane of a 256-bit vector: each lane runs the scalar loop's
 * operations in its order (the same products, fused multiply-adds, sums from 0.0, square root and quotients,
 * each correctly rounded as the scalar instruction rounds it), so every window's bits are the scalar loop's;
 * the lanes only let four windows' dependency chains (the norm, then the quotients, then the sums over i)
 * overlap. Windows [0, m - m % 4); the caller runs the rest through linear_loop. */
#define BC(x) _mm256_set1_pd(x)
#define GEMM3V(x0, x1, x2, y0, y1, y2) _mm256_fmadd_pd((x2), (y2), _mm256_fmadd_pd((x1), (y1), _mm256_mul_pd((x0), (y0))))
#define COL4(ptr, stride, off, w) _mm256_set_pd((ptr)[(stride) * ((w) + 3) + (off)], (ptr)[(stride) * ((w) + 2) + (off)], \
                                                (ptr)[(stride) * ((w) + 1) + (off)], (ptr)[(stride) * (w) + (off)])

__attribute__((target("avx2,fma"))) static void linear_lanes(const double *Ki, const double *o, const double *G,
                                                              const double *C, const double *raw, const double *cov,
                                                              double *H, double *B, double *A, double *V, Py_ssize_t m,
                                                              Py_ssize_t p)
{
    const __m256d sign = BC(-0.0), zero = _mm256_setzero_pd();
    for (Py_ssize_t w = 0; w + 4 <= m; w += 4) {
        const __m256d d0 = _mm256_sub_pd(COL4(raw, 3, 0, w), BC(o[0]));
        const __m256d d1 = _mm256_sub_pd(COL4(raw, 3, 1, w), BC(o[1]));
        const __m256d d2 = _mm256_sub_pd(COL4(raw, 3, 2, w), BC(o[2]));
        __m256d a[3], u[3];
        double lane[4];
        for (int i = 0; i < 3; i++) {
            a[i] = GEMM3V(d0, d1, d2, BC(Ki[3 * i]), BC(Ki[3 * i + 1]), BC(Ki[3 * i + 2]));
            _mm256_storeu_pd(lane, a[i]);
            for (int l = 0; l < 4; l++)
                A[3 * (w + l) + i] = lane[l];
        }
        __m256d h = _mm256_mul_pd(a[0], a[0]);
        h = _mm256_add_pd(h, _mm256_mul_pd(a[1], a[1]));
        h = _mm256_add_pd(h, _mm256_mul_pd(a[2], a[2]));
        h = _mm256_sqrt_pd(h);
        _mm256_storeu_pd(H + w, h);
        for (int i = 0; i < 3; i++)
            u[i] = _mm256_div_pd(a[i], h);
        for (Py_ssize_t q = 0; q < p; q++) {
            const double *Gq = G + 9 * q;
            __m256d b = zero;
            for (int i = 0; i < 3; i++) {
                const __m256d s = _mm256_add_pd(GEMM3V(a[0], a[1], a[2], BC(Gq[3 * i]), BC(Gq[3 * i + 1]),
                                                       BC(Gq[3 * i + 2])), BC(C[i * p + q]));
                b = _mm256_add_pd(b, _mm256_mul_pd(u[i], _mm256_xor_pd(s, sign)));
            }
            _mm256_storeu_pd(lane, b);
            for (int l = 0; l < 4; l++)
                B[(w + l) * p + q] = lane[l];
        }
        if (V != NULL) {
            __m256d g[3], s = zero;
            for (int j = 0; j < 3; j++)
                g[j] = GEMM3V(u[0], u[1], u[2], BC(Ki[j]), BC(Ki[3 + j]), BC(Ki[6 + j]));
            for (int i = 0; i < 3; i++)
                for (int j = 0; j < 3; j++) {
                    const __m256d t = _mm256_mul_pd(g[i], COL4(cov, 9, 3 * i + j, w));
                    s = _mm256_add_pd(s, _mm256_mul_pd(t, g[j]));
                }
            _mm256_storeu_pd(V + w, s);
        }
    }
}
#endif

/* linear_loop, four windows at a time where the CPU has AVX2 and FMA */
static void linear_windows(const double *Ki, const double *o, const double *G, const double *C, const double *raw,
                           const double *cov, double *H, double *B, double *A, double *V, Py_ssize_t m, Py_ssize_t p)
{
    Py_ssize_t done = 0;
#ifdef LANES_AVX2
    if (has_lanes()) {
        linear_lanes(Ki, o, G, C, raw, cov, H, B, A, V, m, p);
        done = m - m % 4;
    }
#endif
    linear_loop(Ki, o, G, C, raw + 3 * done, cov ? cov + 9 * done : NULL, H + done, B + p * done, A + 3 * done,
                V ? V + done : NULL, m - done, p);
}

typedef struct {
    const double *Ki, *o, *G, *C, *raw, *cov;
    double *H, *B, *A, *V;
    Py_ssize_t p;
} LinLoop;

static void lin_loop(void *ctx, Py_ssize_t w0, Py_ssize_t w1, int lane)
{
    const LinLoop *x = ctx;
    const Py_ssize_t p = x->p;
    (void)lane;
    linear_windows(x->Ki, x->o, x->G, x->C, x->raw + 3 * w0, x->cov ? x->cov + 9 * w0 : NULL, x->H + w0, x->B + p * w0,
                x->A + 3 * w0, x->V ? x->V + w0 : NULL, w1 - w0, p);
}

/* linear_norm_jacobian(Kinv (3, 3), o (3,), G (P, 3, 3) = K^-1 dK, C (3, P) = (do @ K^-1.T).T, raw (M, 3),
 *                      cov (M, 3, 3) or None, h (M,) out, B (M, P) out, a (M, 3) out, var (M,) out or None, M, P,
 *                      threads=-1) */
JACOBIANS_INTERNAL PyObject *linear_norm_jacobian(PyObject *self, PyObject *args)
{
    PyObject *obj[10];
    Py_ssize_t m, p;
    int threads = -1;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOnn|i", &obj[0], &obj[1], &obj[2], &obj[3], &obj[4], &obj[5], &obj[6],
                          &obj[7], &obj[8], &obj[9], &m, &p, &threads) || threads_arg(threads) < 0)
        return NULL;
    if (m < 2 || p < 1) {
        PyErr_SetString(PyExc_ValueError, "need M >= 2 windows (one row is dgemv's, not dgemm's, order) and P >= 1");
        return NULL;
    }
    if (m > PY_SSIZE_T_MAX / 8 / 9 / p) {
        PyErr_SetString(PyExc_ValueError, "dimensions too large");
        return NULL;
    }
    const int with_var = obj[5] != Py_None;
    if (with_var != (obj[9] != Py_None)) {
        PyErr_SetString(PyExc_ValueError, "cov and var must both be given or both be None");
        return NULL;
    }
    static const char *names[10] = {"Kinv", "o", "G", "C", "raw", "cov", "h", "B", "a", "var"};
    const Py_ssize_t len[10] = {9, 3, 9 * p, 3 * p, 3 * m, 9 * m, m, m * p, 3 * m, m};
    Py_buffer buf[10];
    int held[10] = {0};
    int ok = 1;
    for (int k = 0; k < 10 && ok; k++) {
        if ((k == 5 || k == 9) && !with_var)
            continue;
        ok = get_doubles(obj[k], &buf[k], len[k], k >= 6, names[k]) == 0;
        held[k] = ok;
    }
    if (ok) {
        const double *cov = with_var ? buf[5].buf : NULL;
        double *V = with_var ? buf[9].buf : NULL;
        LinLoop x = {buf[0].buf, buf[1].buf, buf[2].buf, buf[3].buf, buf[4].buf, cov, buf[6].buf, buf[7].buf,
                     buf[8].buf, V, p};
        Py_BEGIN_ALLOW_THREADS
        /* automatic, in the lanes: one thread. A week's 12 000 windows take ~0.2 ms (extended: ~0.6 ms), about
         * what handing chunks to the helper costs, and a helper without a core keeps the caller waiting */
        share_windows(lin_loop, &x, m, threads < 0 && has_lanes() ? 1 : threads);
        Py_END_ALLOW_THREADS
    }
    for (int k = 0; k < 10; k++)
        if (held[k])
            PyBuffer_Release(&buf[k]);
    if (!ok)
        return NULL;
    Py_RETURN_NONE;
}
