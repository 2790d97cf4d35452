/* The C step on the I2C bus (gravcal.daemon._fastpath.i2c_step): the logger's FIFO polled through the I2C_RDWR
 * ioctl on /dev/i2c-N, its frames through the engine (_fastcall.c), all without the GIL.
 *
 * i2c_step(fd, seconds, max_frames, bus, ist, fst, staged, box, engine, rows, acc, gyro, static)
 *     -> (leftover bytes, the watcher snapshot of a stopped delivery or None)
 *
 * It reads the FIFO exactly as drivers/i2c.py ``_read_fifo`` does (the register map is that module's): one
 * combined transfer of STATUS, FIFO_COUNT and the first ``bus[IB_FIRST]`` frames (``bus[IB_COMBINED]`` 0: STATUS
 * and FIFO_COUNT alone), then the rest in bursts of up to ``bus[IB_BURST]`` frames; polled, it waits the poll
 * interval after a drain and between empty polls; with the DRDY line's sysfs value (``bus[IB_DRDY_FD]`` >= 0) it
 * sleeps on the line's edge instead and reads the frames with STATUS only while the line is high. Each read's
 * bytes go through call_process_nogil, as the serial step's. It returns to Python (reason in ist[IST_REASON],
 * the bus's counters in ``bus``) when due, when the stage is full, and for what the driver decides:
 *   - the frames of a read whose STATUS reported a FIFO overflow (bus[IB_OVERFLOW] 1), handed back undecoded
 *     (reason R_BYTES): the driver flags the gap;
 *   - a transfer that failed (reason R_ERROR, bus[IB_ERRNO]), the frames read before it handed back;
 *   - bytes the frame kernel does not take (R_BYTES), a watcher that is not plain (R_NOT_PLAIN, bytes handed
 *     back), a delivery for fanout (R_DELIVERY), as step. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <errno.h>
#include <linux/i2c-dev.h>
#include <linux/i2c.h>
#include <poll.h>
#include <pthread.h>
#include <string.h>
#include <sys/ioctl.h>
#include <time.h>
#include <unistd.h>

#include "_fastcall.h"
#include "_i2cpoll.h"

#define REG_STATUS 0x02    /* then FIFO_COUNT (auto-increment) */
#define REG_FIFO_DATA 0x10 /* whole frames, oldest first; 0x00 past the FIFO's content */
#define STATUS_FIFO_OVERFLOW 0x02
#define DRDY_RECHECK_NS 100000000LL /* drivers/i2c.py DRDY_RECHECK_S */

static long long now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts); /* time.monotonic_ns()'s clock */
    return (long long)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static void sleep_until(long long t_ns)
{
    struct timespec ts = {(time_t)(t_ns / 1000000000LL), (long)(t_ns % 1000000000LL)};
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR)
        ;
}

/* One I2C_RDWR: per read i a register write of reg[i], then a read of len[i] bytes into out[i] (repeated starts).
   0, or -1 with errno. */
static int rdwr(int fd, unsigned short addr, int nreads, unsigned char *reg, unsigned char **out,
                const unsigned short *len)
{
    struct i2c_msg msgs[4];
    for (int i = 0; i < nreads; i++) {
        msgs[2 * i] = (struct i2c_msg){.addr = addr, .flags = 0, .len = 1, .buf = &reg[i]};
        msgs[2 * i + 1] = (struct i2c_msg){.addr = addr, .flags = I2C_M_RD, .len = len[i], .buf = out[i]};
    }
    struct i2c_rdwr_ioctl_data data = {.msgs = msgs, .nmsgs = (unsigned)(2 * nreads)};
    return ioctl(fd, I2C_RDWR, &data) < 0 ? -1 : 0;
}

/* SysfsDataReady.wait: 1 while the DRDY line is high or once it rose within ``timeout_ns``, else 0 */
static int drdy_wait(int fd, long long timeout_ns)
{
    char v;
    if (pread(fd, &v, 1, 0) == 1 && v == '1')
        return 1;
    struct pollfd p = {fd, POLLPRI | POLLERR, 0};
    int ms = timeout_ns > 0 ? (int)((timeout_ns + 999999) / 1000000) : 0;
    return poll(&p, 1, ms) > 0;
}

