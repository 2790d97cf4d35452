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
 * The GIL is released only while waiting in poll().
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <errno.h>
#include <math.h>
#include <poll.h>
#include <sys/epoll.h>
#include <stdint.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include "../core/_correctkernel.h"
#include "../drivers/_framekernel.h"
#include "_linekernel.h"

#define READ_BYTES 65536 /* drivers/serial.py READ_BYTES: more than the kernel's tty buffer holds */
#define MAX_FRAMES_LIMIT 4096
#define SLCAN_SAMPLE_BYTES 78 /* a CAN sample's four slcan lines: t<id><dlc><hex>\r with dlc 8, 7, 7, 5 */
#define TTY_CHUNK 64 /* tty_read's kernel buffer (drivers/tty/tty_io.c): the line discipline is asked per 64 bytes */

/* ist (int64) and fst (float64) slots: the state shared with daemon/fastpath.py */
enum { IST_EXPECT, IST_SEQ, IST_FRAMES, IST_TICK, IST_UNKNOWN, IST_REASON, IST_CLIENT, IST_SENT, IST_BATCH,
       IST_STAGE_LIMIT, IST_CAN, IST_N };
enum { FST_LAST_T, FST_TICK_HZ, FST_T_RECV, FST_MAX_AGE, FST_TICK_PERIOD, FST_N };
enum { R_DUE, R_BYTES, R_DELIVERY, R_NOT_PLAIN, R_EOF, R_ERROR };
/* a watcher entry of server.fast_watchers (daemon/fanout.py fast_snapshot) */
enum { ENTRY_CLIENT, ENTRY_RECORD, ENTRY_FD, ENTRY_RAW, ENTRY_WATCH, ENTRY_ACQUIRE, ENTRY_RELEASE, ENTRY_N };

/* attribute names, interned once: a lookup is then a pointer comparison */
static PyObject *s_fast_box, *s_correction, *s_gyro_correction, *s_analysed, *s_offset, *s_kinv_t,
    *s_params_generation;

/* ClientRecord: what the step reads and writes per client, as C fields (no attribute lookup per sample).
 *   policy: the watch policy the step may send under, None while it must not (the client is closed or has
 *     output pending); set by ClientState.regate (daemon/client_limits.py) each time the client's lock is
 *     released by Python, so it is exact whenever the step holds that lock;
 *   sent_messages, sent_bytes, last_progress: what fanout.deliver adds to the ClientState for a block taken
 *     whole, accumulated here and folded into the ClientState by take() (under the client's lock). */
typedef struct {
    PyObject_HEAD
    PyObject *policy;
    long long sent_messages, sent_bytes;
    double last_progress;
} ClientRecord;

static PyObject *record_new(PyTypeObject *type, PyObject *args, PyObject *kwds)
{
    if (PyTuple_GET_SIZE(args) != 0 || (kwds != NULL && PyDict_GET_SIZE(kwds) != 0)) {
        PyErr_SetString(PyExc_TypeError, "ClientRecord() takes no arguments");
        return NULL;
    }
    ClientRecord *r = (ClientRecord *)type->tp_alloc(type, 0);
    if (r != NULL)
        r->policy = Py_NewRef(Py_None);
    return (PyObject *)r;
}

static int record_traverse(ClientRecord *r, visitproc visit, void *arg)
{
    Py_VISIT(r->policy);
    return 0;
}

static int record_clear(ClientRecord *r)
{
    Py_CLEAR(r->policy);
    return 0;
}

static void record_dealloc(ClientRecord *r)
{
    PyObject_GC_UnTrack(r);
    record_clear(r);
    Py_TYPE(r)->tp_free((PyObject *)r);
}

static PyObject *record_get_policy(ClientRecord *r, void *closure)
{
    return Py_NewRef(r->policy);
}

static int record_set_policy(ClientRecord *r, PyObject *value, void *closure)
{
    if (value == NULL) {
        PyErr_SetString(PyExc_AttributeError, "ClientRecord.policy cannot be deleted (None: the step may not send)");
        return -1;
    }
    Py_SETREF(r->policy, Py_NewRef(value));
    return 0;
}

/* the counters since the last take, zeroed: one C call, so atomic under the GIL against the step's writes */
static PyObject *record_take(ClientRecord *r, PyObject *unused)
{
    PyObject *out = Py_BuildValue("(LLd)", r->sent_messages, r->sent_bytes, r->last_progress);
    if (out != NULL) {
        r->sent_messages = r->sent_bytes = 0;
        r->last_progress = 0.0;
    }
    return out;
}

