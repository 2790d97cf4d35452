/* gravcald's latency path in one C call per wake-up: bus bytes -> frames -> correction -> IMU lines -> sockets.
 *
 * step(fd, seconds, max_frames, ist, fst, staged, server, processor, rows, acc, gyro, static)
 *     -> (leftover bytes, the watcher snapshot of a stopped delivery or None)
 * take(data, max_frames, ist, ...)  the same for the bytes of one read the caller made (the I2C FIFO)
 *
 * It composes the per-layer kernels in pipeline order, each imported from its own module as a capsule:
 * the frame check and record (drivers/_framekernel.c), the plain correction (core/_correctkernel.c), the
 * IMU line (daemon/_linekernel.c). daemon/fastpath.py calls it and does everything else; it takes only the
 * common case and returns, having consumed nothing of it, whatever the Python path must decide:
 *
 *   - bytes: a read that is not exactly whole intact frames, each continuing the stream by one (the
 *     SeqUnwrapper's rule 2 with a step of 1: no gap, no stray, no restart; the 16-bit counter may wrap),
 *     or more frames than max_frames: returned as leftover, the driver decodes them as it always does;
 *     with ist[IST_CAN] = 1 + a CAN base id the bytes are slcan lines and a "frame" is a CAN sample's four lines
 *     (the frame kernel's slcan_continuing: anything else is handed back to python-can's reader);
 *   - watchers: delivery only to the snapshot ``server.fast_watchers``, the one item of the list
 *     ``server.fast_box`` (watching every sample, read per wake-up; None: some watcher is not plain). A watcher that is closed or whose output is not empty, or
 *     whose policy changed (both told by its ClientRecord's gate, below), or whose socket does not take the
 *     whole block stops the delivery: its lock stays held and the snapshot is returned, so fastpath.py
 *     queues the rest in order (fanout's bookkeeping);
 *   - an extended calibration (processor.correction[1] is not None), end of file or a read error.
 *
 * Per batch (the frames of one read) it does what the Python path does for the same block, in order: the
 *   frame kernel checks that the frames continue the stream and writes their records, stamped as
 *   Driver._stamp does; Processor.correct: the plain correction and the static code (the detector's decision
 *   while at most max_age samples old, else unknown); SocketServer.publish: one joined block of lines per
 *   encoding, one non-blocking send() per watcher in snapshot order under the client's lock;
 *   Gravcald._acquire: the records appended to ``staged`` (the analysis' bytes). It returns at the latest
 *   after ``seconds`` or once ``staged`` holds ist[IST_STAGE_LIMIT] bytes, for the Python loop's housekeeping.
 * step holds the GIL only for what needs Python (see step and "Locks" in _clienttable.h); take holds it throughout.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <errno.h>
#include <math.h>
#include <poll.h>
#include <pthread.h>
#include <sys/epoll.h>
#include <stdint.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include "../core/_correctkernel.h"
#include "../drivers/_framekernel.h"
#include "_clienttable.h"
#include "_linekernel.h"

#define READ_BYTES 65536 /* drivers/serial.py READ_BYTES: more than the kernel's tty buffer holds */
#define MAX_FRAMES_LIMIT 4096
#define SLCAN_SAMPLE_BYTES 78 /* a CAN sample's four slcan lines: t<id><dlc><hex>\r with dlc 8, 7, 7, 5 */
#define TTY_CHUNK 64 /* tty_read's kernel buffer (drivers/tty/tty_io.c): the line discipline is asked per 64 bytes */

/* ist (int64) and fst (float64) slots: the state shared with daemon/fastpath.py */
enum { IST_EXPECT, IST_SEQ, IST_FRAMES, IST_TICK, IST_UNKNOWN, IST_REASON, IST_CLIENT, IST_SENT, IST_BATCH,
       IST_STAGE_LIMIT, IST_CAN, IST_NOGIL, IST_N }; /* IST_NOGIL: the call's batches delivered without the GIL */
enum { FST_LAST_T, FST_TICK_HZ, FST_T_RECV, FST_MAX_AGE, FST_TICK_PERIOD, FST_N };
enum { R_DUE, R_BYTES, R_DELIVERY, R_NOT_PLAIN, R_EOF, R_ERROR };

/* attribute names, interned once: a lookup is then a pointer comparison */
static PyObject *s_fast_box, *s_correction, *s_gyro_correction, *s_analysed, *s_offset, *s_kinv_t,
    *s_params_generation;

/* call a lock's bound ``release`` keeping the pending exception, if any: 0, or -1 when the release failed */
static int release_keeping_error(PyObject *release)
{
    PyObject *type, *value, *tb;
    PyErr_Fetch(&type, &value, &tb);
    PyObject *r = PyObject_CallNoArgs(release);
    if (r == NULL) {
        Py_XDECREF(type);
        Py_XDECREF(value);
        Py_XDECREF(tb);
        return -1;
    }
    Py_DECREF(r);
    PyErr_Restore(type, value, tb);
    return 0;
}

static const GravcalFrameAPI *frame_api;
static const GravcalCorrectAPI *correct_api;
static const GravcalLineAPI *line_api;

static double now_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts); /* time.monotonic()'s clock */
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

typedef struct {
    char *buf;
    Py_ssize_t n, cap;
} Bytes;

