/* The plain correction of one sample (core/correction.py PlainCorrection.one, the daemon's per-sample path).
 *
 * correct_row(row, offset, kinv_t, gyro_bias, gyro_sens, acc, gyro)
 *   row     one SAMPLE_DTYPE record (56 bytes, core/samples.py)
 *   offset  3 float64 o [duty];  kinv_t 9 float64, scale * K^-T row-major (PlainCorrection.kinv_t)
 *   acc     3 float64 out: a = scale * K^-1 (raw - o)  (Lötters 1998's linear model, solved for a)
 *   gyro    1 float64 out: (counts - bias) / sens     (NaN while either is unknown)
 *   returns the record's seq (the caller's static decision needs it; no numpy field access for it)
 *
 * Each step is PlainCorrection.block's numpy operation in the same order, so the bits match:
 * raw = T1 / T2 of the triad's chips (core.samples.duty_ratios, NaN where T2 = 0), x = raw - o,
 * a_j = (x0 * k[0][j] + x1 * k[1][j]) + x2 * k[2][j]. Built with -ffp-contract=off (no fused multiply-add).
 * One sample is well under a microsecond of work: the GIL is kept (dropping and retaking it costs more).
 * The same step is exported to other kernels as a capsule (_correctkernel.h; daemon/_fastpath.c).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "_correctkernel.h"

#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__
#error "SAMPLE_DTYPE is little-endian: the records are read with native loads"
#endif

#define SAMPLE_SIZE 56
#define SEQ_AT 8
#define T1_AT 20
#define T2_AT 36
#define GYRO_AT 44

static const int TRIAD_CHIP[3] = {0, 0, 1}; /* core.samples: channels ax, ay, az; CHANNEL_CHIP of each */

static long long correct_c(const unsigned char *r, const double *off, const double *kin, double bias, double sens,
                           double *acc, double *gyro)
{
    uint32_t t1[4], t2[2];
    uint16_t counts;
    long long seq;
    double o[3], k[9], x[3], a[3], g;
    memcpy(&seq, r + SEQ_AT, 8);
    memcpy(t1, r + T1_AT, 16);
    memcpy(t2, r + T2_AT, 8);
    memcpy(&counts, r + GYRO_AT, 2);
    memcpy(o, off, 24);
    memcpy(k, kin, 72);
    for (int i = 0; i < 3; i++) {
        uint32_t period = t2[TRIAD_CHIP[i]];
        x[i] = (period ? (double)t1[i] / (double)period : NAN) - o[i];
    }
    for (int j = 0; j < 3; j++)
        a[j] = x[0] * k[j] + x[1] * k[3 + j] + x[2] * k[6 + j];
    g = ((double)counts - bias) / sens;
    memcpy(acc, a, 24);
    memcpy(gyro, &g, 8);
    return seq;
}

static const GravcalCorrectAPI c_api = {correct_c};

static PyObject *correct_row(PyObject *self, PyObject *args)
{
    Py_buffer row, off, kin, acc, gyr;
    double bias, sens;
    long long seq = 0;
    if (!PyArg_ParseTuple(args, "y*y*y*ddw*w*:correct_row", &row, &off, &kin, &bias, &sens, &acc, &gyr))
        return NULL;
    const char *why = row.len != SAMPLE_SIZE ? "correct_row: row must be one 56-byte SAMPLE_DTYPE record"
                      : off.len != 3 * 8     ? "correct_row: offset must be 3 float64"
                      : kin.len != 9 * 8     ? "correct_row: kinv_t must be 3x3 float64"
                      : acc.len != 3 * 8     ? "correct_row: acc must be 3 float64"
                      : gyr.len != 8         ? "correct_row: gyro must be 1 float64"
                                             : NULL;
    if (why == NULL)
        seq = correct_c(row.buf, off.buf, kin.buf, bias, sens, acc.buf, gyr.buf);
    PyBuffer_Release(&row);
    PyBuffer_Release(&off);
    PyBuffer_Release(&kin);
    PyBuffer_Release(&acc);
    PyBuffer_Release(&gyr);
    if (why != NULL) {
        PyErr_SetString(PyExc_ValueError, why);
        return NULL;
    }
    return PyLong_FromLongLong(seq);
}

static PyMethodDef methods[] = {
    {"correct_row", correct_row, METH_VARARGS,
     "correct_row(row, offset, kinv_t, gyro_bias, gyro_sens, acc, gyro): the plain correction of one SAMPLE_DTYPE "
     "record into acc (3 float64) and gyro (1 float64); returns the record's seq."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, .m_name = "_correctkernel", .m_doc = "The plain correction of one sample.", .m_size = -1,
                                    .m_methods = methods};

PyMODINIT_FUNC PyInit__correctkernel(void)
{
    PyObject *m = PyModule_Create(&module);
    if (m == NULL)
        return NULL;
    PyObject *cap = PyCapsule_New((void *)&c_api, GRAVCAL_CORRECT_CAPSULE, NULL);
    if (cap == NULL || PyModule_AddObject(m, "_C_API", cap) < 0) {
        Py_XDECREF(cap);
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
