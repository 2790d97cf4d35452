/* What the parts of the _jacobians extension share (core/estimators/_jacobians*.c): Python and the buffer
 * helpers, whether the CPU runs the AVX2 lanes, the helper thread that shares a call's windows, and each
 * part's Python entry point for the module's method table. Internal to the extension: its functions are
 * hidden from other shared objects. */
#ifndef GRAVCAL_JACOBIANS_H
#define GRAVCAL_JACOBIANS_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

#include "../_buffers.h"

#define JACOBIANS_INTERNAL __attribute__((visibility("hidden")))

#if defined(__GNUC__) && defined(__x86_64__)
#include <immintrin.h>
#define LANES_AVX2 1 /* four windows per 256-bit vector where the CPU has AVX2 and FMA */
#endif

static inline int has_lanes(void)
{
#ifdef LANES_AVX2
    return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
#else
    return 0;
#endif
}

/* A loop over windows [w0, w1); lane 0 is the caller's thread, 1 the helper's (each has its own scratch). */
typedef void (*LoopFn)(void *ctx, Py_ssize_t w0, Py_ssize_t w1, int lane);

/* _jacobians_share.c: run(ctx, ...) over windows [0, m) on `threads` threads (1, 2, or -1: automatic), called
 * without the GIL; threads_arg checks the argument (-1 and a Python exception when it is not 1, 2 or -1);
 * share_init once, when the module loads. */
JACOBIANS_INTERNAL void share_windows(LoopFn run, void *ctx, Py_ssize_t m, int threads);
JACOBIANS_INTERNAL int threads_arg(int threads);
JACOBIANS_INTERNAL void share_init(void);

JACOBIANS_INTERNAL PyObject *linear_norm_jacobian(PyObject *self, PyObject *args);    /* _jacobians_linear.c */
JACOBIANS_INTERNAL PyObject *extended_accel_jacobian(PyObject *self, PyObject *args); /* _jacobians_extended.c */

#endif