/* room for ``more`` bytes: 0, or -1 out of memory (no exception set: callable without the GIL) */
static int reserve(Bytes *b, Py_ssize_t more)
{
    if (b->n + more <= b->cap)
        return 0;
    Py_ssize_t cap = b->cap ? b->cap : 4096;
    while (cap < b->n + more)
        cap *= 2;
    char *p = PyMem_RawRealloc(b->buf, (size_t)cap);
    if (p == NULL)
        return -1;
    b->buf = p;
    b->cap = cap;
    return 0;
}

/* What Processor.correct reads per block: the plain correction's offset and K^-T, the gyro's (bias, sens), the
   detector's latest decision. Read again only when processor.params_generation (bumped by the processor after
   it swaps one of the three tuples) differs from ``generation``; the arrays copied only when the processor
   swapped the correction's tuple. */
typedef struct {
    PyObject *correction, *gyro; /* the tuples the values below were copied from (strong references) */
    double o[3], k[9], bias, sens;
    int have_last, still;
    long long last;
    int loaded;           /* the values are the plain correction of ``generation`` */
    long long generation; /* processor.params_generation[0] when they were read */
} Params;

static int copy_floats(PyObject *owner, PyObject *name, double *out, Py_ssize_t n)
{
    PyObject *a = PyObject_GetAttr(owner, name);
    if (a == NULL)
        return -1;
    Py_buffer v;
    int rc = PyObject_GetBuffer(a, &v, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT);
    Py_DECREF(a);
    if (rc < 0)
        return -1;
    rc = 0;
    if (v.len != n * 8 || v.itemsize != 8 || v.format == NULL || strchr(v.format, 'd') == NULL) {
        PyErr_Format(PyExc_TypeError, "fastpath: %U must hold %zd float64", name, n);
        rc = -1;
    } else {
        memcpy(out, v.buf, (size_t)(n * 8));
    }
    PyBuffer_Release(&v);
    return rc;
}

static PyObject *pair_of(PyObject *owner, PyObject *name)
{
    PyObject *t = PyObject_GetAttr(owner, name);
    if (t != NULL && (!PyTuple_Check(t) || PyTuple_GET_SIZE(t) != 2)) {
        PyErr_Format(PyExc_TypeError, "fastpath: %U must be a pair", name);
        Py_CLEAR(t);
    }
    return t;
}

/* 1 plain, 0 extended (the Python path's), -1 error */
static int load_params(PyObject *processor, Params *p)
{
    PyObject *corr = pair_of(processor, s_correction);
    if (corr == NULL)
        return -1;
    if (PyTuple_GET_ITEM(corr, 1) != Py_None) {
        Py_DECREF(corr);
        return 0;
    }
    if (corr != p->correction) {
        PyObject *plain = PyTuple_GET_ITEM(corr, 0);
        if (copy_floats(plain, s_offset, p->o, 3) < 0 || copy_floats(plain, s_kinv_t, p->k, 9) < 0) {
            Py_DECREF(corr);
            return -1;
        }
        Py_XSETREF(p->correction, corr);
    } else {
        Py_DECREF(corr);
    }
    PyObject *gyro = pair_of(processor, s_gyro_correction);
    if (gyro == NULL)
        return -1;
    if (gyro != p->gyro) {
        p->bias = PyFloat_AsDouble(PyTuple_GET_ITEM(gyro, 0));
        p->sens = PyFloat_AsDouble(PyTuple_GET_ITEM(gyro, 1));
        Py_XSETREF(p->gyro, gyro);
        if (PyErr_Occurred()) {
            Py_CLEAR(p->gyro);
            return -1;
        }
    } else {
        Py_DECREF(gyro);
    }
    PyObject *analysed = pair_of(processor, s_analysed);
    if (analysed == NULL)
        return -1;
    PyObject *last = PyTuple_GET_ITEM(analysed, 0);
    p->have_last = last != Py_None;
    p->last = p->have_last ? PyLong_AsLongLong(last) : 0;
    p->still = PyObject_IsTrue(PyTuple_GET_ITEM(analysed, 1));
    Py_DECREF(analysed);
    return PyErr_Occurred() || p->still < 0 ? -1 : 1;
}

/* Processor._static_code: the detector's decision while at most max_age samples older than seq, else unknown */
static long long static_code(const Params *p, long long seq, double max_age)
{
    return p->have_last && (double)(seq - p->last) <= max_age ? p->still : -1;
}

/* fanout.deliver's plain case for one watcher: 1 sent whole (counted in its record), 2 stopped with the lock held
   (*sent: bytes the socket took, -1: not tried; a closed client too: fanout skips it), -1 error (lock released) */