/* The frames of one wake-up into buf (at most max_frames), as _read_fifo reads them: the bytes read (whole
   frames), 0 when none came by ``deadline``, -1 when a transfer failed (errno in bus; *n_read: the bytes read
   before it). Sets bus[IB_OVERFLOW] when STATUS reported an overflow. */
static Py_ssize_t read_fifo(int fd, long long *bus, long long deadline, unsigned char *buf, int max_frames,
                            Py_ssize_t *n_read)
{
    unsigned short addr = (unsigned short)bus[IB_ADDRESS];
    int drdy = (int)bus[IB_DRDY_FD];
    long long poll_ns = bus[IB_POLL_NS];
    long long count = 0, first = bus[IB_FIRST] < max_frames ? bus[IB_FIRST] : max_frames;
    Py_ssize_t n = 0;
    *n_read = 0;
    if (drdy < 0) { /* polled: asking right after a drain finds the FIFO empty; wait out the poll interval */
        long long now = now_ns(), wait = bus[IB_NEXT_POLL_NS] - now;
        if (wait > deadline - now) { /* not within this call: wait to its end, the next call waits the rest */
            sleep_until(deadline);
            return 0;
        }
        if (wait > 0)
            sleep_until(bus[IB_NEXT_POLL_NS]);
    }
    for (;;) {
        int combined = (int)bus[IB_COMBINED];
        if (drdy >= 0) {
            long long left = deadline - now_ns();
            combined = drdy_wait(drdy, left < DRDY_RECHECK_NS ? left : DRDY_RECHECK_NS) && combined;
        }
        unsigned char st[2], reg[2] = {REG_STATUS, REG_FIFO_DATA}, *out[2] = {st, buf};
        unsigned short len[2] = {2, (unsigned short)(first * GRAVCAL_FRAME_LEN)};
        if (rdwr(fd, addr, combined ? 2 : 1, reg, out, len) < 0) {
            bus[IB_ERRNO] = errno ? errno : EIO;
            return -1;
        }
        bus[IB_POLLS]++;
        bus[IB_BURSTS] += combined;
        count = st[1];
        if (st[0] & STATUS_FIFO_OVERFLOW)
            bus[IB_OVERFLOW] = 1;
        if (combined) { /* the frames the count had, and any that came in before the data phase (a frame starts
                           with its sync bytes; past the FIFO's content the device reads 0x00) */
            long long taken = count < first ? count : first;
            while (taken < first) {
                const unsigned char *f = buf + taken * GRAVCAL_FRAME_LEN;
                int any = 0;
                for (int i = 0; i < GRAVCAL_FRAME_LEN && !any; i++)
                    any = f[i] != 0;
                if (!any)
                    break;
                taken++;
            }
            n = (Py_ssize_t)taken * GRAVCAL_FRAME_LEN;
            count -= taken;
        }
        if (n > 0 || count > 0)
            break;
        long long now = now_ns();
        if (now >= deadline)
            return 0;
        if (drdy < 0)
            sleep_until(now + (poll_ns < deadline - now ? poll_ns : deadline - now));
    }
    while (count > 0 && n < (Py_ssize_t)max_frames * GRAVCAL_FRAME_LEN) {
        long long room = max_frames - n / GRAVCAL_FRAME_LEN, k = count < bus[IB_BURST] ? count : bus[IB_BURST];
        k = k < room ? k : room;
        unsigned char reg = REG_FIFO_DATA, *out = buf + n;
        unsigned short len = (unsigned short)(k * GRAVCAL_FRAME_LEN);
        if (rdwr(fd, addr, 1, &reg, &out, &len) < 0) {
            bus[IB_ERRNO] = errno ? errno : EIO;
            *n_read = n;
            return -1;
        }
        bus[IB_BURSTS]++;
        n += (Py_ssize_t)k * GRAVCAL_FRAME_LEN;
        count -= k;
    }
    /* the FIFO drained: ask again a poll interval later; frames left beyond max_frames: at once */
    bus[IB_NEXT_POLL_NS] = count > 0 ? 0 : now_ns() + poll_ns;
    return n;
}

