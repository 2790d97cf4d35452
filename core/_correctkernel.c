/* The correction of each published sample (core/correction.py; gravcald's per-sample engine, daemon/_engine.c).
 *
 * correct_rows(rows, params, gyro_bias, gyro_sens, acc, gyro) -> seq of the last record (None: no record)
 *   rows    N SAMPLE_DTYPE records (56 bytes each, core/samples.py)
 *   params  CP_N float64: a calibration as core/correction.py correction_params packs it (_correctkernel.h)
 *   acc     3N float64 out: a = scale (K + dK)^-1 (raw - o - do), dK, do the terms at each record's covariates
 *   gyro    N float64 out: (counts - bias) / sens  (NaN while either is unknown)
 *
 * The calibrated model (core/calibration.py Calibration.apply, core/model/effect.py apply_terms) is
 *   raw = (K + dK) a + o + do,   do_i = sum_c p_oc,i z_c,i,   dK_ii = sum_c p_sc,i z_c,i
 * with z_c the covariate's deviation from its reference: temperature [°C], supply [V], time [h] (seq / fs from
 * t0 [s]) and, for the nonlinearity, |K_ii| a0_i² with a0 = K^-1 (raw - o). A plain calibration (no covariate)
 * takes the plain form a_j = (x0 k[0][j] + x1 k[1][j]) + x2 k[2][j], x = raw - o, in that order: the bits of
 * the numpy reference plain_block (tests/support/correction_reference.py). With sensitivity terms the 3x3
 * system is solved by its adjugate, within a few ulps times K's condition number of LAPACK's solve.
 * raw = T1 / T2 of the triad's chips (core.samples.duty_ratios, NaN where T2 = 0). Built with
 * -ffp-contract=off (no fused multiply-add). The same step is exported as a capsule (_correctkernel.h).
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
#define TEMP_AT 46
#define VSUPPLY_AT 50

static const int TRIAD_CHIP[3] = {0, 0, 1}; /* core.samples: channels ax, ay, az; CHANNEL_CHIP of each */

static const char *unpack(const double *v, GravcalCorrection *c)
{
    memcpy(c->o, v + CP_OFFSET, sizeof c->o);
    memcpy(c->kinv_t, v + CP_KINV_T, sizeof c->kinv_t);
    memcpy(c->k, v + CP_K, sizeof c->k);
    memcpy(c->ref, v + CP_REF, sizeof c->ref);
    memcpy(c->coef, v + CP_COEF, sizeof c->coef);
    c->scale = v[CP_SCALE];
    c->fs = v[CP_FS];
    c->extended = c->on_sens = 0;
    for (int cov = 0; cov < COV_N; cov++) {
        double u = v[CP_USES + cov];
        if (u != 0.0 && u != 1.0)
            return "a covariate's use flag must be 0 or 1";
        c->uses[cov] = u == 1.0;
        c->extended |= c->uses[cov];
        for (int i = 0; i < 3 && c->uses[cov]; i++)
            c->on_sens |= c->coef[ON_SENSITIVITY][cov][i] != 0.0;
    }
    if (c->uses[COV_TIME] && !(c->fs > 0.0))
        return "a time term needs the sample rate (fs > 0)";
    return NULL;
}

/* a = scale * M^-1 x for M = K + diag(dk), by the adjugate */
static void solve_shifted(const GravcalCorrection *c, const double dk[3], const double x[3], double a[3])
{
    double m[9];
    memcpy(m, c->k, sizeof m);
    m[0] += dk[0];
    m[4] += dk[1];
    m[8] += dk[2];
    double adj[9] = {m[4] * m[8] - m[5] * m[7], m[2] * m[7] - m[1] * m[8], m[1] * m[5] - m[2] * m[4],
                     m[5] * m[6] - m[3] * m[8], m[0] * m[8] - m[2] * m[6], m[2] * m[3] - m[0] * m[5],
                     m[3] * m[7] - m[4] * m[6], m[1] * m[6] - m[0] * m[7], m[0] * m[4] - m[1] * m[3]};
    double det = m[0] * adj[0] + m[1] * adj[3] + m[2] * adj[6];
    for (int j = 0; j < 3; j++)
        a[j] = (adj[3 * j] * x[0] + adj[3 * j + 1] * x[1] + adj[3 * j + 2] * x[2]) / det * c->scale;
}

