/* The IMU lines of gravcald's samples (daemon/protocol.py encode_imu_joined; the C step's, daemon/_fastcall.c).
 *
 * imu_line(row, acc, gyro, static, raw) -> bytes
 *   row     one SAMPLE_DTYPE record (56 bytes, core/samples.py); acc 3 float64 [m/s²]; gyro float [rad/s]
 *   static  a bool or an int code: 1 still, 0 moving, <= -1 unknown (protocol.static_words, clipped to -1..1)
 *   raw     add the driver's raw fields
 *
 * The bytes are those of the %-templates (protocol._HEAD_FIELDS / _RAW_FIELDS; their numpy form, the oracle, is
 * tests/support/line_reference.py): each %.Nf
 * is PyOS_double_to_string(x, 'f', N, 0) as Python's % does, each %d the integer, and a number that is
 * not finite is the word null (what the block encoder's replacement of nan/inf/-inf gives). The duty cycles
 * are core.samples.duty_ratios: T1 / T2 of the channel's chip, NaN where T2 = 0.
 * imu_lines(rows, acc, gyro, static, raw) -> the lines of a block, joined (every block gravcald publishes).
 *
 * Numbers below 2^53 (x 10^N below 2^64) are written in integer arithmetic (put_f_exact), the rest by
 * PyOS_double_to_string, which allocates with PyMem: the GIL is kept. A raw line takes ~0.7 µs warm
 * (1.2-1.9 µs with dtoa for every number).
 * The same writer is exported to other kernels as a capsule (_linekernel.h; daemon/_fastcall.c).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "_linekernel.h"

#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__
#error "SAMPLE_DTYPE is little-endian: the records are read with native loads"
#endif

#define SAMPLE_SIZE 56
/* 11 floats of at most 309 integer digits + 7, 12 integers of at most 20 digits, and the keys */
#define IMU_LINE_MAX GRAVCAL_IMU_LINE_MAX

static const int CHANNEL_CHIP[4] = {0, 0, 1, 1}; /* core.samples.CHANNEL_CHIP */

typedef struct {
    char buf[IMU_LINE_MAX];
    size_t n;
    int failed;
    int nogil; /* written without the GIL: a number put_f_exact cannot write fails the line (-2: ask with the GIL) */
} Line;

static void put(Line *L, const char *s, size_t k)
{
    if (L->failed || L->n + k > IMU_LINE_MAX) {
        L->failed = 1;
        return;
    }
    memcpy(L->buf + L->n, s, k);
    L->n += k;
}

static void put_s(Line *L, const char *s) { put(L, s, strlen(s)); }

static const uint64_t POW10[10] = {1ull, 10ull, 100ull, 1000ull, 10000ull, 100000ull, 1000000ull, 10000000ull,
                                    100000000ull, 1000000000ull};

/* "%.{prec}f" % x for prec <= 9 in integer arithmetic, or 0 when |x| is too large for it (the caller asks
 * PyOS_double_to_string then). x = m 2^e exactly (m < 2^53), so x 10^prec = m 10^prec 2^e (m 10^prec < 2^83) is
 * shifted right by -e and rounded half to even on the exact remainder: the correctly rounded digits that
 * PyOS_double_to_string(x, 'f', prec, 0) writes (David Gay's dtoa, mode 3), sign of a negative zero included. */
