/* One call of the C step (daemon/_fastcall.c), shared by daemon/_fastpath.c's step (a descriptor it reads) and
 * take (the bytes of a read the caller made). Linked into gravcal.daemon._fastpath. */
#ifndef GRAVCAL_FASTCALL_H
#define GRAVCAL_FASTCALL_H

#include <Python.h>
#include <stdint.h>

#include "../drivers/_framekernel.h"
#include "_clienttable.h"
#include "_engine.h"
#include "_linekernel.h"

#define MAX_FRAMES_LIMIT 4096

/* ist (int64) and fst (float64) slots: the state shared with daemon/fastpath.py */
enum { IST_EXPECT, IST_SEQ, IST_FRAMES, IST_TICK, IST_UNKNOWN, IST_REASON, IST_CLIENT, IST_SENT, IST_BATCH,
       IST_STAGE_LIMIT, IST_CAN, IST_NOGIL, IST_N }; /* IST_NOGIL: the call's batches delivered without the GIL */
enum { FST_LAST_T, FST_TICK_HZ, FST_T_RECV, FST_TICK_PERIOD, FST_N };
/* why a call returned: due, bytes for the Python path, a delivery for fanout, a watcher that is not plain
   (decimated: fanout's), end of file, a read error */
enum { R_DUE, R_BYTES, R_DELIVERY, R_NOT_PLAIN, R_EOF, R_ERROR };

GRAVCAL_ENGINE_INTERNAL extern const GravcalFrameAPI *gravcal_frame_api;
GRAVCAL_ENGINE_INTERNAL extern const GravcalLineAPI *gravcal_line_api;

typedef struct {
    char *buf;
    Py_ssize_t n, cap;
} Bytes;

typedef struct {
    long long ist[IST_N];
    double fst[FST_N];
} State;

/* One call's arguments and scratch (step and take share everything after the bytes are in hand). */
typedef struct {
    int max_frames;
    Py_buffer ist, fst, rows, acc, gyro, codes;
    PyObject *staged, *leftover, *stopped;
    WatcherBox *box; /* the server's watcher table */
    Engine *engine;  /* the parameters */
    uint32_t *ticks;
    Bytes lines[2];
    Bytes stage;    /* the records taken, appended to ``staged`` at the end (with the GIL: one resize per call) */
    Py_ssize_t had; /* len(staged) at the start */
    State S;
    EngineParams P;         /* the engine's parameters, copied when they change (gravcal_engine_current) */
    long long generation;   /* theirs */
    int started;            /* S holds the caller's state (copied back at the end) */
} Call;

GRAVCAL_ENGINE_INTERNAL double gravcal_now_s(void);
/* room for ``more`` bytes: 0, or -1 out of memory (no exception set: callable without the GIL) */
GRAVCAL_ENGINE_INTERNAL int gravcal_reserve(Bytes *b, Py_ssize_t more);
GRAVCAL_ENGINE_INTERNAL void gravcal_take_gil(PyThreadState **ts);
/* C's arguments checked and its scratch made, with the GIL (box, engine, staged, buffers set by the caller):
   0, or -1 with an exception; call_close in either case */
GRAVCAL_ENGINE_INTERNAL int call_open(Call *C, Py_ssize_t batch_frames);
/* the watcher snapshot for the next bytes, with the GIL: 1 (*snapshot set), 0 none (R_NOT_PLAIN), -1 error */
GRAVCAL_ENGINE_INTERNAL int call_prepare(Call *C, PyObject **snapshot);
/* one read's bytes with the GIL: 1 taken and delivered, 0 stopped, -1 error; consumes ``snapshot`` */
GRAVCAL_ENGINE_INTERNAL int call_process(Call *C, const unsigned char *buf, Py_ssize_t n, PyObject *snapshot);
/* as call_process without the GIL, holding the box's mutex (released here); the GIL is held on return unless 1 */
GRAVCAL_ENGINE_INTERNAL int call_process_nogil(Call *C, const unsigned char *buf, Py_ssize_t n, PyThreadState **ts);
/* (leftover, stopped) or NULL; staged and the state copied back either way */
GRAVCAL_ENGINE_INTERNAL PyObject *call_close(Call *C, int ok);

#endif