static PyGetSetDef record_getset[] = {
    {"policy", (getter)record_get_policy, (setter)record_set_policy,
     "the watch policy the step may send under; None: it may not (closed, output pending)", NULL},
    {NULL},
};

static PyMethodDef record_methods[] = {
    {"take", (PyCFunction)record_take, METH_NOARGS,
     "take() -> (messages, bytes, last_progress): the counters the step added since the last take, zeroed"},
    {NULL},
};

static PyTypeObject ClientRecordType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "gravcal.daemon._fastpath.ClientRecord",
    .tp_basicsize = sizeof(ClientRecord),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
    .tp_doc = "What the C step reads and writes for one client: its send gate and counters (see _fastpath.c).",
    .tp_new = record_new,
    .tp_traverse = (traverseproc)record_traverse,
    .tp_clear = (inquiry)record_clear,
    .tp_dealloc = (destructor)record_dealloc,
    .tp_getset = record_getset,
    .tp_methods = record_methods,
};

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

static int reserve(Bytes *b, Py_ssize_t more)
{
    if (b->n + more <= b->cap)
        return 0;
    Py_ssize_t cap = b->cap ? b->cap : 4096;
    while (cap < b->n + more)
        cap *= 2;
    char *p = PyMem_Realloc(b->buf, (size_t)cap);
    if (p == NULL) {
        PyErr_NoMemory();
        return -1;
    }
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
        !PyObject_TypeCheck(PyTuple_GET_ITEM(entry, ENTRY_RECORD), &ClientRecordType)) {
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

/* One read's records (written and stamped by the frame kernel) through correction, staging and the lines:
   0, or -1 with an exception */
static int run_batch(State *S, long long *live_ist, Py_ssize_t k, const uint32_t *ticks, const Params *P,
                     double t_recv, unsigned char *rows, double *acc, double *gyro, signed char *codes,
                     PyObject *staged, PyObject *snapshot, Bytes lines[2])
{
    for (Py_ssize_t i = 0; i < k; i++) {
        long long seq = correct_api->correct(rows + i * GRAVCAL_SAMPLE_SIZE, P->o, P->k, P->bias, P->sens, acc + 3 * i,
                                             gyro + i);
        long long code = static_code(P, seq, S->fst[FST_MAX_AGE]);
        codes[i] = (signed char)code;
        S->ist[IST_UNKNOWN] += code < 0;
    }
    Py_ssize_t had = PyByteArray_GET_SIZE(staged);
    if (PyByteArray_Resize(staged, had + k * GRAVCAL_SAMPLE_SIZE) < 0)
        return -1;
    memcpy(PyByteArray_AS_STRING(staged) + had, rows, (size_t)(k * GRAVCAL_SAMPLE_SIZE));
    S->ist[IST_EXPECT] = (S->ist[IST_EXPECT] + k) & 0xFFFF;
    S->ist[IST_SEQ] += k;
    S->ist[IST_FRAMES] += k;
    S->ist[IST_BATCH] = k;
    memcpy(live_ist + IST_BATCH, &S->ist[IST_BATCH], 8); /* ?POLL reads the newest batch's last record meanwhile */
    S->ist[IST_TICK] = ticks[k - 1];
    if (k >= 2) /* SeqUnwrapper._learn_ticks: device ticks per sample */
        S->fst[FST_TICK_PERIOD] = (double)(uint32_t)(ticks[k - 1] - ticks[0]) / (double)(k - 1);
    S->fst[FST_T_RECV] = t_recv;
    int need[2] = {0, 0};
    for (Py_ssize_t j = 0; j < PyTuple_GET_SIZE(snapshot); j++) {
        PyObject *e = PyTuple_GET_ITEM(snapshot, j);
        int raw =
            PyTuple_Check(e) && PyTuple_GET_SIZE(e) == ENTRY_N ? PyObject_IsTrue(PyTuple_GET_ITEM(e, ENTRY_RAW)) : 0;
        if (raw < 0)
            return -1;
        need[raw] = 1;
    }
    for (int raw = 0; raw < 2; raw++) {
        lines[raw].n = 0;
        for (Py_ssize_t i = 0; need[raw] && i < k; i++) {
            if (reserve(&lines[raw], GRAVCAL_IMU_LINE_MAX) < 0)
                return -1;
            Py_ssize_t m = line_api->line(rows + i * GRAVCAL_SAMPLE_SIZE, acc + 3 * i, gyro[i], codes[i], raw,
                                          lines[raw].buf + lines[raw].n, lines[raw].cap - lines[raw].n);
            if (m < 0)
                return -1;
            lines[raw].n += m;
        }
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
    State S;
    Params P;
    Py_buffer generation; /* processor.params_generation: one int64 */
    PyObject *box; /* server.fast_box, a list whose one item is the watcher snapshot (NULL: read fast_watchers) */
    int started; /* S holds the caller's state (copied back at the end) */
} Call;

static int call_open(Call *C)
{
    C->leftover = NULL;
    C->stopped = Py_NewRef(Py_None);
    C->ticks = NULL;
    C->lines[0] = C->lines[1] = (Bytes){NULL, 0, 0};
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
        strpbrk(C->generation.format, "lq") == NULL) {
        PyErr_SetString(PyExc_TypeError, "fastpath: processor.params_generation must be one int64");
        return -1;
    }
    /* the server's snapshot box: a list of exactly one item (the server only replaces the item) */
    PyObject *box = PyObject_GetAttr(C->server, s_fast_box);
    if (box == NULL)
        return -1;
    if (!PyList_CheckExact(box) || PyList_GET_SIZE(box) != 1) {
        Py_DECREF(box);
        PyErr_SetString(PyExc_TypeError, "fastpath: server.fast_box must be a list of one watcher snapshot");
        return -1;
    }
    C->box = box;
    C->ticks = PyMem_Malloc(sizeof(uint32_t) * (size_t)C->max_frames);
    if (C->ticks == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    State *S = &C->S;
    memcpy(S->ist, C->ist.buf, sizeof S->ist);
    memcpy(S->fst, C->fst.buf, sizeof S->fst);
    S->ist[IST_FRAMES] = S->ist[IST_UNKNOWN] = 0;
    S->ist[IST_CLIENT] = S->ist[IST_SENT] = -1;
    S->ist[IST_REASON] = R_DUE;
    C->started = 1;
    return 0;
}

/* The watcher snapshot and the correction for the next bytes: 1 plain (*snapshot set), 0 not (the Python
   path's: reason R_NOT_PLAIN), -1 error */
static int call_prepare(Call *C, PyObject **snapshot)
{
    if (PyList_GET_SIZE(C->box) != 1) {
        PyErr_SetString(PyExc_TypeError, "fastpath: server.fast_box must keep exactly one item");
        return -1;
    }
    PyObject *snap = Py_NewRef(PyList_GET_ITEM(C->box, 0)); /* per wake-up: a pointer read */
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

/* One read's bytes: 1 taken and delivered, 0 stopped (bytes handed back, or a delivery for fanout), -1 error.
   Consumes the reference to ``snapshot``. */
static int call_process(Call *C, const unsigned char *buf, Py_ssize_t n, PyObject *snapshot)
{
    State *S = &C->S;
    double t_recv = now_s();
    /* the records source: ist[IST_CAN] 0 the serial frames, else slcan lines of CAN samples from base id - 1 */
    long long can_base = S->ist[IST_CAN] - 1;
    Py_ssize_t k = can_base < 0 ? frame_api->continuing(buf, n, S->ist[IST_EXPECT], C->max_frames, S->ist[IST_SEQ],
                                                        S->fst[FST_TICK_HZ], t_recv, &S->fst[FST_LAST_T],
                                                        C->rows.buf, C->ticks)
                                : frame_api->slcan_continuing(buf, n, can_base, S->ist[IST_EXPECT], C->max_frames,
                                                              S->ist[IST_SEQ], S->fst[FST_TICK_HZ], t_recv,
                                                              &S->fst[FST_LAST_T], C->rows.buf, C->ticks);
    if (k == 0) {
        Py_DECREF(snapshot);
        C->leftover = PyBytes_FromStringAndSize((const char *)buf, n);
        S->ist[IST_REASON] = R_BYTES;
        return C->leftover == NULL ? -1 : 0;
    }
    if (run_batch(S, C->ist.buf, k, C->ticks, &C->P, t_recv, C->rows.buf, C->acc.buf, C->gyro.buf, C->codes.buf,
                  C->staged, snapshot, C->lines) < 0) {
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

/* (leftover, stopped) or NULL; the state copied back either way (what was consumed stays accounted) */
static PyObject *call_close(Call *C, int ok)
{
    PyObject *result = NULL;
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
    PyMem_Free(C->lines[0].buf);
    PyMem_Free(C->lines[1].buf);
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

/* step(fd, seconds, ...): wait on fd (the GIL released) and read it, until due or stopped */
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
    if (call_open(&C) < 0)
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
        if (PyByteArray_GET_SIZE(C.staged) >= S->ist[IST_STAGE_LIMIT])
            break;
        double left = deadline - now_s();
        if (left <= 0)
            break;
        int r, timeout_ms = (int)ceil(left * 1e3);
        unsigned revents = 0;
        if (ep >= 0) {
            struct epoll_event ev;
            Py_BEGIN_ALLOW_THREADS
            r = epoll_wait(ep, &ev, 1, timeout_ms);
            Py_END_ALLOW_THREADS
            if (r > 0)
                revents = (ev.events & EPOLLIN ? POLLIN : 0) | (ev.events & (EPOLLHUP | EPOLLERR) ? POLLHUP : 0);
        } else {
            struct pollfd pfd = {fd, POLLIN, 0};
            Py_BEGIN_ALLOW_THREADS
            r = poll(&pfd, 1, timeout_ms);
            Py_END_ALLOW_THREADS
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
        PyObject *snapshot;
        int plain = call_prepare(&C, &snapshot); /* before reading: bytes for the Python path stay unread */
        if (plain < 0)
            goto done;
        if (plain == 0)
            break;
        /* Never ask a tty for more than it holds: n_tty_read, short of VMIN in the 64-byte chunk tty_read hands
           it last (the 14 bytes after the first 64 of a 78-byte slcan sample), waits for the tty's flush work
           still running after the wake-up: a second sleep and wake-up. So one chunk first (a 29-byte frame: all
           there was, one read), and while a read filled what it asked, FIONREAD says how much more to take.
           What arrives later queues the next epoll event. */
        size_t ask = TTY_CHUNK;
        ssize_t n = read(fd, buf, ask);
        if (n < 0 && (errno == EAGAIN || errno == EINTR)) {
            Py_DECREF(snapshot);
            continue;
        }
        if (n <= 0) {
            Py_DECREF(snapshot);
            S->ist[IST_REASON] = n == 0 ? R_EOF : R_ERROR;
            break;
        }
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
           delivering the rest: one more read, which waits for that work, keeps the batch whole and in C (the
           frame kernel takes only whole frames); anything else (a stray byte) costs one read that finds nothing. */
        ssize_t unit = S->ist[IST_CAN] ? SLCAN_SAMPLE_BYTES : GRAVCAL_FRAME_LEN;
        if (n % unit && n < READ_BYTES && (last = read(fd, buf + n, (size_t)(READ_BYTES - n))) > 0)
            n += last;
        int more = call_process(&C, buf, n, snapshot);
        if (more < 0)
            goto done;
        if (more == 0)
            break;
    }
    ok = 1;
done:
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
    if (call_open(&C) == 0) {
        PyObject *snapshot;
        int plain = call_prepare(&C, &snapshot);
        if (plain == 0)
            C.leftover = PyBytes_FromStringAndSize(data.buf, data.len);
        ok = plain == 0 ? C.leftover != NULL : plain == 1 && call_process(&C, data.buf, data.len, snapshot) >= 0;
    }
    PyBuffer_Release(&data);
    return call_close(&C, ok);
}

static PyMethodDef methods[] = {
    {"step", step, METH_VARARGS,
     "step(fd, seconds, max_frames, ist, fst, staged, server, processor, rows, acc, gyro, static) -> (leftover, "
     "stopped snapshot or None): the latency path's common case from the bus to the sockets (see daemon/fastpath.py)."},
    {"take", take, METH_VARARGS,
     "take(data, max_frames, ist, fst, staged, server, processor, rows, acc, gyro, static) -> (leftover, stopped "
     "snapshot or None): as step for the bytes of one read made by the caller."},
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
    if (line_api == NULL || PyType_Ready(&ClientRecordType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m != NULL && PyModule_AddObjectRef(m, "ClientRecord", (PyObject *)&ClientRecordType) < 0)
        Py_CLEAR(m);
    return m;
}