PyObject *gravcal_i2c_step(PyObject *self, PyObject *args)
{
    int fd;
    double seconds;
    Py_buffer busbuf;
    Call C;
    if (!PyArg_ParseTuple(args, "idiw*w*w*O!O!O!w*w*w*w*:i2c_step", &fd, &seconds, &C.max_frames, &busbuf, &C.ist,
                          &C.fst, &PyByteArray_Type, &C.staged, &GravcalWatcherBoxType, &C.box, &GravcalEngineType,
                          &C.engine, &C.rows, &C.acc, &C.gyro, &C.codes))
        return NULL;
    unsigned char *buf = NULL;
    int ok = 0;
    PyThreadState *ts = NULL;
    long long *bus = busbuf.buf;
    if (call_open(&C, MAX_FRAMES_LIMIT) < 0)
        goto done;
    if (busbuf.len != IB_N * 8 || ((uintptr_t)bus & 7) || fd < 0 || !(seconds >= 0) || bus[IB_FIRST] < 1 ||
        bus[IB_BURST] < 1 || bus[IB_POLL_NS] < 0 || bus[IB_ADDRESS] < 0 || bus[IB_ADDRESS] > 0x7F) {
        PyErr_SetString(PyExc_ValueError, "fastpath.i2c_step: needs fd >= 0, seconds >= 0 and the IB_N int64 "
                                          "of daemon/fastpath.py (address 0..0x7F, first and burst >= 1)");
        goto done;
    }
    buf = PyMem_Malloc((size_t)C.max_frames * GRAVCAL_FRAME_LEN);
    if (buf == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    State *S = &C.S;
    bus[IB_POLLS] = bus[IB_BURSTS] = bus[IB_OVERFLOW] = bus[IB_ERRNO] = 0;
    long long deadline = now_ns() + (long long)(seconds * 1e9);
    for (;;) {
        if (ts == NULL)
            ts = PyEval_SaveThread();
        if (C.had + C.stage.n >= S->ist[IST_STAGE_LIMIT])
            break;
        Py_ssize_t before, n = read_fifo(fd, bus, deadline, buf, C.max_frames, &before);
        if (n == 0)
            break; /* due */
        if (n < 0 || bus[IB_OVERFLOW]) { /* the driver's: the frames read go back to it undecoded */
            n = n < 0 ? before : n;
            S->ist[IST_REASON] = bus[IB_ERRNO] ? R_ERROR : R_BYTES;
            gravcal_take_gil(&ts);
            C.leftover = PyBytes_FromStringAndSize((const char *)buf, n);
            if (C.leftover == NULL)
                goto done;
            break;
        }
        pthread_mutex_lock(&C.box->mu); /* without the GIL: a plain wait */
        int more;
        if (C.box->ready) {
            more = call_process_nogil(&C, buf, n, &ts);
        } else {
            pthread_mutex_unlock(&C.box->mu);
            gravcal_take_gil(&ts);
            PyObject *snapshot;
            int plain = call_prepare(&C, &snapshot);
            if (plain < 0)
                goto done;
            if (plain == 0) { /* R_NOT_PLAIN: the Python path's fanout decodes and delivers these */
                C.leftover = PyBytes_FromStringAndSize((const char *)buf, n);
                if (C.leftover == NULL)
                    goto done;
                break;
            }
            more = call_process(&C, buf, n, snapshot);
        }
        if (more < 0)
            goto done;
        if (more == 0)
            break;
    }
    ok = 1;
done:
    gravcal_take_gil(&ts);
    PyMem_Free(buf);
    PyBuffer_Release(&busbuf);
    return call_close(&C, ok);
}
