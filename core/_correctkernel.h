/* The correction kernel's C interface for other kernels (core/_correctkernel.c exports it as the capsule
 * gravcal.core._correctkernel._C_API; daemon/_engine.c imports it with PyCapsule_Import). */
#ifndef GRAVCAL_CORRECTKERNEL_H
#define GRAVCAL_CORRECTKERNEL_H

#include <Python.h>

/* The correction's parameters as one float64 vector (core/correction.py correction_params writes it; the slot
   names are its CP_* constants): a calibration's reference K and o, K^-T scaled to the output unit, and each
   covariate's coefficients on the offsets and on the diagonal sensitivities (every term the online calibrator
   can publish, by its calibration view's acts_on and covariate). */
enum { COV_TEMP, COV_VSUPPLY, COV_TIME, COV_ACCEL, COV_N }; /* [°C], [V], [h] from t0, diag(K) a0² [g²] */
enum { ON_OFFSET, ON_SENSITIVITY, ON_N };
enum {
    CP_OFFSET = 0,              /* o (3) [duty] */
    CP_KINV_T = 3,              /* scale K^-T (9), row-major */
    CP_K = 12,                  /* K (9) [duty per g], row-major */
    CP_SCALE = 21,              /* g -> the output unit */
    CP_FS = 22,                 /* samples per second: a record's time is seq / fs [s] */
    CP_REF = 23,                /* the covariates' references (COV_TEMP..COV_TIME): °C, V, s */
    CP_USES = 26,               /* per covariate (COV_N): 1 when a term needs it (a NaN covariate then gives NaN) */
    CP_COEF = 30,               /* [ON_N][COV_N][3]: o_i += c z_i, or K_ii += c z_i */
    CP_N = 30 + ON_N * COV_N * 3
};

typedef struct {
    double o[3], kinv_t[9], k[9], scale, fs, ref[3];
    double coef[ON_N][COV_N][3];
    int uses[COV_N];
    int extended;  /* some covariate is used */
    int on_sens;   /* some term acts on the sensitivities: K + diag(dk) is solved per sample */
} GravcalCorrection;

typedef struct {
    /* the vector ``v`` of CP_N float64 checked and unpacked into ``out``: NULL, or why it is not a correction */
    const char *(*unpack)(const double *v, GravcalCorrection *out);
    /* one 56-byte SAMPLE_DTYPE record: acc[3] = scale (K + dK)^-1 (raw - o - do) at its covariates, *gyro =
       (counts - bias) / sens; returns its seq */
    long long (*correct)(const unsigned char *row, const GravcalCorrection *c, double bias, double sens, double *acc,
                         double *gyro);
} GravcalCorrectAPI;

#define GRAVCAL_CORRECT_CAPSULE "gravcal.core._correctkernel._C_API"

#endif
