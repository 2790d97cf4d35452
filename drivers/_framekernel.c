/* The frame decoder's per-frame kernel (drivers/codec.py FrameDecoder, the one-frame-per-read path).
 *
 * frame_header(frame)                 -> (seq, tick) of an intact 29-byte frame, else None
 * frame_to_row(frame, row, seq, flags)   writes one SAMPLE_DTYPE row (core/samples.py) for it
 * sample_to_row(row, seq, tick, ...)       the same row from one sample's raw fields (drivers/can.py)
 * slcan_samples(data, base_id, ...)       the rows of slcan bytes that are whole CAN samples continuing the stream
 * stamp_rows(rows, tick_hz, t_recv, last_t)  the host times of a read's records (drivers/base.py Driver._stamp)
 *
 * The values are those of codec.wire_to_samples followed by the decoder's unwrapping: the wire
 * layout and the CRC are codec.py's (CRC-16/CCITT-FALSE over the whole frame is 0 when intact),
 * temp/vsupply are codec.temp_from_raw / vsupply_from_raw in float64 then stored as float32.
 * Built with -ffp-contract=off so each operation rounds as numpy's elementwise ops do.
 * One sample is well under a microsecond of work: the GIL is kept (dropping and retaking it costs more).
 * The record writer, and a whole read's records when it only continues the stream (stamped as the driver
 * stamps them), are exported to other kernels as a capsule (_framekernel.h; daemon/_fastcall.c).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "_framekernel.h"

#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__
#error "SAMPLE_DTYPE is little-endian: the records are written with native stores"
#endif

#define FRAME_LEN 29
#define PAYLOAD_LEN 24
#define SAMPLE_SIZE 56 /* SAMPLE_DTYPE: t f8, seq i8, tick u4, t1 4*u4, t2 2*u4, gyro u2, temp f4, vsupply f4, flags u2 */
#define ADC_FULL_SCALE 4095

static unsigned int u16le(const unsigned char *p) { return (unsigned int)p[0] | ((unsigned int)p[1] << 8); }