static int put_f_exact(Line *L, double x, int prec)
{
    uint64_t bits;
    memcpy(&bits, &x, sizeof bits);
    int biased = (int)((bits >> 52) & 0x7ff);
    uint64_t m = bits & ((1ull << 52) - 1);
    int e = biased ? biased - 1075 : -1074;
    if (biased)
        m |= 1ull << 52;
    if (e > 0 || prec < 0 || prec > 9)
        return 0; /* |x| >= 2^53: rare on the socket, the general path */
    unsigned __int128 v = (unsigned __int128)m * POW10[prec], q;
    int shift = -e;
    if (shift >= 128) {
        q = 0; /* below 2^-1074 * 2^83 / 2^128: far under half a unit of the last digit */
    } else {
        q = shift ? v >> shift : v;
        if (shift) {
            const unsigned __int128 one = 1;
            unsigned __int128 rem = v & ((one << shift) - 1), half = one << (shift - 1);
            if (rem > half || (rem == half && (q & 1)))
                q += 1;
        }
    }
    if (q >> 64)
        return 0;
    uint64_t u = (uint64_t)q, ip = u / POW10[prec], fp = u % POW10[prec];
    char s[48];
    int k = sizeof s;
    for (int d = 0; d < prec; d++) {
        s[--k] = (char)('0' + fp % 10);
        fp /= 10;
    }
    if (prec)
        s[--k] = '.';
    do {
        s[--k] = (char)('0' + ip % 10);
        ip /= 10;
    } while (ip);
    if (bits >> 63)
        s[--k] = '-';
    put(L, s + k, sizeof s - (size_t)k);
    return 1;
}

/* "%.{prec}f" % x, or null when x is not finite */
static void put_f(Line *L, double x, int prec)
{
    if (!isfinite(x)) {
        put_s(L, "null");
        return;
    }
    if (put_f_exact(L, x, prec))
        return;
    if (L->nogil) {
        L->failed = 1;
        return;
    }
    char *s = PyOS_double_to_string(x, 'f', prec, 0, NULL);
    if (s == NULL) {
        L->failed = 1;
        return;
    }
    put_s(L, s);
    PyMem_Free(s);
}

/* "%d" % v: decimal digits, a leading '-' when negative (no snprintf: its format parsing is most of the cost) */
static void put_i(Line *L, long long v)
{
    char s[24];
    int k = sizeof s;
    unsigned long long u = v < 0 ? 0ull - (unsigned long long)v : (unsigned long long)v;
    do {
        s[--k] = (char)('0' + u % 10);
        u /= 10;
    } while (u);
    if (v < 0)
        s[--k] = '-';
    put(L, s + k, sizeof s - (size_t)k);
}

/* protocol.static_words: clip(code, -1, 1) */
static const char *word_of(long long c) { return c >= 1 ? "true" : c == 0 ? "false" : "null"; }

static const char *static_word(PyObject *code)
{
    if (!PyNumber_Check(code)) {
        PyErr_SetString(PyExc_TypeError, "imu_line: static must be a bool or an integer code");
        return NULL;
    }
    PyObject *v = PyNumber_Long(code); /* a bool is 0 or 1: the same words as the codes */
    if (v == NULL)
        return NULL;
    int overflow;
    long long c = PyLong_AsLongLongAndOverflow(v, &overflow);
    Py_DECREF(v);
    if (c == -1 && PyErr_Occurred())
        return NULL;
    if (overflow)
        c = overflow;
    return word_of(c);
}