static int deliver_one(PyObject *entry, const Bytes *lines, long long k, double now, Py_ssize_t *sent)
{
    if (!PyTuple_Check(entry) || PyTuple_GET_SIZE(entry) != ENTRY_N ||
        !PyObject_TypeCheck(PyTuple_GET_ITEM(entry, ENTRY_RECORD), &GravcalClientRecordType)) {
        PyErr_SetString(PyExc_TypeError, "fastpath: a watcher entry is (client, ClientRecord, fd, raw, watch, "
                                         "lock.acquire, lock.release_unchanged)");
        return -1;
    }
    ClientRecord *rec = (ClientRecord *)PyTuple_GET_ITEM(entry, ENTRY_RECORD);
    PyObject *watch = PyTuple_GET_ITEM(entry, ENTRY_WATCH);
    long fd = PyLong_AsLong(PyTuple_GET_ITEM(entry, ENTRY_FD));
    int raw = PyObject_IsTrue(PyTuple_GET_ITEM(entry, ENTRY_RAW));
    if ((fd == -1 && PyErr_Occurred()) || raw < 0)
        return -1;
    PyObject *r = PyObject_CallNoArgs(PyTuple_GET_ITEM(entry, ENTRY_ACQUIRE));
    if (r == NULL)
        return -1;
    Py_DECREF(r);
    *sent = -1;
    /* the gate, exact while the lock is held: None (closed or output pending: fanout decides, which skips a
       closed client and queues behind pending output) or a policy other than the snapshot's (changed) */
    if (rec->policy != watch)
        return 2;
    const Bytes *b = &lines[raw];
    ssize_t s = send((int)fd, b->buf, (size_t)b->n, MSG_NOSIGNAL | MSG_DONTWAIT);
    if (s != b->n) {
        *sent = s > 0 ? s : 0; /* EAGAIN, EPIPE, a partial send: fanout's bookkeeping */
        return 2;
    }
    rec->sent_messages += k; /* fanout.deliver: c.sent_messages += n; c.sent_bytes += sent; c.last_progress = now */
    rec->sent_bytes += s;
    rec->last_progress = now;
    return release_keeping_error(PyTuple_GET_ITEM(entry, ENTRY_RELEASE)) < 0 ? -1 : 1;
}

typedef struct {
    long long ist[IST_N];
    double fst[FST_N];
} State;

/* One read's records (written and stamped by the frame kernel) through correction and staging, as
   Processor.correct and Gravcald._acquire do: the acceleration a = K^-T applied to (raw - o) and the gyro rate
   (core/_correctkernel.c), the static code, the records appended to the staging area. No Python: runs with or
   without the GIL, under gravcal_latest_mu (the arrays ?POLL reads). */
static void correct_batch(State *S, long long *live_ist, Py_ssize_t k, const uint32_t *ticks, const Params *P,
                          double t_recv, unsigned char *rows, double *acc, double *gyro, signed char *codes, Bytes *stage)
{
    for (Py_ssize_t i = 0; i < k; i++) {
        long long seq = correct_api->correct(rows + i * GRAVCAL_SAMPLE_SIZE, P->o, P->k, P->bias, P->sens, acc + 3 * i,
                                             gyro + i);
        long long code = static_code(P, seq, S->fst[FST_MAX_AGE]);
        codes[i] = (signed char)code;
        S->ist[IST_UNKNOWN] += code < 0;
    }
    /* room for a whole batch is kept by call_open and the step's stage check */
    memcpy(stage->buf + stage->n, rows, (size_t)(k * GRAVCAL_SAMPLE_SIZE));
    stage->n += k * GRAVCAL_SAMPLE_SIZE;
    S->ist[IST_EXPECT] = (S->ist[IST_EXPECT] + k) & 0xFFFF;
    S->ist[IST_SEQ] += k;
    S->ist[IST_FRAMES] += k;
    S->ist[IST_BATCH] = k;
    live_ist[IST_BATCH] = k; /* ?POLL reads the newest batch's last record meanwhile (under gravcal_latest_mu) */
    S->ist[IST_TICK] = ticks[k - 1];
    if (k >= 2) /* SeqUnwrapper._learn_ticks: device ticks per sample */
        S->fst[FST_TICK_PERIOD] = (double)(uint32_t)(ticks[k - 1] - ticks[0]) / (double)(k - 1);
    S->fst[FST_T_RECV] = t_recv;
}

/* The batch's IMU lines per encoding a watcher needs (ImuBlock.joined): 0; -1 with an exception (with the GIL);
   -2 without the GIL when a line needs it (call again with nogil 0) */
static int batch_lines(Py_ssize_t k, const unsigned char *rows, const double *acc, const double *gyro,
                       const signed char *codes, const int need[2], Bytes lines[2], int nogil)
{
    for (int raw = 0; raw < 2; raw++) {
        lines[raw].n = 0;
        for (Py_ssize_t i = 0; need[raw] && i < k; i++) {
            if (reserve(&lines[raw], GRAVCAL_IMU_LINE_MAX) < 0) {
                if (nogil)
                    return -2;
                PyErr_NoMemory();
                return -1;
            }
            const unsigned char *row = rows + i * GRAVCAL_SAMPLE_SIZE;
            char *out = lines[raw].buf + lines[raw].n;
            Py_ssize_t cap = lines[raw].cap - lines[raw].n,
                       m = nogil ? line_api->line_nogil(row, acc + 3 * i, gyro[i], codes[i], raw, out, cap)
                                 : line_api->line(row, acc + 3 * i, gyro[i], codes[i], raw, out, cap);
            if (m < 0)
                return (int)m;
            lines[raw].n += m;
        }
    }
    return 0;
}

/* the encodings the watchers of a snapshot tuple need (with the GIL): 0, or -1 with an exception */
static int snapshot_need(PyObject *snapshot, int need[2])
{
    need[0] = need[1] = 0;
    for (Py_ssize_t j = 0; j < PyTuple_GET_SIZE(snapshot); j++) {
        PyObject *e = PyTuple_GET_ITEM(snapshot, j);
        int raw =
            PyTuple_Check(e) && PyTuple_GET_SIZE(e) == ENTRY_N ? PyObject_IsTrue(PyTuple_GET_ITEM(e, ENTRY_RAW)) : 0;
        if (raw < 0)
            return -1;
        need[raw] = 1;
    }
    return 0;
}

