/* What the parts of the _blockkernels extension share (core/_blockkernels*.c): Python and the buffer
 * helpers, the biquad cascade (Lötters' chain and sosfilt), the per-axis scatter coefficients (Lötters'
 * gate and the moving variance), and each part's Python entry point for the module's method table.
 * Internal to the extension: its entry points are hidden from other shared objects. */
#ifndef GRAVCAL_BLOCKKERNELS_H
#define GRAVCAL_BLOCKKERNELS_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>

#include "_buffers.h"

#define MAX_SECTIONS 8 /* biquads per cascade (order 16): the state lives on the stack */
#define BLOCKKERNELS_INTERNAL __attribute__((visibility("hidden")))

/* the six second moments' axis pairs: (0,0) (1,1) (2,2) (0,1) (0,2) (1,2) */
static const int I6[6] = {0, 1, 2, 0, 0, 1};
static const int J6[6] = {0, 1, 2, 1, 2, 2};

/* Per-axis within-block scatter in g² from the six second moments W_q (fastdetect._axis_var_g): Σ_q c_iq W_q,
 * c_iq = K⁻¹_iI K⁻¹_iJ, twice off the diagonal. */
static inline void axis_scatter_coefficients(const double *K, double cv[3][6])
{
    for (int i = 0; i < 3; i++)
        for (int p = 0; p < 6; p++)
            cv[i][p] = K[3 * i + I6[p]] * K[3 * i + J6[p]] * (I6[p] == J6[p] ? 1.0 : 2.0);
}

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

BLOCKKERNELS_INTERNAL PyObject *block_pass(PyObject *self, PyObject *args);         /* _blockkernels_pass.c */
BLOCKKERNELS_INTERNAL PyObject *lotters_chain(PyObject *self, PyObject *args);      /* _blockkernels_lotters.c */
BLOCKKERNELS_INTERNAL PyObject *chain_lanes(PyObject *self, PyObject *unused);      /* _blockkernels_lotters.c */
BLOCKKERNELS_INTERNAL PyObject *variance_chain(PyObject *self, PyObject *args);     /* _blockkernels_variance.c */
BLOCKKERNELS_INTERNAL PyObject *window_sums(PyObject *self, PyObject *args);        /* _blockkernels_windows.c */

#endif