/* One IMU line into L (see the top of this file for the fields and formats). */
static void write_line(Line *L, const unsigned char *r, const double *acc, double gyro_rate, const char *word, int raw)
{
    double t, a[3];
    long long seq;
    uint32_t tick, t1[4], t2[2];
    uint16_t counts, flags;
    float temp, vsupply;
    memcpy(&t, r + 0, 8);
    memcpy(&seq, r + 8, 8);
    memcpy(&tick, r + 16, 4);
    memcpy(t1, r + 20, 16);
    memcpy(t2, r + 36, 8);
    memcpy(&counts, r + 44, 2);
    memcpy(&temp, r + 46, 4);
    memcpy(&vsupply, r + 50, 4);
    memcpy(&flags, r + 54, 2);
    memcpy(a, acc, 24);
    /* _HEAD_FIELDS: {"class":"IMU","seq":%d,"t":%.6f,"acc":[%.5f,%.5f,%.5f],"gyro":%.6f|null,"static":%s,
       "temp":%.2f,"vsupply":%.3f */
    put_s(L, "{\"class\":\"IMU\",\"seq\":");
    put_i(L, seq);
    put_s(L, ",\"t\":");
    put_f(L, t, 6);
    put_s(L, ",\"acc\":[");
    for (int j = 0; j < 3; j++) {
        if (j)
            put_s(L, ",");
        put_f(L, a[j], 5);
    }
    put_s(L, "],\"gyro\":");
    put_f(L, gyro_rate, 6);
    put_s(L, ",\"static\":");
    put_s(L, word);
    put_s(L, ",\"temp\":");
    put_f(L, (double)temp, 2);
    put_s(L, ",\"vsupply\":");
    put_f(L, (double)vsupply, 3);
    if (raw) {
        /* _RAW_FIELDS: ,"duty":[%.6f x4],"t1":[%d x4],"t2":[%d,%d],"gyro_counts":%d,"tick":%d,"flags":%d} */
        put_s(L, ",\"duty\":[");
        for (int c = 0; c < 4; c++) {
            uint32_t period = t2[CHANNEL_CHIP[c]];
            if (c)
                put_s(L, ",");
            put_f(L, period ? (double)t1[c] / (double)period : NAN, 6);
        }
        put_s(L, "],\"t1\":[");
        for (int c = 0; c < 4; c++) {
            if (c)
                put_s(L, ",");
            put_i(L, t1[c]);
        }
        put_s(L, "],\"t2\":[");
        put_i(L, t2[0]);
        put_s(L, ",");
        put_i(L, t2[1]);
        put_s(L, "],\"gyro_counts\":");
        put_i(L, counts);
        put_s(L, ",\"tick\":");
        put_i(L, tick);
        put_s(L, ",\"flags\":");
        put_i(L, flags);
    }
    put_s(L, "}\n");
}

static Py_ssize_t line_c(const unsigned char *row, const double *acc, double gyro, long long static_code, int raw,
                         char *out, Py_ssize_t cap)
{
    Line *L = PyMem_Malloc(sizeof(Line));
    if (L == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    L->n = 0;
    L->failed = L->nogil = 0;
    write_line(L, row, acc, gyro, word_of(static_code), raw);
    Py_ssize_t n = -1;
    if (L->failed || (Py_ssize_t)L->n > cap) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_ValueError, "imu_line: the line does not fit its buffer");
    } else {
        memcpy(out, L->buf, L->n);
        n = (Py_ssize_t)L->n;
    }
    PyMem_Free(L);
    return n;
}

/* line_c without the GIL: -2 when the line needs it (a number beyond put_f_exact, or it does not fit ``cap``) */
static Py_ssize_t line_nogil_c(const unsigned char *row, const double *acc, double gyro, long long static_code,
                               int raw, char *out, Py_ssize_t cap)
{
    Line L;
    L.n = 0;
    L.failed = 0;
    L.nogil = 1;
    write_line(&L, row, acc, gyro, word_of(static_code), raw);
    if (L.failed || (Py_ssize_t)L.n > cap)
        return -2;
    memcpy(out, L.buf, L.n);
    return (Py_ssize_t)L.n;
}

static const GravcalLineAPI c_api = {line_c, line_nogil_c};

static PyObject *imu_line(PyObject *self, PyObject *args)
{
    Py_buffer row, acc;
    double gyro_rate;
    PyObject *code;
    int raw;
    if (!PyArg_ParseTuple(args, "y*y*dOp:imu_line", &row, &acc, &gyro_rate, &code, &raw))
        return NULL;
    if (row.len != SAMPLE_SIZE || acc.len != 3 * 8) {
        PyErr_SetString(PyExc_ValueError, row.len != SAMPLE_SIZE
                                              ? "imu_line: row must be one 56-byte SAMPLE_DTYPE record"
                                              : "imu_line: acc must be 3 float64");
        PyBuffer_Release(&row);
        PyBuffer_Release(&acc);
        return NULL;
    }
    const char *word = static_word(code);
    if (word == NULL) {
        PyBuffer_Release(&row);
        PyBuffer_Release(&acc);
        return NULL;
    }
    Line *L = PyMem_Malloc(sizeof(Line));
    if (L == NULL) {
        PyBuffer_Release(&row);
        PyBuffer_Release(&acc);
        return PyErr_NoMemory();
    }
    L->n = 0;
    L->failed = L->nogil = 0;
    write_line(L, row.buf, acc.buf, gyro_rate, word, raw);
    PyBuffer_Release(&row);
    PyBuffer_Release(&acc);
    PyObject *out = NULL;
    if (L->failed) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_ValueError, "imu_line: the line does not fit its buffer");
    } else {
        out = PyBytes_FromStringAndSize(L->buf, (Py_ssize_t)L->n);
    }
    PyMem_Free(L);
    return out;
}

