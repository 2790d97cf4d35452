/* The correction kernel's C interface for other kernels (core/_correctkernel.c exports it as the capsule
 * gravcal.core._correctkernel._C_API; daemon/_fastpath.c imports it with PyCapsule_Import). */
#ifndef GRAVCAL_CORRECTKERNEL_H
#define GRAVCAL_CORRECTKERNEL_H

typedef struct {
    /* PlainCorrection.one of the 56-byte SAMPLE_DTYPE record ``row``: acc[3] = scale K^-1 (raw - o) from
       offset o[3] and kinv_t[9] (scale K^-T, row-major); *gyro = (counts - bias) / sens; returns its seq */
    long long (*correct)(const unsigned char *row, const double *o, const double *kinv_t, double bias, double sens,
                         double *acc, double *gyro);
} GravcalCorrectAPI;

#define GRAVCAL_CORRECT_CAPSULE "gravcal.core._correctkernel._C_API"

#endif
