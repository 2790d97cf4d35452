/* The frame kernel's C interface for other kernels (drivers/_framekernel.c exports it as the capsule
 * gravcal.drivers._framekernel._C_API; daemon/_fastpath.c imports it with PyCapsule_Import). */
#ifndef GRAVCAL_FRAMEKERNEL_H
#define GRAVCAL_FRAMEKERNEL_H

#include <stdint.h>

#define GRAVCAL_FRAME_LEN 29
#define GRAVCAL_SAMPLE_SIZE 56 /* one SAMPLE_DTYPE record (core/samples.py) */

typedef struct {
    /* 1 and the frame's raw 16-bit seq and tick when p[0..n) is one intact frame (sync, length, CRC), else 0 */
    int (*header)(const unsigned char *p, Py_ssize_t n, unsigned int *seq, uint32_t *tick);
    /* the SAMPLE_DTYPE record (t NaN) of an intact frame, with the unwrapped seq and the flags */
    void (*to_row)(const unsigned char *frame, unsigned char *row, long long seq, uint16_t flags);
} GravcalFrameAPI;

#define GRAVCAL_FRAME_CAPSULE "gravcal.drivers._framekernel._C_API"

#endif
