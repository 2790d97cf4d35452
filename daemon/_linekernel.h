/* The line kernel's C interface for other kernels (daemon/_linekernel.c exports it as the capsule
 * gravcal.daemon._linekernel._C_API; daemon/_fastpath.c imports it with PyCapsule_Import for
 * daemon/_fastcall.c). */
#ifndef GRAVCAL_LINEKERNEL_H
#define GRAVCAL_LINEKERNEL_H

#define GRAVCAL_IMU_LINE_MAX 8192 /* the longest IMU line there is (see _linekernel.c) */

typedef struct {
    /* imu_line's bytes for the 56-byte SAMPLE_DTYPE record ``row`` into out[0..cap): their length, or -1 with a
       Python exception set. ``static_code``: 1 still, 0 moving, <= -1 unknown. Needs the GIL. */
    Py_ssize_t (*line)(const unsigned char *row, const double *acc, double gyro, long long static_code, int raw,
                       char *out, Py_ssize_t cap);
    /* the same without the GIL: the length, or -2 when the line needs the GIL (call ``line`` then) */
    Py_ssize_t (*line_nogil)(const unsigned char *row, const double *acc, double gyro, long long static_code, int raw,
                             char *out, Py_ssize_t cap);
} GravcalLineAPI;

#define GRAVCAL_LINE_CAPSULE "gravcal.daemon._linekernel._C_API"

#endif