/* imu_lines(rows, acc, gyro, codes, raw) -> the joined lines of N records: rows N SAMPLE_DTYPE records, acc 3N
   float64, gyro N float64, codes N int8 static codes (1 still, 0 moving, <= -1 unknown) */
static PyObject *imu_lines(PyObject *self, PyObject *args)
{
    Py_buffer rows, acc, gyro, codes;
    int raw;
    if (!PyArg_ParseTuple(args, "y*y*y*y*p:imu_lines", &rows, &acc, &gyro, &codes, &raw))
        return NULL;
    Py_ssize_t n = rows.len / SAMPLE_SIZE, used = 0, cap = 0;
    char *buf = NULL;
    const char *why = rows.len % SAMPLE_SIZE ? "imu_lines: rows must be whole 56-byte SAMPLE_DTYPE records"
                      : acc.len != 24 * n    ? "imu_lines: acc must be 3 float64 per record"
                      : gyro.len != 8 * n    ? "imu_lines: gyro must be 1 float64 per record"
                      : codes.len != n       ? "imu_lines: static must be 1 int8 code per record"
                                             : NULL;
    if (why != NULL)
        PyErr_SetString(PyExc_ValueError, why);
    for (Py_ssize_t i = 0; why == NULL && i < n; i++) {
        if (cap - used < IMU_LINE_MAX) {
            Py_ssize_t grown = cap ? 2 * cap : (n < 16 ? n : 16) * 512 + IMU_LINE_MAX;
            char *p = PyMem_Realloc(buf, (size_t)grown);
            if (p == NULL) {
                PyErr_NoMemory();
                why = "";
                break;
            }
            buf = p;
            cap = grown;
        }
        double g;
        memcpy(&g, (const char *)gyro.buf + 8 * i, 8);
        Py_ssize_t m = line_c((const unsigned char *)rows.buf + SAMPLE_SIZE * i, (const double *)acc.buf + 3 * i, g,
                              ((const signed char *)codes.buf)[i], raw, buf + used, cap - used);
        if (m < 0)
            why = "";
        else
            used += m;
    }
    PyObject *out = why == NULL ? PyBytes_FromStringAndSize(buf, used) : NULL;
    PyMem_Free(buf);
    PyBuffer_Release(&rows);
    PyBuffer_Release(&acc);
    PyBuffer_Release(&gyro);
    PyBuffer_Release(&codes);
    return out;
}

static PyMethodDef methods[] = {
    {"imu_lines", imu_lines, METH_VARARGS,
     "imu_lines(rows, acc, gyro, static, raw) -> the IMU lines (bytes, joined) of N SAMPLE_DTYPE records, each "
     "imu_line's."},
    {"imu_line", imu_line, METH_VARARGS,
     "imu_line(row, acc, gyro, static, raw) -> the IMU line (bytes) of one SAMPLE_DTYPE record, byte for byte "
     "the block encoder's."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, .m_name = "_linekernel", .m_doc = "The IMU line of one sample.", .m_size = -1,
                                    .m_methods = methods};

PyMODINIT_FUNC PyInit__linekernel(void)
{
    PyObject *m = PyModule_Create(&module);
    if (m == NULL)
        return NULL;
    PyObject *cap = PyCapsule_New((void *)&c_api, GRAVCAL_LINE_CAPSULE, NULL);
    if (cap == NULL || PyModule_AddObject(m, "_C_API", cap) < 0) {
        Py_XDECREF(cap);
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