static uint32_t u32le(const unsigned char *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

/* binascii.crc_hqx(frame, 0xFFFF): CRC-16/CCITT-FALSE, poly 0x1021, MSB first */
static unsigned int crc_ccitt(const unsigned char *p, Py_ssize_t n)
{
    unsigned int crc = 0xFFFF;
    for (Py_ssize_t i = 0; i < n; i++) {
        crc ^= (unsigned int)p[i] << 8;
        for (int b = 0; b < 8; b++)
            crc = (crc & 0x8000) ? ((crc << 1) ^ 0x1021) & 0xFFFF : (crc << 1) & 0xFFFF;
    }
    return crc;
}

static int intact_bytes(const unsigned char *p, Py_ssize_t n)
{
    return n == FRAME_LEN && p[0] == 0xA5 && p[1] == 0x5A && p[2] == PAYLOAD_LEN && crc_ccitt(p, FRAME_LEN) == 0;
}

static int intact(const Py_buffer *f) { return intact_bytes(f->buf, f->len); }

/* codec._adc_volts: code * (2.5 V / 4096), NaN above the 12-bit full scale */
static double adc_volts(unsigned int code)
{
    return code > ADC_FULL_SCALE ? NAN : (double)code * (2.5 / 4096.0);
}

/* One SAMPLE_DTYPE record: t NaN (the driver stamps host time), the unwrapped seq, the raw fields, and
   temp/vsupply as codec.temp_from_raw / vsupply_from_raw compute them in float64, stored as float32. */
static void write_row(unsigned char *r, long long seq, uint32_t tick, const uint32_t t1[4], const uint32_t t2[2],
                      uint16_t gyro, unsigned int temp_raw, unsigned int vsupply_raw, uint16_t flags)
{
    double t = NAN;
    float temp = (float)((adc_volts(temp_raw) - 0.5) / 0.01); /* (V - 0.5 V) / 10 mV/°C */
    float vsupply = (float)(adc_volts(vsupply_raw) * 3.0);    /* V * 3 (1:3 divider) */
    memcpy(r + 0, &t, 8);
    memcpy(r + 8, &seq, 8);
    memcpy(r + 16, &tick, 4);
    memcpy(r + 20, t1, 16);
    memcpy(r + 36, t2, 8);
    memcpy(r + 44, &gyro, 2);
    memcpy(r + 46, &temp, 4);
    memcpy(r + 50, &vsupply, 4);
    memcpy(r + 54, &flags, 2);
}

static void to_row_c(const unsigned char *p, unsigned char *row, long long seq, uint16_t flags)
{
    uint32_t t1[4], t2[2];
    for (int c = 0; c < 4; c++)
        t1[c] = u16le(p + 9 + 2 * c);
    for (int k = 0; k < 2; k++)
        t2[k] = u16le(p + 17 + 2 * k);
    write_row(row, seq, u32le(p + 5), t1, t2, (uint16_t)u16le(p + 21), u16le(p + 23), u16le(p + 25), flags);
}

/* base.py Driver._stamp for k records: one at t_recv, several back from the newest by their tick distance
   (32-bit; a backwards step counts 0) / tick_hz (tick_hz 0: all at t_recv), never before *last_t (updated). */
static void stamp(unsigned char *rows, const uint32_t *ticks, Py_ssize_t k, double tick_hz, double t_recv,
                  double *last_t)
{
    double newest = *last_t;
    for (Py_ssize_t i = 0; i < k; i++) {
        double t = t_recv;
        if (k > 1 && tick_hz > 0) {
            uint32_t back = ticks[k - 1] - ticks[i];
            t = t_recv - (double)(back > 0x7FFFFFFFu ? 0u : back) / tick_hz;
        }
        if (t < newest)
            t = newest;
        newest = t;
        memcpy(rows + i * SAMPLE_SIZE, &t, 8);
    }
    *last_t = newest;
}

/* The records of a read that only continues the stream (the unwrapper's rule 2 with a step of 1, as
   SeqUnwrapper.unwrap decides it; the rule's one-frame reference: tests/support/sequence_reference.py
   continue_one): no gap, no stray, no restart; the 16-bit counter may wrap. Stamped as
   base.py Driver._stamp: one frame at t_recv, several back from the newest by their tick distance (32-bit;
   a backwards step counts 0) / tick_hz (tick_hz 0: all at t_recv), never before the newest stamp so far. */
static Py_ssize_t continuing_c(const unsigned char *buf, Py_ssize_t n, long long expect, Py_ssize_t max_frames,
                               long long seq0, double tick_hz, double t_recv, double *last_t, unsigned char *rows,
                               uint32_t *ticks)
{
    if (n == 0 || n % FRAME_LEN != 0 || n / FRAME_LEN > max_frames)
        return 0;
    Py_ssize_t k = n / FRAME_LEN;
    for (Py_ssize_t i = 0; i < k; i++) {
        const unsigned char *p = buf + i * FRAME_LEN;
        if (!intact_bytes(p, FRAME_LEN) || u16le(p + 3) != (unsigned int)((expect + i) & 0xFFFF))
            return 0;
        ticks[i] = u32le(p + 5);
    }
    for (Py_ssize_t i = 0; i < k; i++)
        to_row_c(buf + i * FRAME_LEN, rows + i * SAMPLE_SIZE, seq0 + i, 0);
    stamp(rows, ticks, k, tick_hz, t_recv, last_t);
    return k;
}

/* One hex digit's value (either case, as int(.., 16) and bytes.fromhex read it), else -1 */
static int hexval(unsigned char c)
{
    if (c >= '0' && c <= '9')
        return c - '0';
    c |= 0x20;
    return c >= 'a' && c <= 'f' ? c - 'a' + 10 : -1;
}

/* ``n`` hex digits at p as an integer (at most 32 bits), else -1 */
static long long hexnum(const unsigned char *p, int n)
{
    long long v = 0;
    for (int i = 0; i < n; i++) {
        int d = hexval(p[i]);
        if (d < 0)
            return -1;
        v = v << 4 | d;
    }
    return v;
}

/* drivers/can.py FRAME_DLC, and the length of a frame's slcan line ``t<3 hex id><dlc><2*dlc hex>\r`` */
static const int can_dlc[4] = {8, 7, 7, 5};
#define SLCAN_LINE(dlc) (6 + 2 * (dlc))
#define SLCAN_SAMPLE (SLCAN_LINE(8) + 2 * SLCAN_LINE(7) + SLCAN_LINE(5))

/* The payload of a standard data frame's line at p with the id and dlc given (into data), else -1 */
static int slcan_line(const unsigned char *p, long long id, int dlc, unsigned char *data)
{
    if (p[0] != 't' || hexnum(p + 1, 3) != id || p[4] != '0' + dlc || p[SLCAN_LINE(dlc) - 1] != '\r')
        return -1;
    for (int i = 0; i < dlc; i++) {
        long long b = hexnum(p + 5 + 2 * i, 2);
        if (b < 0)
            return -1;
        data[i] = (unsigned char)b;
    }
    return 0;
}

/* The records of one read of slcan bytes when it is exactly k <= max_samples samples, each the four frames
   base_id..base_id+3 in order (drivers/can.py: TIMING seq u16, tick u32, gyro u16; CHIP_A/B seq_lo, T1 x2, T2;
   HOUSEKEEPING seq_lo, temp_raw, vsupply_raw) whose seq continue ``expect`` one by one and whose frames all carry
   its low byte: SampleAssembler's complete sample, then the row of the reference's record_to_sample
   (tests/support/sequence_reference.py: the unwrapper's rule 2 with a step of 1), stamped as the driver stamps
   a read. k, or 0 (nothing written). */
static Py_ssize_t slcan_continuing_c(const unsigned char *buf, Py_ssize_t n, long long base_id, long long expect,
                                     Py_ssize_t max_samples, long long seq0, double tick_hz, double t_recv,
                                     double *last_t, unsigned char *rows, uint32_t *ticks)
{
    if (n == 0 || n % SLCAN_SAMPLE != 0 || n / SLCAN_SAMPLE > max_samples || base_id < 0 || base_id > 0x7FF - 3)
        return 0;
    Py_ssize_t k = n / SLCAN_SAMPLE;
    for (Py_ssize_t i = 0; i < k; i++) { /* all checked before any record is written */
        const unsigned char *p = buf + i * SLCAN_SAMPLE;
        unsigned char d[4][8];
        for (int f = 0; f < 4; f++) {
            if (slcan_line(p, base_id + f, can_dlc[f], d[f]) < 0)
                return 0;
            p += SLCAN_LINE(can_dlc[f]);
        }
        unsigned int seq = u16le(d[0]);
        if (seq != (unsigned int)((expect + i) & 0xFFFF) || d[1][0] != (seq & 0xFF) || d[2][0] != (seq & 0xFF) ||
            d[3][0] != (seq & 0xFF))
            return 0;
    }
    for (Py_ssize_t i = 0; i < k; i++) {
        const unsigned char *p = buf + i * SLCAN_SAMPLE;
        unsigned char d[4][8];
        for (int f = 0; f < 4; f++) {
            slcan_line(p, base_id + f, can_dlc[f], d[f]);
            p += SLCAN_LINE(can_dlc[f]);
        }
        /* t1 = (CHIP_A T1 ax, ay, CHIP_B T1 az, ax2), t2 = (CHIP_A T2, CHIP_B T2): SampleAssembler's order */
        uint32_t t1[4] = {u16le(d[1] + 1), u16le(d[1] + 3), u16le(d[2] + 1), u16le(d[2] + 3)};
        uint32_t t2[2] = {u16le(d[1] + 5), u16le(d[2] + 5)};
        ticks[i] = u32le(d[0] + 2);
        write_row(rows + i * SAMPLE_SIZE, seq0 + i, ticks[i], t1, t2, (uint16_t)u16le(d[0] + 6), u16le(d[3] + 1),
                  u16le(d[3] + 3), 0);
    }
    stamp(rows, ticks, k, tick_hz, t_recv, last_t);
    return k;
}

static const GravcalFrameAPI c_api = {to_row_c, continuing_c, slcan_continuing_c};

static PyObject *frame_header(PyObject *self, PyObject *args)
{
    Py_buffer f;
    if (!PyArg_ParseTuple(args, "y*:frame_header", &f))
        return NULL;
    if (!intact(&f)) {
        PyBuffer_Release(&f);
        Py_RETURN_NONE;
    }
    const unsigned char *p = f.buf;
    PyObject *out = Py_BuildValue("(Ik)", u16le(p + 3), (unsigned long)u32le(p + 5));
    PyBuffer_Release(&f);
    return out;
}

static PyObject *frame_to_row(PyObject *self, PyObject *args)
{
    Py_buffer f, row;
    long long seq;
    unsigned int flags;
    if (!PyArg_ParseTuple(args, "y*w*LI:frame_to_row", &f, &row, &seq, &flags))
        return NULL;
    if (!intact(&f) || row.len != SAMPLE_SIZE || flags > 0xFFFF) {
        const char *why = !intact(&f) ? "frame_to_row: not an intact 29-byte frame"
                          : row.len != SAMPLE_SIZE ? "frame_to_row: row must be one 56-byte SAMPLE_DTYPE record"
                                                   : "frame_to_row: flags must fit 16 bits";
        PyBuffer_Release(&f);
        PyBuffer_Release(&row);
        PyErr_SetString(PyExc_ValueError, why);
        return NULL;
    }
    to_row_c(f.buf, row.buf, seq, (uint16_t)flags);
    PyBuffer_Release(&f);
    PyBuffer_Release(&row);
    Py_RETURN_NONE;
}

static PyObject *sample_to_row(PyObject *self, PyObject *args)
{
    Py_buffer row;
    long long seq;
    unsigned long tick;
    unsigned int gyro, t1[4], t2[2], temp_raw, vsupply_raw, flags;
    if (!PyArg_ParseTuple(args, "w*LkI(IIII)(II)III:sample_to_row", &row, &seq, &tick, &gyro, &t1[0], &t1[1],
                          &t1[2], &t1[3], &t2[0], &t2[1], &temp_raw, &vsupply_raw, &flags))
        return NULL;
    const char *why = NULL;
    if (row.len != SAMPLE_SIZE)
        why = "sample_to_row: row must be one 56-byte SAMPLE_DTYPE record";
    else if (tick > 0xFFFFFFFFul || gyro > 0xFFFF || temp_raw > 0xFFFF || vsupply_raw > 0xFFFF || flags > 0xFFFF)
        why = "sample_to_row: tick must fit 32 bits, gyro, the ADC codes and flags 16 bits";
    if (why == NULL) {
        uint32_t a[4] = {t1[0], t1[1], t1[2], t1[3]}, b[2] = {t2[0], t2[1]};
        write_row(row.buf, seq, (uint32_t)tick, a, b, (uint16_t)gyro, temp_raw, vsupply_raw, (uint16_t)flags);
    }
    PyBuffer_Release(&row);
    if (why != NULL) {
        PyErr_SetString(PyExc_ValueError, why);
        return NULL;
    }
    Py_RETURN_NONE;
}

/* stamp_rows(rows, tick_hz, t_recv, last_t) -> last_t: Driver._stamp of a read's records (every bus's), their t
   written as ``stamp`` writes the C step's */
static PyObject *stamp_rows(PyObject *self, PyObject *args)
{
    Py_buffer rows;
    double tick_hz, t_recv, last_t;
    if (!PyArg_ParseTuple(args, "w*ddd:stamp_rows", &rows, &tick_hz, &t_recv, &last_t))
        return NULL;
    Py_ssize_t k = rows.len / SAMPLE_SIZE;
    uint32_t *ticks = NULL;
    const char *why = !PyBuffer_IsContiguous(&rows, 'C') || rows.len % SAMPLE_SIZE != 0
                          ? "stamp_rows: rows must be contiguous whole 56-byte SAMPLE_DTYPE records"
                          : NULL;
    if (why == NULL && k > 0 && (ticks = PyMem_Malloc(sizeof(uint32_t) * (size_t)k)) == NULL) {
        PyBuffer_Release(&rows);
        return PyErr_NoMemory();
    }
    for (Py_ssize_t i = 0; why == NULL && i < k; i++)
        memcpy(&ticks[i], (const unsigned char *)rows.buf + i * SAMPLE_SIZE + 16, 4);
    if (why == NULL)
        stamp(rows.buf, ticks, k, tick_hz, t_recv, &last_t);
    PyMem_Free(ticks);
    PyBuffer_Release(&rows);
    if (why != NULL) {
        PyErr_SetString(PyExc_ValueError, why);
        return NULL;
    }
    return PyFloat_FromDouble(last_t);
}

/* slcan_samples(data, base_id, expect, seq0, tick_hz, t_recv, last_t, rows) -> (k, last_t): the capsule's
   slcan_continuing for tests and tools; rows a writable buffer of whole 56-byte records (k <= their count) */
static PyObject *slcan_samples(PyObject *self, PyObject *args)
{
    Py_buffer data, rows;
    long long base_id, expect, seq0;
    double tick_hz, t_recv, last_t;
    if (!PyArg_ParseTuple(args, "y*LLLdddw*:slcan_samples", &data, &base_id, &expect, &seq0, &tick_hz, &t_recv,
                          &last_t, &rows))
        return NULL;
    const char *why = NULL;
    if (!PyBuffer_IsContiguous(&rows, 'C') || rows.len % SAMPLE_SIZE != 0 || rows.len == 0)
        why = "slcan_samples: rows must be contiguous whole 56-byte SAMPLE_DTYPE records";
    else if (base_id < 0 || base_id > 0x7FF - 3)
        why = "slcan_samples: base_id must leave room for 4 standard identifiers (0..0x7FC)";
    else if (expect < 0 || expect > 0xFFFF)
        why = "slcan_samples: expect must be a 16-bit sequence number";
    Py_ssize_t k = 0;
    uint32_t *ticks = NULL;
    if (why == NULL) {
        Py_ssize_t cap = rows.len / SAMPLE_SIZE;
        ticks = PyMem_Malloc(sizeof(uint32_t) * (size_t)cap);
        if (ticks == NULL) {
            PyBuffer_Release(&data);
            PyBuffer_Release(&rows);
            return PyErr_NoMemory();
        }
        k = slcan_continuing_c(data.buf, data.len, base_id, expect, cap, seq0, tick_hz, t_recv, &last_t, rows.buf,
                               ticks);
        PyMem_Free(ticks);
    }
    PyBuffer_Release(&data);
    PyBuffer_Release(&rows);
    if (why != NULL) {
        PyErr_SetString(PyExc_ValueError, why);
        return NULL;
    }
    return Py_BuildValue("(nd)", k, last_t);
}

static PyMethodDef methods[] = {
    {"slcan_samples", slcan_samples, METH_VARARGS,
     "slcan_samples(data, base_id, expect, seq0, tick_hz, t_recv, last_t, rows) -> (k, last_t): the records of "
     "slcan bytes that are exactly k whole CAN samples continuing the stream from raw seq ``expect``, else k 0."},
    {"stamp_rows", stamp_rows, METH_VARARGS,
     "stamp_rows(rows, tick_hz, t_recv, last_t) -> last_t: host times of a read's records: the newest at t_recv, "
     "earlier ones back by their tick distance / tick_hz (0: all at t_recv), never before last_t nor each other."},
    {"frame_header", frame_header, METH_VARARGS,
     "frame_header(frame) -> (seq, tick) of an intact 29-byte frame (sync, length, CRC), else None."},
    {"frame_to_row", frame_to_row, METH_VARARGS,
     "frame_to_row(frame, row, seq, flags): write the frame's SAMPLE_DTYPE record (t NaN) into the 56-byte row."},
    {"sample_to_row", sample_to_row, METH_VARARGS,
     "sample_to_row(row, seq, tick, gyro, t1[4], t2[2], temp_raw, vsupply_raw, flags): write the SAMPLE_DTYPE record "
     "(t NaN) of one sample's raw fields (a CAN sample's four frames) into the 56-byte row."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, .m_name = "_framekernel", .m_doc = "The frame decoder's per-frame kernel.", .m_size = -1,
                                    .m_methods = methods};

PyMODINIT_FUNC PyInit__framekernel(void)
{
    PyObject *m = PyModule_Create(&module);
    if (m == NULL)
        return NULL;
    PyObject *cap = PyCapsule_New((void *)&c_api, GRAVCAL_FRAME_CAPSULE, NULL);
    if (cap == NULL || PyModule_AddObject(m, "_C_API", cap) < 0) {
        Py_XDECREF(cap);
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
