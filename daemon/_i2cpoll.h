/* The C step on the I2C bus (daemon/_i2cpoll.c), linked into gravcal.daemon._fastpath. */
#ifndef GRAVCAL_I2CPOLL_H
#define GRAVCAL_I2CPOLL_H

#include <Python.h>

#include "_engine.h"

/* i2c_step's ``bus`` (int64; daemon/fastpath.py IB_*): the driver's transfer set-up, then what the call did */
enum {
    IB_ADDRESS,      /* the logger's 7-bit address */
    IB_FIRST,        /* frames read with STATUS in each poll's one transfer (the watermark's, at most a burst) */
    IB_BURST,        /* frames per burst after it */
    IB_COMBINED,     /* 1: STATUS, FIFO_COUNT and the first frames in one transfer; 0: STATUS first */
    IB_POLL_NS,      /* the poll interval without a DRDY line */
    IB_DRDY_FD,      /* the DRDY line's sysfs value, opened by the driver; -1: polled */
    IB_NEXT_POLL_NS, /* in and out: the FIFO is not asked before (CLOCK_MONOTONIC ns) */
    IB_POLLS,        /* out: STATUS reads */
    IB_BURSTS,       /* out: FIFO_DATA reads */
    IB_OVERFLOW,     /* out: 1 when STATUS reported a FIFO overflow (the frames read went back undecoded) */
    IB_ERRNO,        /* out: the errno of a transfer that failed (reason R_ERROR) */
    IB_N
};

GRAVCAL_ENGINE_INTERNAL PyObject *gravcal_i2c_step(PyObject *self, PyObject *args);

#endif
