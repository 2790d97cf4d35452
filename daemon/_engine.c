/* The per-sample engine's parameters and its correction of one record (see _engine.h). Part of
 * gravcal.daemon._fastpath.
 *
 * Engine()                       no parameters yet (the step and correct refuse to run without)
 * Engine.set_params(vector)      the one setter: EP_N float64 (_engine.h), copied and swapped whole
 * Engine.correct(rows, acc, gyro, static) -> samples whose static is unknown: what the step does per record, for
 *                                a block the Python path publishes (the same parameters, the same bits)
 * Engine.generation              swaps so far
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#include "_engine.h"

static const GravcalCorrectAPI *correct_api;

int gravcal_engine_init(void)
{
    if (correct_api != NULL)
        return 0;
    PyObject *m = PyImport_ImportModule("gravcal.core._correctkernel");
    if (m == NULL)
        return -1;
    Py_DECREF(m);
    correct_api = PyCapsule_Import(GRAVCAL_CORRECT_CAPSULE, 0);
    return correct_api == NULL ? -1 : 0;
}

void gravcal_engine_current(Engine *e, EngineParams *out, long long *generation)
{
    if (__atomic_load_n(&e->generation, __ATOMIC_ACQUIRE) == *generation)
        return;
    pthread_mutex_lock(&e->mu);
    *out = e->p;
    *generation = e->generation;
    pthread_mutex_unlock(&e->mu);
}

long long gravcal_engine_sample(const EngineParams *p, const unsigned char *row, double *acc, double *gyro,
                                signed char *code)
{
    long long seq = correct_api->correct(row, &p->corr, p->bias, p->sens, acc, gyro);
    /* the detector's decision while at most max_age samples older than the record, else unknown */
    *code = (signed char)(p->have_last && (double)(seq - p->last) <= p->max_age ? p->still : -1);
    return seq;
}

static PyObject *engine_new(PyTypeObject *type, PyObject *args, PyObject *kwds)
{
    if (PyTuple_GET_SIZE(args) != 0 || (kwds != NULL && PyDict_GET_SIZE(kwds) != 0)) {
        PyErr_SetString(PyExc_TypeError, "Engine() takes no arguments");
        return NULL;
    }
    Engine *e = (Engine *)type->tp_alloc(type, 0);
    if (e == NULL)
        return NULL;
    if (pthread_mutex_init(&e->mu, NULL) != 0) {
        Py_DECREF(e);
        PyErr_SetString(PyExc_RuntimeError, "Engine: cannot create its lock");
        return NULL;
    }
    return (PyObject *)e;
}

static void engine_dealloc(Engine *e)
{
    pthread_mutex_destroy(&e->mu);
    Py_TYPE(e)->tp_free((PyObject *)e);
}

static const char *unpack_engine(const double *v, EngineParams *p)
{
    const char *why = correct_api->unpack(v, &p->corr);
    if (why != NULL)
        return why;
    double have = v[EP_HAVE_LAST], still = v[EP_STILL], last = v[EP_LAST_SEQ];
    if ((have != 0.0 && have != 1.0) || (still != 0.0 && still != 1.0))
        return "the detector's decision flags must be 0 or 1";
    if (have == 1.0 && !(last == (double)(long long)last))
        return "the decision's seq must be an integer";
    p->bias = v[EP_GYRO_BIAS];
    p->sens = v[EP_GYRO_SENS];
    p->max_age = v[EP_MAX_AGE];
    p->have_last = have == 1.0;
    p->still = still == 1.0;
    p->last = p->have_last ? (long long)last : 0;
    return NULL;
}

static PyObject *engine_set_params(Engine *e, PyObject *arg)
{
    Py_buffer v;
    if (PyObject_GetBuffer(arg, &v, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
        return NULL;
    EngineParams p;
    const char *why = v.len != EP_N * 8 || v.itemsize != 8 || v.format == NULL || strchr(v.format, 'd') == NULL
                          ? "Engine.set_params: needs the EP_N float64 of daemon/processing.py"
                          : unpack_engine(v.buf, &p);
    PyBuffer_Release(&v);
    if (why != NULL) {
        PyErr_Format(PyExc_ValueError, "Engine.set_params: %s", why);
        return NULL;
    }
    pthread_mutex_lock(&e->mu); /* a leaf (_engine.h): never held by a thread waiting for the GIL */
    e->p = p;
    e->set = 1;
    __atomic_store_n(&e->generation, e->generation + 1, __ATOMIC_RELEASE);
    pthread_mutex_unlock(&e->mu);
    Py_RETURN_NONE;
}

static PyObject *engine_correct(Engine *e, PyObject *args)
{
    Py_buffer rows, acc, gyro, codes;
    if (!PyArg_ParseTuple(args, "y*w*w*w*:correct", &rows, &acc, &gyro, &codes))
        return NULL;
    Py_ssize_t n = rows.len / 56, unknown = 0;
    const char *why = !e->set                   ? "Engine.correct: no parameters set"
                      : rows.len % 56           ? "Engine.correct: rows must be whole SAMPLE_DTYPE records"
                      : acc.len != 24 * n       ? "Engine.correct: acc must hold 3 float64 per record"
                      : gyro.len != 8 * n       ? "Engine.correct: gyro must hold 1 float64 per record"
                      : codes.len != n          ? "Engine.correct: static must hold 1 int8 per record"
                                                : NULL;
    if (why == NULL) {
        EngineParams p;
        long long generation = -1;
        gravcal_engine_current(e, &p, &generation);
        for (Py_ssize_t i = 0; i < n; i++) {
            signed char *code = (signed char *)codes.buf + i;
            gravcal_engine_sample(&p, (const unsigned char *)rows.buf + 56 * i, (double *)acc.buf + 3 * i,
                                  (double *)gyro.buf + i, code);
            unknown += *code < 0;
        }
    }
    PyBuffer_Release(&rows);
    PyBuffer_Release(&acc);
    PyBuffer_Release(&gyro);
    PyBuffer_Release(&codes);
    if (why != NULL) {
        PyErr_SetString(PyExc_ValueError, why);
        return NULL;
    }
    return PyLong_FromSsize_t(unknown);
}

static PyObject *engine_generation(Engine *e, void *unused)
{
    return PyLong_FromLongLong(__atomic_load_n(&e->generation, __ATOMIC_ACQUIRE));
}

static PyMethodDef engine_methods[] = {
    {"set_params", (PyCFunction)engine_set_params, METH_O,
     "set_params(vector): the engine's parameters, EP_N float64 (daemon/_engine.h), swapped whole"},
    {"correct", (PyCFunction)engine_correct, METH_VARARGS,
     "correct(rows, acc, gyro, static) -> number of unknown static codes: the records corrected as the step does"},
    {NULL},
};

static PyGetSetDef engine_getset[] = {
    {"generation", (getter)engine_generation, NULL, "parameter swaps so far", NULL},
    {NULL},
};

PyTypeObject GravcalEngineType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "gravcal.daemon._fastpath.Engine",
    .tp_basicsize = sizeof(Engine),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Engine(): the per-sample engine's parameters (set_params) and its correction of a block (correct).",
    .tp_new = engine_new,
    .tp_dealloc = (destructor)engine_dealloc,
    .tp_methods = engine_methods,
    .tp_getset = engine_getset,
};
