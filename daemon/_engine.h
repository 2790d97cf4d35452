/* The per-sample engine's parameters (daemon/_engine.c, linked into gravcal.daemon._fastpath): what corrects and
 * labels each published sample, set by Python's control plane through one setter, read by the C step and by
 * Engine.correct (the Python path's blocks) alike. */
#ifndef GRAVCAL_ENGINE_H
#define GRAVCAL_ENGINE_H

#include <Python.h>
#include <pthread.h>

#include "../core/_correctkernel.h"

/* internal to gravcal.daemon._fastpath: hidden from other shared objects */
#define GRAVCAL_ENGINE_INTERNAL __attribute__((visibility("hidden")))

/* Engine.set_params' vector: the correction's CP_N slots (core/correction.py correction_params), then these
   (daemon/processing.py writes them; the names are its EP_* constants) */
enum {
    EP_GYRO_BIAS = CP_N, /* [counts] */
    EP_GYRO_SENS,        /* [counts per rad/s] */
    EP_LAST_SEQ,         /* seq of the detector's latest decision */
    EP_HAVE_LAST,        /* 1 when there is one */
    EP_STILL,            /* that decision: 1 still, 0 moving */
    EP_MAX_AGE,          /* the decision labels samples at most this many samples newer; older: unknown */
    EP_N
};

typedef struct {
    GravcalCorrection corr;
    double bias, sens, max_age;
    long long last;
    int have_last, still;
} EngineParams;

/* Engine: the parameters, swapped whole under ``mu``. ``mu`` is a leaf: held only to copy the parameters in or
   out, never while waiting for anything else (the GIL included), so the setter may take it holding the GIL and the
   step without it. ``generation`` counts the swaps (read atomically: a step copies the parameters only when it
   changed). */
typedef struct {
    PyObject_HEAD
    pthread_mutex_t mu;
    long long generation;
    int set;
    EngineParams p;
} Engine;

GRAVCAL_ENGINE_INTERNAL extern PyTypeObject GravcalEngineType;

/* the correction kernel's capsule, imported once (with the GIL): 0, or -1 with an exception */
GRAVCAL_ENGINE_INTERNAL int gravcal_engine_init(void);

/* ``*out`` made the engine's current parameters when ``*generation`` is not theirs; no Python, no GIL needed */
GRAVCAL_ENGINE_INTERNAL void gravcal_engine_current(Engine *e, EngineParams *out, long long *generation);

/* one record corrected into acc[3], *gyro, *code (static: 1 still, 0 moving, -1 unknown); returns its seq */
GRAVCAL_ENGINE_INTERNAL long long gravcal_engine_sample(const EngineParams *p, const unsigned char *row, double *acc,
                                                        double *gyro, signed char *code);

#endif
