/* One call of the C step (daemon/_fastpath.c step and take): a read's bytes through frames, the engine's
 * correction, staging, IMU lines and the watchers' sockets, with or without the GIL. See _fastcall.h. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <pthread.h>
#include <stdint.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>

#include "_fastcall.h"

const GravcalFrameAPI *gravcal_frame_api;
const GravcalLineAPI *gravcal_line_api;

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

double gravcal_now_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts); /* time.monotonic()'s clock */
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

int gravcal_reserve(Bytes *b, Py_ssize_t more)
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

/* fanout.deliver for one plain watcher (its general _send and _sent, for a block the socket takes whole): 1 sent whole (counted in its record), 2 stopped with the lock held
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
    rec->sent_messages += k; /* fanout._sent: c.sent_messages += n; c.sent_bytes += sent; c.last_progress = now */
    rec->sent_bytes += s;
    rec->last_progress = now;
    return release_keeping_error(PyTuple_GET_ITEM(entry, ENTRY_RELEASE)) < 0 ? -1 : 1;
}

/* One read's records (written and stamped by the frame kernel) through the engine and staging, as the Python
   path's Processor.correct (Engine.correct) and Gravcald._acquire do: each record corrected with the engine's
   parameters and labelled with the detector's decision (gravcal_engine_sample), the records appended to the
   staging area. No Python: runs with or without the GIL, under gravcal_latest_mu (the arrays ?POLL reads). */
static void correct_batch(State *S, long long *live_ist, Py_ssize_t k, const uint32_t *ticks, const EngineParams *P,
                          double t_recv, unsigned char *rows, double *acc, double *gyro, signed char *codes,
                          Bytes *stage)
{
    for (Py_ssize_t i = 0; i < k; i++) {
        gravcal_engine_sample(P, rows + i * GRAVCAL_SAMPLE_SIZE, acc + 3 * i, gyro + i, codes + i);
        S->ist[IST_UNKNOWN] += codes[i] < 0;
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
            if (gravcal_reserve(&lines[raw], GRAVCAL_IMU_LINE_MAX) < 0) {
                if (nogil)
                    return -2;
                PyErr_NoMemory();
                return -1;
            }
            const unsigned char *row = rows + i * GRAVCAL_SAMPLE_SIZE;
            char *out = lines[raw].buf + lines[raw].n;
            Py_ssize_t cap = lines[raw].cap - lines[raw].n,
                       m = nogil ? gravcal_line_api->line_nogil(row, acc + 3 * i, gyro[i], codes[i], raw, out, cap)
                                 : gravcal_line_api->line(row, acc + 3 * i, gyro[i], codes[i], raw, out, cap);
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

/* ``batch_frames``: the most frames one batch of this call can hold (the stage keeps room for one beyond the
   stage limit) */
int call_open(Call *C, Py_ssize_t batch_frames)
{
    C->leftover = NULL;
    C->stopped = Py_NewRef(Py_None);
    C->ticks = NULL;
    C->lines[0] = C->lines[1] = C->stage = (Bytes){NULL, 0, 0};
    C->generation = -1;
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
    if (!C->engine->set) {
        PyErr_SetString(PyExc_ValueError, "fastpath: the engine has no parameters (Engine.set_params)");
        return -1;
    }
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
    if (gravcal_reserve(&C->stage, (room > 0 ? (Py_ssize_t)room : 0) + batch_frames * GRAVCAL_SAMPLE_SIZE) < 0) {
        PyErr_NoMemory();
        return -1;
    }
    S->ist[IST_FRAMES] = S->ist[IST_UNKNOWN] = S->ist[IST_NOGIL] = 0;
    S->ist[IST_CLIENT] = S->ist[IST_SENT] = -1;
    S->ist[IST_REASON] = R_DUE;
    C->started = 1;
    gravcal_engine_current(C->engine, &C->P, &C->generation);
    return 0;
}

/* The watcher snapshot for the next bytes, with the GIL: 1 (*snapshot set), 0 none (some watcher is not plain:
   the Python path's fanout, reason R_NOT_PLAIN), -1 error */
int call_prepare(Call *C, PyObject **snapshot)
{
    PyObject *snap = Py_NewRef(C->box->item); /* per wake-up: a pointer read */
    if (snap != Py_None && !PyTuple_Check(snap)) {
        Py_DECREF(snap);
        PyErr_SetString(PyExc_TypeError, "fastpath: the watcher snapshot (box[0]) must be a tuple or None");
        return -1;
    }
    if (snap == Py_None) {
        Py_DECREF(snap);
        C->S.ist[IST_REASON] = R_NOT_PLAIN;
        return 0;
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
    gravcal_engine_current(C->engine, &C->P, &C->generation); /* the parameters as of this read */
    pthread_mutex_lock(&gravcal_latest_mu); /* held by no thread that waits for the GIL: a plain wait */
    const GravcalFrameAPI *f = gravcal_frame_api;
    Py_ssize_t k = can_base < 0 ? f->continuing(buf, n, S->ist[IST_EXPECT], C->max_frames, S->ist[IST_SEQ],
                                                S->fst[FST_TICK_HZ], t_recv, &S->fst[FST_LAST_T], C->rows.buf, C->ticks)
                                : f->slcan_continuing(buf, n, can_base, S->ist[IST_EXPECT], C->max_frames,
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
int call_process(Call *C, const unsigned char *buf, Py_ssize_t n, PyObject *snapshot)
{
    State *S = &C->S;
    double t_recv = gravcal_now_s();
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

void gravcal_take_gil(PyThreadState **ts)
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
int call_process_nogil(Call *C, const unsigned char *buf, Py_ssize_t n, PyThreadState **ts)
{
    State *S = &C->S;
    WatcherBox *box = C->box;
    double t_recv = gravcal_now_s();
    Py_ssize_t k = call_frames(C, buf, n, t_recv);
    if (k == 0) {
        pthread_mutex_unlock(&box->mu);
        gravcal_take_gil(ts);
        C->leftover = PyBytes_FromStringAndSize((const char *)buf, n);
        S->ist[IST_REASON] = R_BYTES;
        return C->leftover == NULL ? -1 : 0;
    }
    int rc = batch_lines(k, C->rows.buf, C->acc.buf, C->gyro.buf, C->codes.buf, box->need, C->lines, 1);
    if (rc == -2) { /* the box's mutex held while taking the GIL: allowed (see "Locks" in _clienttable.h) */
        gravcal_take_gil(ts);
        rc = batch_lines(k, C->rows.buf, C->acc.buf, C->gyro.buf, C->codes.buf, box->need, C->lines, 0);
    }
    if (rc < 0) {
        pthread_mutex_unlock(&box->mu);
        gravcal_take_gil(ts);
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
                rec->sent_messages += k; /* fanout._sent's counters for a block taken whole */
                rec->sent_bytes += s;
                rec->last_progress = t_recv;
                pthread_mutex_unlock(&rec->mu);
                continue;
            }
            sent = s > 0 ? s : 0;
        }
        gravcal_take_gil(ts);
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
PyObject *call_close(Call *C, int ok)
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
    Py_DECREF(C->stopped);
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
    return result;
}