static long long correct_c(const unsigned char *r, const GravcalCorrection *c, double bias, double sens,
                           double *acc, double *gyro)
{
    uint32_t t1[4], t2[2];
    uint16_t counts;
    long long seq;
    float temp, vsupply;
    double x[3], a[3], g;
    memcpy(&seq, r + SEQ_AT, 8);
    memcpy(t1, r + T1_AT, 16);
    memcpy(t2, r + T2_AT, 8);
    memcpy(&counts, r + GYRO_AT, 2);
    for (int i = 0; i < 3; i++) {
        uint32_t period = t2[TRIAD_CHIP[i]];
        x[i] = (period ? (double)t1[i] / (double)period : NAN) - c->o[i];
    }
    const double *k = c->kinv_t;
    for (int j = 0; j < 3; j++)
        a[j] = x[0] * k[j] + x[1] * k[3 + j] + x[2] * k[6 + j];
    if (c->extended) {
        double z[COV_N][3], dk[3] = {0, 0, 0};
        memcpy(&temp, r + TEMP_AT, 4);
        memcpy(&vsupply, r + VSUPPLY_AT, 4);
        double zs[3] = {(double)temp - c->ref[COV_TEMP], (double)vsupply - c->ref[COV_VSUPPLY],
                        ((double)seq / c->fs - c->ref[COV_TIME]) / 3600.0};
        for (int i = 0; i < 3; i++) {
            for (int cov = 0; cov < COV_ACCEL; cov++)
                z[cov][i] = zs[cov];
            double a0 = a[i] / c->scale; /* the plain form's a, in g */
            z[COV_ACCEL][i] = fabs(c->k[4 * i]) * a0 * a0;
        }
        for (int cov = 0; cov < COV_N; cov++) {
            if (!c->uses[cov])
                continue; /* a covariate no term needs: its NaN must not reach the result */
            for (int i = 0; i < 3; i++) {
                x[i] -= c->coef[ON_OFFSET][cov][i] * z[cov][i];
                dk[i] += c->coef[ON_SENSITIVITY][cov][i] * z[cov][i];
            }
        }
        if (c->on_sens)
            solve_shifted(c, dk, x, a);
        else
            for (int j = 0; j < 3; j++)
                a[j] = x[0] * k[j] + x[1] * k[3 + j] + x[2] * k[6 + j];
    }
    g = ((double)counts - bias) / sens;
    memcpy(acc, a, 24);
    memcpy(gyro, &g, 8);
    return seq;
}

static const GravcalCorrectAPI c_api = {unpack, correct_c};

static PyObject *correct_rows(PyObject *self, PyObject *args)
{
    Py_buffer rows, par, acc, gyr;
    double bias, sens;
    long long seq = 0;
    if (!PyArg_ParseTuple(args, "y*y*ddw*w*:correct_rows", &rows, &par, &bias, &sens, &acc, &gyr))
        return NULL;
    Py_ssize_t n = rows.len / SAMPLE_SIZE;
    GravcalCorrection c;
    const char *why = rows.len % SAMPLE_SIZE ? "correct_rows: rows must be whole 56-byte SAMPLE_DTYPE records"
                      : par.len != CP_N * 8  ? "correct_rows: params must be the CP_N float64 of correction_params"
                      : acc.len != 24 * n    ? "correct_rows: acc must be 3 float64 per record"
                      : gyr.len != 8 * n     ? "correct_rows: gyro must be 1 float64 per record"
                                             : unpack(par.buf, &c);
    if (why == NULL)
        for (Py_ssize_t i = 0; i < n; i++)
            seq = correct_c((const unsigned char *)rows.buf + i * SAMPLE_SIZE, &c, bias, sens,
                            (double *)acc.buf + 3 * i, (double *)gyr.buf + i);
    PyBuffer_Release(&rows);
    PyBuffer_Release(&par);
    PyBuffer_Release(&acc);
    PyBuffer_Release(&gyr);
    if (why != NULL) {
        PyErr_SetString(PyExc_ValueError, why);
        return NULL;
    }
    if (n == 0)
        Py_RETURN_NONE;
    return PyLong_FromLongLong(seq);
}

static PyMethodDef methods[] = {
    {"correct_rows", correct_rows, METH_VARARGS,
     "correct_rows(rows, params, gyro_bias, gyro_sens, acc, gyro): the correction of SAMPLE_DTYPE records into acc "
     "(3 float64 each) and gyro (1 float64 each); returns the last record's seq (None: no record)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, .m_name = "_correctkernel",
                                    .m_doc = "The correction of each published sample.", .m_size = -1,
                                    .m_methods = methods};

PyMODINIT_FUNC PyInit__correctkernel(void)
{
    PyObject *m = PyModule_Create(&module);
    if (m == NULL)
        return NULL;
    PyObject *cap = PyCapsule_New((void *)&c_api, GRAVCAL_CORRECT_CAPSULE, NULL);
    if (cap == NULL || PyModule_AddObject(m, "_C_API", cap) < 0 || PyModule_AddIntConstant(m, "CP_N", CP_N) < 0) {
        Py_XDECREF(cap);
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