static int check_len(const Py_buffer *b, Py_ssize_t need, const char *what)
{
    if (b->len >= need)
        return 0;
    PyErr_Format(PyExc_ValueError, "fastpath: %s holds %zd bytes, needs %zd", what, b->len, need);
    return -1;
}

/* One call's arguments and scratch (step and take share everything after the bytes are in hand). */
typedef struct {
    int max_frames;
    Py_buffer ist, fst, rows, acc, gyro, codes;
    PyObject *staged, *server, *processor, *leftover, *stopped;
    uint32_t *ticks;
    Bytes lines[2];
    Bytes stage; /* the records taken, appended to ``staged`` at the end (with the GIL: one resize per call) */
    Py_ssize_t had; /* len(staged) at the start */
    State S;
    Params P;
    Py_buffer generation; /* processor.params_generation: one int64 */
    WatcherBox *box;      /* server.fast_box */
    int started; /* S holds the caller's state (copied back at the end) */
} Call;

/* ``batch_frames``: the most frames one batch of this call can hold (the stage keeps room for one beyond the
   stage limit) */
static int call_open(Call *C, Py_ssize_t batch_frames)
{
    C->leftover = NULL;
    C->stopped = Py_NewRef(Py_None);
    C->ticks = NULL;
    C->lines[0] = C->lines[1] = C->stage = (Bytes){NULL, 0, 0};
    C->P = (Params){NULL, NULL};
    C->generation.obj = NULL;
    C->box = NULL;
    C->started = 0;
    if (C->max_frames < 1 || C->max_frames > MAX_FRAMES_LIMIT) {
        PyErr_SetString(PyExc_ValueError, "fastpath: needs 1 <= max_frames <= 4096");
        return -1;
    }
    if (check_len(&C->ist, IST_N * 8, "ist") || check_len(&C->fst, FST_N * 8, "fst") ||
        check_len(&C->rows, (Py_ssize_t)C->max_frames * GRAVCAL_SAMPLE_SIZE, "rows") ||
        check_len(&C->acc, (Py_ssize_t)C->max_frames * 24, "acc") ||
        check_len(&C->gyro, (Py_ssize_t)C->max_frames * 8, "gyro") || check_len(&C->codes, C->max_frames, "static"))
        return -1;
    PyObject *gen = PyObject_GetAttr(C->processor, s_params_generation);
    int rc = gen == NULL ? -1 : PyObject_GetBuffer(gen, &C->generation, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT);
    Py_XDECREF(gen);
    if (rc < 0) {
        C->generation.obj = NULL;
        return -1;
    }
    if (C->generation.len != 8 || C->generation.itemsize != 8 || C->generation.format == NULL ||
        strpbrk(C->generation.format, "lq") == NULL || ((uintptr_t)C->generation.buf & 7) != 0) {
        PyErr_SetString(PyExc_TypeError, "fastpath: processor.params_generation must be one aligned int64");
        return -1;
    }
    PyObject *box = PyObject_GetAttr(C->server, s_fast_box);
    if (box == NULL)
        return -1;
    if (!PyObject_TypeCheck(box, &GravcalWatcherBoxType)) {
        Py_DECREF(box);
        PyErr_SetString(PyExc_TypeError, "fastpath: server.fast_box must be a WatcherBox (daemon/_fastpath.c)");
        return -1;
    }
    C->box = (WatcherBox *)box;
    C->ticks = PyMem_Malloc(sizeof(uint32_t) * (size_t)C->max_frames);
    if (C->ticks == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    State *S = &C->S;
    memcpy(S->ist, C->ist.buf, sizeof S->ist);
    memcpy(S->fst, C->fst.buf, sizeof S->fst);
    /* the stage: what the step may add before its stage check stops it, and one batch (take's only one) */
    C->had = PyByteArray_GET_SIZE(C->staged);
    long long room = batch_frames < C->max_frames ? 0 : S->ist[IST_STAGE_LIMIT] - C->had;
    batch_frames = batch_frames < C->max_frames ? batch_frames : C->max_frames;
    if (reserve(&C->stage, (room > 0 ? (Py_ssize_t)room : 0) + batch_frames * GRAVCAL_SAMPLE_SIZE) < 0) {
        PyErr_NoMemory();
        return -1;
    }
    S->ist[IST_FRAMES] = S->ist[IST_UNKNOWN] = S->ist[IST_NOGIL] = 0;
    S->ist[IST_CLIENT] = S->ist[IST_SENT] = -1;
    S->ist[IST_REASON] = R_DUE;
    C->started = 1;
    /* the parameters now, while the caller holds the GIL: the first wake-up needs it only when they change */
    C->P.generation = *(const long long *)C->generation.buf;
    int plain = load_params(C->processor, &C->P);
    C->P.loaded = plain == 1;
    return plain < 0 ? -1 : 0;
}

/* The watcher snapshot and the correction for the next bytes, with the GIL: 1 plain (*snapshot set), 0 not (the
   Python path's: reason R_NOT_PLAIN), -1 error */
static int call_prepare(Call *C, PyObject **snapshot)
{
    PyObject *snap = Py_NewRef(C->box->item); /* per wake-up: a pointer read */
    if (snap != Py_None && !PyTuple_Check(snap)) {
        Py_DECREF(snap);
        PyErr_SetString(PyExc_TypeError, "fastpath: server.fast_watchers must be a tuple or None");
        return -1;
    }
    Params *P = &C->P;
    long long generation = *(const long long *)C->generation.buf;
    int plain = snap == Py_None ? 0 : P->loaded && P->generation == generation ? 1 : load_params(C->processor, P);
    P->loaded = plain == 1;
    P->generation = generation;
    if (plain != 1) {
        Py_DECREF(snap);
        if (plain == 0)
            C->S.ist[IST_REASON] = R_NOT_PLAIN;
        return plain;
    }
    *snapshot = snap;
    return 1;
}

/* The frames of one read, corrected and staged (the frame kernel, then correct_batch), under gravcal_latest_mu: their
   count, 0 when the bytes are not such frames (nothing consumed). With or without the GIL. */
static Py_ssize_t call_frames(Call *C, const unsigned char *buf, Py_ssize_t n, double t_recv)
{
    State *S = &C->S;
    /* the records source: ist[IST_CAN] 0 the serial frames, else slcan lines of CAN samples from base id - 1 */
    long long can_base = S->ist[IST_CAN] - 1;
    pthread_mutex_lock(&gravcal_latest_mu); /* held by no thread that waits for the GIL: a plain wait */
    Py_ssize_t k = can_base < 0 ? frame_api->continuing(buf, n, S->ist[IST_EXPECT], C->max_frames, S->ist[IST_SEQ],
                                                        S->fst[FST_TICK_HZ], t_recv, &S->fst[FST_LAST_T],
                                                        C->rows.buf, C->ticks)
                                : frame_api->slcan_continuing(buf, n, can_base, S->ist[IST_EXPECT], C->max_frames,
                                                              S->ist[IST_SEQ], S->fst[FST_TICK_HZ], t_recv,
                                                              &S->fst[FST_LAST_T], C->rows.buf, C->ticks);
    if (k > 0)
        correct_batch(S, C->ist.buf, k, C->ticks, &C->P, t_recv, C->rows.buf, C->acc.buf, C->gyro.buf, C->codes.buf,
                      &C->stage);
    pthread_mutex_unlock(&gravcal_latest_mu);
    return k;
}

/* One read's bytes with the GIL: 1 taken and delivered, 0 stopped (bytes handed back, or a delivery for fanout),
   -1 error. Consumes the reference to ``snapshot``. */
static int call_process(Call *C, const unsigned char *buf, Py_ssize_t n, PyObject *snapshot)
{
    State *S = &C->S;
    double t_recv = now_s();
    Py_ssize_t k = call_frames(C, buf, n, t_recv);
    if (k == 0) {
        Py_DECREF(snapshot);
        C->leftover = PyBytes_FromStringAndSize((const char *)buf, n);
        S->ist[IST_REASON] = R_BYTES;
        return C->leftover == NULL ? -1 : 0;
    }
    int need[2];
    if (snapshot_need(snapshot, need) < 0 ||
        batch_lines(k, C->rows.buf, C->acc.buf, C->gyro.buf, C->codes.buf, need, C->lines, 0) < 0) {
        Py_DECREF(snapshot);
        return -1;
    }
    for (Py_ssize_t j = 0; j < PyTuple_GET_SIZE(snapshot); j++) {
        Py_ssize_t sent;
        int d = deliver_one(PyTuple_GET_ITEM(snapshot, j), C->lines, k, t_recv, &sent);
        if (d < 0) {
            Py_DECREF(snapshot);
            return -1;
        }
        if (d == 2) {
            S->ist[IST_CLIENT] = j;
            S->ist[IST_SENT] = sent;
            S->ist[IST_REASON] = R_DELIVERY;
            Py_SETREF(C->stopped, snapshot);
            return 0;
        }
    }
    Py_DECREF(snapshot);
    return 1;
}

static void take_gil(PyThreadState **ts)
{
    if (*ts != NULL) {
        PyEval_RestoreThread(*ts);
        *ts = NULL;
    }
}

/* One read's bytes without the GIL, called holding the box's mutex (released here), its table ready and the
   parameters current: as call_process, each watcher's lock tried, never waited for. The GIL is taken only for
   what needs Python: bytes that are not frames (handed back), a line beyond the integer formatting, a stopped
   delivery (a busy lock, a closed gate, a short send: the snapshot and that client's lock go to fanout as from
   call_process). 1, 0 or -1 as call_process; the GIL is held on return unless 1. */
static int call_process_nogil(Call *C, const unsigned char *buf, Py_ssize_t n, PyThreadState **ts)
{
    State *S = &C->S;
    WatcherBox *box = C->box;
    double t_recv = now_s();
    Py_ssize_t k = call_frames(C, buf, n, t_recv);
    if (k == 0) {
        pthread_mutex_unlock(&box->mu);
        take_gil(ts);
        C->leftover = PyBytes_FromStringAndSize((const char *)buf, n);
        S->ist[IST_REASON] = R_BYTES;
        return C->leftover == NULL ? -1 : 0;
    }
    int rc = batch_lines(k, C->rows.buf, C->acc.buf, C->gyro.buf, C->codes.buf, box->need, C->lines, 1);
    if (rc == -2) { /* the box's mutex held while taking the GIL: allowed (see "Locks" in _clienttable.h) */
        take_gil(ts);
        rc = batch_lines(k, C->rows.buf, C->acc.buf, C->gyro.buf, C->codes.buf, box->need, C->lines, 0);
    }
    if (rc < 0) {
        pthread_mutex_unlock(&box->mu);
        take_gil(ts);
        return -1;
    }
    for (Py_ssize_t j = 0; j < box->n; j++) {
        const Watcher *w = &box->w[j];
        ClientRecord *rec = w->rec;
        Py_ssize_t sent = -1;
        int held = pthread_mutex_trylock(&rec->mu) == 0;
        /* deliver_one's gate and send: the policy pointer, compared only (the snapshot keeps ``watch`` alive) */
        if (held && rec->policy == w->watch) {
            const Bytes *b = &C->lines[w->raw];
            ssize_t s = send(w->fd, b->buf, (size_t)b->n, MSG_NOSIGNAL | MSG_DONTWAIT);
            if (s == b->n) {
                rec->sent_messages += k; /* fanout.deliver's counters for a block taken whole */
                rec->sent_bytes += s;
                rec->last_progress = t_recv;
                pthread_mutex_unlock(&rec->mu);
                continue;
            }
            sent = s > 0 ? s : 0;
        }
        take_gil(ts);
        PyObject *snapshot = Py_NewRef(box->item);
        pthread_mutex_unlock(&box->mu);
        if (!held) { /* the lock is busy (the server thread is at this client): wait for it as fanout would */
            if (!gravcal_lock_with_gil(&rec->mu, 1, -1.0)) {
                Py_DECREF(snapshot);
                PyErr_SetString(PyExc_RuntimeError, "fastpath: a client's lock could not be taken");
                return -1;
            }
        }
        S->ist[IST_CLIENT] = j;
        S->ist[IST_SENT] = sent;
        S->ist[IST_REASON] = R_DELIVERY;
        Py_SETREF(C->stopped, snapshot);
        return 0;
    }
    pthread_mutex_unlock(&box->mu);
    S->ist[IST_NOGIL] += *ts != NULL; /* the whole batch without the GIL */
    return 1;
}

/* (leftover, stopped) or NULL; the records staged and the state copied back either way (what was consumed stays
   accounted) */
static PyObject *call_close(Call *C, int ok)
{
    PyObject *result = NULL;
    if (C->stage.n > 0) {
        PyObject *type, *value, *tb;
        PyErr_Fetch(&type, &value, &tb);
        Py_ssize_t had = PyByteArray_GET_SIZE(C->staged);
        if (PyByteArray_Resize(C->staged, had + C->stage.n) == 0)
            memcpy(PyByteArray_AS_STRING(C->staged) + had, C->stage.buf, (size_t)C->stage.n);
        else if (type == NULL)
            ok = 0; /* the records are lost: MemoryError */
        else
            PyErr_Clear();
        if (type != NULL)
            PyErr_Restore(type, value, tb);
    }
    if (ok) {
        if (C->leftover == NULL)
            C->leftover = PyBytes_FromStringAndSize(NULL, 0);
        if (C->leftover != NULL)
            result = PyTuple_Pack(2, C->leftover, C->stopped);
    }
    if (result == NULL && C->stopped != Py_None) /* the stopped watcher's lock is not handed over: release it */
        release_keeping_error(PyTuple_GET_ITEM(PyTuple_GET_ITEM(C->stopped, C->S.ist[IST_CLIENT]), ENTRY_RELEASE));
    if (C->started) {
        memcpy(C->ist.buf, C->S.ist, sizeof C->S.ist);
        memcpy(C->fst.buf, C->S.fst, sizeof C->S.fst);
    }
    Py_XDECREF(C->leftover);
    Py_XDECREF(C->box);
    Py_DECREF(C->stopped);
    Py_XDECREF(C->P.correction);
    Py_XDECREF(C->P.gyro);
    PyMem_Free(C->ticks);
    PyMem_RawFree(C->lines[0].buf);
    PyMem_RawFree(C->lines[1].buf);
    PyMem_RawFree(C->stage.buf);
    PyBuffer_Release(&C->ist);
    PyBuffer_Release(&C->fst);
    PyBuffer_Release(&C->rows);
    PyBuffer_Release(&C->acc);
    PyBuffer_Release(&C->gyro);
    PyBuffer_Release(&C->codes);
    if (C->generation.obj != NULL)
        PyBuffer_Release(&C->generation);
    return result;
}

/* Everything that had arrived on fd, without the GIL: its length, 0 end of file, -1 with errno.
   Never ask a tty for more than it holds: n_tty_read, short of VMIN in the 64-byte chunk tty_read hands it last
   (the 14 bytes after the first 64 of a 78-byte slcan sample), waits for the tty's flush work still running after
   the wake-up: a second sleep and wake-up. So one chunk first (a 29-byte frame: all there was, one read), and
   while a read filled what it asked, FIONREAD says how much more to take. What arrives later queues the next
   epoll event. */
static ssize_t read_arrived(int fd, unsigned char *buf, ssize_t unit)
{
    size_t ask = TTY_CHUNK;
    ssize_t n = read(fd, buf, ask);
    if (n <= 0)
        return n;
    int avail;
    ssize_t last = n;
    while ((size_t)last == ask && n < READ_BYTES && ioctl(fd, FIONREAD, &avail) == 0 && avail > 0) {
        ask = (size_t)avail < (size_t)(READ_BYTES - n) ? (size_t)avail : (size_t)(READ_BYTES - n);
        last = read(fd, buf + n, ask);
        if (last <= 0)
            break;
        n += last;
    }
    /* A read that ends inside a frame (a CAN sample's lines) may have come while the tty's flush work was still
       delivering the rest: one more read, which waits for that work, keeps the batch whole and in C (the frame
       kernel takes only whole frames); anything else (a stray byte) costs one read that finds nothing. */
    if (n % unit && n < READ_BYTES && (last = read(fd, buf + n, (size_t)(READ_BYTES - n))) > 0)
        n += last;
    return n;
}

/* step(fd, seconds, ...): wait on fd and read it, until due or stopped. The GIL is released for the whole loop and
   taken only when a wake-up needs Python: the first of the call (the parameters are read), a changed
   params_generation or a box that is not ready (call_prepare and call_process, as with the GIL throughout), and
   what call_process_nogil hands to Python. */
static PyObject *step(PyObject *self, PyObject *args)
{
    int fd;
    double seconds;
    Call C;
    if (!PyArg_ParseTuple(args, "idiw*w*O!OOw*w*w*w*:step", &fd, &seconds, &C.max_frames, &C.ist, &C.fst,
                          &PyByteArray_Type, &C.staged, &C.server, &C.processor, &C.rows, &C.acc, &C.gyro, &C.codes))
        return NULL;
    unsigned char *buf = NULL;
    int ok = 0, ep = -1;
    PyThreadState *ts = NULL;
    if (call_open(&C, MAX_FRAMES_LIMIT) < 0)
        goto done;
    if (fd < 0 || !(seconds >= 0)) {
        PyErr_SetString(PyExc_ValueError, "fastpath.step: needs fd >= 0 and seconds >= 0");
        goto done;
    }
    buf = PyMem_Malloc(READ_BYTES);
    if (buf == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    State *S = &C.S;
    const long long *generation = C.generation.buf;
    ssize_t unit = S->ist[IST_CAN] ? SLCAN_SAMPLE_BYTES : GRAVCAL_FRAME_LEN;
    double deadline = now_s() + seconds;
    /* Edge-triggered epoll: the tty is looked at only when the kernel's line discipline wakes it (a frame came
       in). poll() instead asks n_tty_poll on every entry, which, with fewer than VMIN bytes there, waits for the
       tty's flush work still running after the wake-up that brought the last frame: a second sleep and wake-up
       for about one frame in four on this host. Edge-triggered is exact here: every read takes all that had
       arrived (a short read, or FIONREAD read on), and each arrival queues the next event. poll() stays for a
       descriptor epoll refuses (a regular file). */
    ep = epoll_create1(EPOLL_CLOEXEC);
    if (ep >= 0) {
        struct epoll_event ev = {.events = EPOLLIN | EPOLLET, .data.fd = fd};
        if (epoll_ctl(ep, EPOLL_CTL_ADD, fd, &ev) < 0) {
            close(ep);
            ep = -1;
        }
    }
    for (;;) {
        if (ts == NULL)
            ts = PyEval_SaveThread();
        if (C.had + C.stage.n >= S->ist[IST_STAGE_LIMIT])
            break;
        double left = deadline - now_s();
        if (left <= 0)
            break;
        int r, timeout_ms = (int)ceil(left * 1e3);
        unsigned revents = 0;
        if (ep >= 0) {
            struct epoll_event ev;
            r = epoll_wait(ep, &ev, 1, timeout_ms);
            if (r > 0)
                revents = (ev.events & EPOLLIN ? POLLIN : 0) | (ev.events & (EPOLLHUP | EPOLLERR) ? POLLHUP : 0);
        } else {
            struct pollfd pfd = {fd, POLLIN, 0};
            r = poll(&pfd, 1, timeout_ms);
            revents = (unsigned)pfd.revents;
        }
        if (r < 0 && errno == EINTR)
            continue;
        if (r < 0) {
            S->ist[IST_REASON] = R_ERROR;
            break;
        }
        if (r == 0)
            continue;
        if (!(revents & POLLIN)) { /* hang-up or error alone: the driver's read reports it */
            S->ist[IST_REASON] = R_EOF;
            break;
        }
        /* before reading: bytes for the Python path stay unread */
        PyObject *snapshot = NULL;
        pthread_mutex_lock(&C.box->mu); /* without the GIL: a plain wait */
        int fast = C.box->ready && C.P.loaded && C.P.generation == __atomic_load_n(generation, __ATOMIC_ACQUIRE);
        if (!fast)
            pthread_mutex_unlock(&C.box->mu);
        if (!fast) {
            take_gil(&ts);
            int plain = call_prepare(&C, &snapshot);
            if (plain < 0)
                goto done;
            if (plain == 0)
                break;
        }
        ssize_t n = read_arrived(fd, buf, unit);
        if (n <= 0) {
            int again = n < 0 && (errno == EAGAIN || errno == EINTR);
            if (fast)
                pthread_mutex_unlock(&C.box->mu);
            else
                Py_DECREF(snapshot);
            if (again)
                continue;
            S->ist[IST_REASON] = n == 0 ? R_EOF : R_ERROR;
            break;
        }
        int more = fast ? call_process_nogil(&C, buf, n, &ts) : call_process(&C, buf, n, snapshot);
        if (more < 0)
            goto done;
        if (more == 0)
            break;
    }
    ok = 1;
done:
    take_gil(&ts);
    if (ep >= 0)
        close(ep);
    PyMem_Free(buf);
    return call_close(&C, ok);
}

/* take(data, ...): the bytes of one read made by the caller (the I2C FIFO's bursts, read by smbus2) */
static PyObject *take(PyObject *self, PyObject *args)
{
    Py_buffer data;
    Call C;
    if (!PyArg_ParseTuple(args, "y*iw*w*O!OOw*w*w*w*:take", &data, &C.max_frames, &C.ist, &C.fst, &PyByteArray_Type,
                          &C.staged, &C.server, &C.processor, &C.rows, &C.acc, &C.gyro, &C.codes))
        return NULL;
    int ok = 0;
    if (call_open(&C, data.len / GRAVCAL_FRAME_LEN + 1) == 0) { /* its one batch: whole 29-byte frames at most */
        PyObject *snapshot;
        int plain = call_prepare(&C, &snapshot);
        if (plain == 0)
            C.leftover = PyBytes_FromStringAndSize(data.buf, data.len);
        ok = plain == 0 ? C.leftover != NULL : plain == 1 && call_process(&C, data.buf, data.len, snapshot) >= 0;
    }
    PyBuffer_Release(&data);
    return call_close(&C, ok);
}

/* latest(ist, rows, acc, gyro, static, row, acc1, gyro1, static1): the newest batch's last sample copied out under
   gravcal_latest_mu (the step may be writing the arrays without the GIL): whether there was one */
static PyObject *latest(PyObject *self, PyObject *args)
{
    Py_buffer in[5], out[4];
    if (!PyArg_ParseTuple(args, "w*w*w*w*w*w*w*w*w*:latest", &in[0], &in[1], &in[2], &in[3], &in[4], &out[0], &out[1],
                          &out[2], &out[3]))
        return NULL;
    static const Py_ssize_t size[4] = {GRAVCAL_SAMPLE_SIZE, 24, 8, 1}; /* a row, acc, gyro, static */
    int ok = in[0].len >= IST_N * 8 && ((uintptr_t)in[0].buf & 7) == 0, have = 0;
    for (int i = 0; i < 4; i++)
        ok = ok && out[i].len == size[i] && in[i + 1].len % size[i] == 0;
    if (ok) {
        Py_BEGIN_ALLOW_THREADS
        pthread_mutex_lock(&gravcal_latest_mu);
        long long k = ((const long long *)in[0].buf)[IST_BATCH];
        have = k > 0;
        for (int i = 0; i < 4 && have; i++)
            have = k <= in[i + 1].len / size[i];
        for (int i = 0; i < 4 && have; i++)
            memcpy(out[i].buf, (const char *)in[i + 1].buf + (k - 1) * size[i], (size_t)size[i]);
        pthread_mutex_unlock(&gravcal_latest_mu);
        Py_END_ALLOW_THREADS
    }
    for (int i = 0; i < 5; i++)
        PyBuffer_Release(&in[i]);
    for (int i = 0; i < 4; i++)
        PyBuffer_Release(&out[i]);
    if (!ok) {
        PyErr_SetString(PyExc_ValueError, "fastpath.latest: ist, then rows, acc, gyro, static of whole records, "
                                          "then one record of each");
        return NULL;
    }
    return PyBool_FromLong(have);
}

static PyMethodDef methods[] = {
    {"step", step, METH_VARARGS,
     "step(fd, seconds, max_frames, ist, fst, staged, server, processor, rows, acc, gyro, static) -> (leftover, "
     "stopped snapshot or None): the latency path's common case from the bus to the sockets (see daemon/fastpath.py)."},
    {"take", take, METH_VARARGS,
     "take(data, max_frames, ist, fst, staged, server, processor, rows, acc, gyro, static) -> (leftover, stopped "
     "snapshot or None): as step for the bytes of one read made by the caller."},
    {"latest", latest, METH_VARARGS,
     "latest(ist, rows, acc, gyro, static, row, acc1, gyro1, static1) -> bool: the newest batch's last sample copied "
     "into the one-record buffers (False: none yet)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, .m_name = "_fastpath",
                                    .m_doc = "gravcald's latency path in one C call per wake-up.", .m_size = -1,
                                    .m_methods = methods};

/* the capsule of a kernel module, imported first (PyCapsule_Import walks attributes the import sets) */
static void *import_api(const char *module, const char *capsule)
{
    PyObject *m = PyImport_ImportModule(module);
    if (m == NULL)
        return NULL;
    Py_DECREF(m);
    return PyCapsule_Import(capsule, 0);
}

PyMODINIT_FUNC PyInit__fastpath(void)
{
    struct {
        PyObject **name;
        const char *text;
    } names[] = {{&s_fast_box, "fast_box"}, {&s_correction, "correction"},
                 {&s_gyro_correction, "gyro_correction"}, {&s_analysed, "analysed"}, {&s_offset, "offset"},
                 {&s_kinv_t, "kinv_t"}, {&s_params_generation, "params_generation"}};
    for (size_t i = 0; i < sizeof names / sizeof names[0]; i++)
        if (*names[i].name == NULL && (*names[i].name = PyUnicode_InternFromString(names[i].text)) == NULL)
            return NULL;
    frame_api = import_api("gravcal.drivers._framekernel", GRAVCAL_FRAME_CAPSULE);
    correct_api = frame_api ? import_api("gravcal.core._correctkernel", GRAVCAL_CORRECT_CAPSULE) : NULL;
    line_api = correct_api ? import_api("gravcal.daemon._linekernel", GRAVCAL_LINE_CAPSULE) : NULL;
    if (line_api == NULL || PyType_Ready(&GravcalClientRecordType) < 0 || PyType_Ready(&GravcalWatcherBoxType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m != NULL && (PyModule_AddObjectRef(m, "ClientRecord", (PyObject *)&GravcalClientRecordType) < 0 ||
                      PyModule_AddObjectRef(m, "WatcherBox", (PyObject *)&GravcalWatcherBoxType) < 0))
        Py_CLEAR(m);
    return m;
}
