/* The frame decoder's per-frame kernel (drivers/codec.py FrameDecoder, the one-frame-per-read path).
 *
 * frame_header(frame)                 -> (seq, tick) of an intact 29-byte frame, else None
 * frame_to_row(frame, row, seq, flags)   writes one SAMPLE_DTYPE row (core/samples.py) for it
 * sample_to_row(row, seq, tick, ...)       the same row from one sample's raw fields (drivers/can.py)
 *
 * The values are those of codec.wire_to_samples followed by the decoder's unwrapping: the wire
 * layout and the CRC are codec.py's (CRC-16/CCITT-FALSE over the whole frame is 0 when intact),
 * temp/vsupply are codec.temp_from_raw / vsupply_from_raw in float64 then stored as float32.
 * Built with -ffp-contract=off so each operation rounds as numpy's elementwise ops do.
 * One sample is well under a microsecond of work: the GIL is kept (dropping and retaking it costs more).
 * The record writer, and a whole read's records when it only continues the stream (stamped as the driver
 * stamps them), are exported to other kernels as a capsule (_framekernel.h; daemon/_fastpath.c).
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

/* The records of a read that only continues the stream (the unwrapper's rule 2 with a step of 1, sequence.py
   SeqUnwrapper.continue_one: no gap, no stray, no restart; the 16-bit counter may wrap), stamped as
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
    double newest = *last_t;
    for (Py_ssize_t i = 0; i < k; i++) {
        unsigned char *row = rows + i * SAMPLE_SIZE;
        to_row_c(buf + i * FRAME_LEN, row, seq0 + i, 0);
        double t = t_recv;
        if (k > 1 && tick_hz > 0) {
            uint32_t back = ticks[k - 1] - ticks[i];
            t = t_recv - (double)(back > 0x7FFFFFFFu ? 0u : back) / tick_hz;
        }
        if (t < newest)
            t = newest;
        newest = t;
        memcpy(row, &t, 8);
    }
    *last_t = newest;
    return k;
}

static const GravcalFrameAPI c_api = {to_row_c, continuing_c};

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

static PyMethodDef methods[] = {
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
