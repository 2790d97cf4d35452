/* The frame kernel's C interface for other kernels (drivers/_framekernel.c exports it as the capsule
 * gravcal.drivers._framekernel._C_API; daemon/_fastpath.c imports it with PyCapsule_Import for
 * daemon/_fastcall.c). */
#ifndef GRAVCAL_FRAMEKERNEL_H
#define GRAVCAL_FRAMEKERNEL_H

#include <stdint.h>

#define GRAVCAL_FRAME_LEN 29
#define GRAVCAL_SAMPLE_SIZE 56 /* one SAMPLE_DTYPE record (core/samples.py) */

typedef struct {
    /* the SAMPLE_DTYPE record (t NaN) of an intact frame, with the unwrapped seq and the flags */
    void (*to_row)(const unsigned char *frame, unsigned char *row, long long seq, uint16_t flags);
    /* The records of one read buf[0..n) when it is exactly k <= max_frames intact frames whose raw seq continue
       ``expect`` one by one, numbered from ``seq0`` and stamped from ``t_recv`` as the driver stamps a read
       (*last_t: the newest stamp so far, updated); their ticks into ``ticks``. k, or 0 (nothing written). */
    Py_ssize_t (*continuing)(const unsigned char *buf, Py_ssize_t n, long long expect, Py_ssize_t max_frames,
                             long long seq0, double tick_hz, double t_recv, double *last_t, unsigned char *rows,
                             uint32_t *ticks);
    /* As ``continuing`` for slcan bytes (drivers/can.py): exactly k <= max_samples samples, each the four
       standard-frame lines of ids base_id..base_id+3 in order. k, or 0 (nothing written). */
    Py_ssize_t (*slcan_continuing)(const unsigned char *buf, Py_ssize_t n, long long base_id, long long expect,
                                   Py_ssize_t max_samples, long long seq0, double tick_hz, double t_recv,
                                   double *last_t, unsigned char *rows, uint32_t *ticks);
} GravcalFrameAPI;

#define GRAVCAL_FRAME_CAPSULE "gravcal.drivers._framekernel._C_API"

#endif
