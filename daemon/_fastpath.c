/* gravcald's per-sample engine, in one C call per wake-up: bus bytes -> frames -> correction -> IMU lines -> sockets.
 *
 * step(fd, seconds, max_frames, ist, fst, staged, box, engine, rows, acc, gyro, static)
 *     -> (leftover bytes, the watcher snapshot of a stopped delivery or None)
 * i2c_step(fd, seconds, max_frames, bus, ist, ...)  the same for the logger's FIFO on /dev/i2c-N, read through
 *     the I2C_RDWR ioctl in C (daemon/_i2cpoll.c)
 * Engine, WatcherBox, ClientRecord: the objects the step shares with Python (_engine.c, _clienttable.c)
 *
 * Python's control plane hands the engine its parameters through one setter, Engine.set_params (the calibration,
 * every term the online calibrator can publish included, the gyro's, the detector's latest decision), and the
 * server's watcher table through WatcherBox; the step reads nothing of Python objects by name. It returns, having
 * consumed nothing of it, whatever the Python path must decide (its one channel back: the reason in ist and the
 * returned pair, which daemon/fastpath.py applies):
 *
 *   - bytes: a read that is not exactly whole intact frames, each continuing the stream by one (the
 *     SeqUnwrapper's rule 2 with a step of 1: no gap, no stray, no restart; the 16-bit counter may wrap),
 *     or more frames than max_frames: returned as leftover, the driver decodes them as it always does;
 *     with ist[IST_CAN] = 1 + a CAN base id the bytes are slcan lines and a "frame" is a CAN sample's four lines
 *     (the frame kernel's slcan_continuing: anything else is handed back to python-can's reader);
 *   - watchers: delivery only to box[0], the snapshot of the watchers (all watching every sample; None: some
 *     watcher is not plain, R_NOT_PLAIN). A watcher that is closed or whose output is not empty, or whose policy
 *     changed (both told by its ClientRecord's gate), or whose socket does not take the whole block stops the
 *     delivery: its lock stays held and the snapshot is returned, so fastpath.py queues the rest in order
 *     (fanout's bookkeeping);
 *   - end of file or a read error.
 *
 * Per batch (the frames of one read) it does, in order (_fastcall.c): the frame kernel checks that the frames
 *   continue the stream and writes their records, stamped as Driver._stamp does (drivers/_framekernel.c); the
 *   engine corrects each record and labels it with the detector's decision (_engine.c, core/_correctkernel.c: the
 *   code Engine.correct runs for the Python path's blocks); SocketServer.publish: one joined block of lines per
 *   encoding (daemon/_linekernel.c), one non-blocking send() per watcher in snapshot order under the client's
 *   lock; Gravcald._acquire: the records appended to ``staged`` (the analysis' bytes). It returns at the latest
 *   after ``seconds`` or once ``staged`` holds ist[IST_STAGE_LIMIT] bytes, for the Python loop's housekeeping.
 * step and i2c_step hold the GIL only for what needs Python (see step and "Locks" in _clienttable.h).
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
#include <time.h>
#include <unistd.h>

#include "_fastcall.h"
#include "_i2cpoll.h"

#define READ_BYTES 65536 /* drivers/serial.py READ_BYTES: more than the kernel's tty buffer holds */
#define SLCAN_SAMPLE_BYTES 78 /* a CAN sample's four slcan lines: t<id><dlc><hex>\r with dlc 8, 7, 7, 5 */
#define TTY_CHUNK 64 /* tty_read's kernel buffer (drivers/tty/tty_io.c): the line discipline is asked per 64 bytes */

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
   taken only when a wake-up needs Python: a box that is not ready (call_prepare and call_process, as with the GIL
   throughout) and what call_process_nogil hands to Python. The engine's parameters are copied without the GIL
   whenever Engine.set_params swapped them (gravcal_engine_current, per read). */
static PyObject *step(PyObject *self, PyObject *args)
{
    int fd;
    double seconds;
    Call C;
    if (!PyArg_ParseTuple(args, "idiw*w*O!O!O!w*w*w*w*:step", &fd, &seconds, &C.max_frames, &C.ist, &C.fst,
                          &PyByteArray_Type, &C.staged, &GravcalWatcherBoxType, &C.box, &GravcalEngineType, &C.engine,
                          &C.rows, &C.acc, &C.gyro, &C.codes))
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
    ssize_t unit = S->ist[IST_CAN] ? SLCAN_SAMPLE_BYTES : GRAVCAL_FRAME_LEN;
    double deadline = gravcal_now_s() + seconds;
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
        double left = deadline - gravcal_now_s();
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
        int fast = C.box->ready;
        if (!fast)
            pthread_mutex_unlock(&C.box->mu);
        if (!fast) {
            gravcal_take_gil(&ts);
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
    gravcal_take_gil(&ts);
    if (ep >= 0)
        close(ep);
    PyMem_Free(buf);
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
     "step(fd, seconds, max_frames, ist, fst, staged, box, engine, rows, acc, gyro, static) -> (leftover, "
     "stopped snapshot or None): the latency path's common case from the bus to the sockets (see daemon/fastpath.py)."},
    {"i2c_step", gravcal_i2c_step, METH_VARARGS,
     "i2c_step(fd, seconds, max_frames, bus, ist, fst, staged, box, engine, rows, acc, gyro, static) -> (leftover, "
     "stopped snapshot or None): as step for the logger's FIFO on /dev/i2c-N, polled in C (daemon/_i2cpoll.c)."},
    {"latest", latest, METH_VARARGS,
     "latest(ist, rows, acc, gyro, static, row, acc1, gyro1, static1) -> bool: the newest batch's last sample copied "
     "into the one-record buffers (False: none yet)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, .m_name = "_fastpath",
                                    .m_doc = "gravcald's per-sample engine, in one C call per wake-up.", .m_size = -1,
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
    gravcal_frame_api = import_api("gravcal.drivers._framekernel", GRAVCAL_FRAME_CAPSULE);
    gravcal_line_api = gravcal_frame_api ? import_api("gravcal.daemon._linekernel", GRAVCAL_LINE_CAPSULE) : NULL;
    if (gravcal_line_api == NULL || gravcal_engine_init() < 0 || PyType_Ready(&GravcalClientRecordType) < 0 ||
        PyType_Ready(&GravcalWatcherBoxType) < 0 || PyType_Ready(&GravcalEngineType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m != NULL && (PyModule_AddObjectRef(m, "ClientRecord", (PyObject *)&GravcalClientRecordType) < 0 ||
                      PyModule_AddObjectRef(m, "WatcherBox", (PyObject *)&GravcalWatcherBoxType) < 0 ||
                      PyModule_AddObjectRef(m, "Engine", (PyObject *)&GravcalEngineType) < 0 ||
                      PyModule_AddIntConstant(m, "EP_N", EP_N) < 0))
        Py_CLEAR(m);
    return m;
}
