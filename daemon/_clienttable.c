/* Each client's record and lock (ClientRecord), the server's watcher table (WatcherBox) and the locks the C step
 * shares with Python; see _clienttable.h for the lock order. Part of gravcal.daemon._fastpath. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <pthread.h>
#include <stdint.h>
#include <time.h>

#include "_clienttable.h"

pthread_mutex_t gravcal_latest_mu = PTHREAD_MUTEX_INITIALIZER;

int gravcal_lock_with_gil(pthread_mutex_t *m, int blocking, double timeout)
{
    if (pthread_mutex_trylock(m) == 0)
        return 1;
    if (!blocking)
        return 0;
    int rc;
    Py_BEGIN_ALLOW_THREADS
    if (timeout < 0) {
        rc = pthread_mutex_lock(m);
    } else {
        struct timespec ts;
        clock_gettime(CLOCK_REALTIME, &ts); /* pthread_mutex_timedlock's clock */
        double end = (double)ts.tv_nsec * 1e-9 + timeout;
        ts.tv_sec += (time_t)end;
        ts.tv_nsec = (long)((end - floor(end)) * 1e9);
        rc = pthread_mutex_timedlock(m, &ts);
    }
    Py_END_ALLOW_THREADS
    return rc == 0;
}

static PyObject *record_new(PyTypeObject *type, PyObject *args, PyObject *kwds)
{
    if (PyTuple_GET_SIZE(args) != 0 || (kwds != NULL && PyDict_GET_SIZE(kwds) != 0)) {
        PyErr_SetString(PyExc_TypeError, "ClientRecord() takes no arguments");
        return NULL;
    }
    ClientRecord *r = (ClientRecord *)type->tp_alloc(type, 0);
    if (r == NULL)
        return NULL;
    r->policy = Py_NewRef(Py_None);
    pthread_mutexattr_t a;
    pthread_mutexattr_init(&a);
    pthread_mutexattr_settype(&a, PTHREAD_MUTEX_RECURSIVE); /* threading.RLock's: a holder may take it again */
    int rc = pthread_mutex_init(&r->mu, &a);
    pthread_mutexattr_destroy(&a);
    if (rc != 0) {
        Py_DECREF(r);
        PyErr_SetString(PyExc_RuntimeError, "ClientRecord: cannot create its lock");
        return NULL;
    }
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
    pthread_mutex_destroy(&r->mu);
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

static PyObject *record_lock(ClientRecord *r, PyObject *args, PyObject *kwds)
{
    static char *kw[] = {"blocking", "timeout", NULL};
    int blocking = 1;
    double timeout = -1.0;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "|pd:lock", kw, &blocking, &timeout))
        return NULL;
    return PyBool_FromLong(gravcal_lock_with_gil(&r->mu, blocking, timeout));
}

static PyObject *record_unlock(ClientRecord *r, PyObject *unused)
{
    if (pthread_mutex_unlock(&r->mu) != 0) {
        PyErr_SetString(PyExc_RuntimeError, "ClientRecord.unlock: the lock is not held by this thread");
        return NULL;
    }
    Py_RETURN_NONE;
}

static PyGetSetDef record_getset[] = {
    {"policy", (getter)record_get_policy, (setter)record_set_policy,
     "the watch policy the step may send under; None: it may not (closed, output pending)", NULL},
    {NULL},
};

static PyMethodDef record_methods[] = {
    {"take", (PyCFunction)record_take, METH_NOARGS,
     "take() -> (messages, bytes, last_progress): the counters the step added since the last take, zeroed"},
    {"lock", (PyCFunction)(void (*)(void))record_lock, METH_VARARGS | METH_KEYWORDS,
     "lock(blocking=True, timeout=-1) -> bool: take the client's lock (reentrant; the GIL released while waiting)"},
    {"unlock", (PyCFunction)record_unlock, METH_NOARGS, "unlock(): release the client's lock once"},
    {NULL},
};

PyTypeObject GravcalClientRecordType = {
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


static int box_set(WatcherBox *b, PyObject *item)
{
    Watcher *w = NULL;
    Py_ssize_t n = PyTuple_Check(item) ? PyTuple_GET_SIZE(item) : 0;
    int ready = PyTuple_Check(item), need[2] = {0, 0};
    if (n > 0 && (w = PyMem_Malloc(sizeof(Watcher) * (size_t)n)) == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    for (Py_ssize_t j = 0; ready && j < n; j++) {
        PyObject *e = PyTuple_GET_ITEM(item, j);
        if (!PyTuple_Check(e) || PyTuple_GET_SIZE(e) != ENTRY_N ||
            !PyObject_TypeCheck(PyTuple_GET_ITEM(e, ENTRY_RECORD), &GravcalClientRecordType) ||
            !PyLong_Check(PyTuple_GET_ITEM(e, ENTRY_FD))) {
            ready = 0;
            break;
        }
        long fd = PyLong_AsLong(PyTuple_GET_ITEM(e, ENTRY_FD));
        int raw = PyObject_IsTrue(PyTuple_GET_ITEM(e, ENTRY_RAW));
        if (fd < 0 || fd > INT32_MAX || raw < 0) {
            PyErr_Clear(); /* the step's GIL path reports a malformed entry */
            ready = 0;
            break;
        }
        w[j] = (Watcher){(ClientRecord *)PyTuple_GET_ITEM(e, ENTRY_RECORD), PyTuple_GET_ITEM(e, ENTRY_WATCH), (int)fd,
                         raw};
        need[raw] = 1;
    }
    Py_INCREF(item);
    gravcal_lock_with_gil(&b->mu, 1, -1.0);
    PyObject *old_item = b->item;
    Watcher *old_w = b->w;
    b->item = item;
    b->w = w;
    b->n = n;
    b->ready = ready;
    b->need[0] = need[0];
    b->need[1] = need[1];
    pthread_mutex_unlock(&b->mu);
    Py_XDECREF(old_item); /* after the unlock: the step no longer reads the old table */
    PyMem_Free(old_w);
    return 0;
}

static PyObject *box_new(PyTypeObject *type, PyObject *args, PyObject *kwds)
{
    PyObject *item = NULL;
    if ((kwds != NULL && PyDict_GET_SIZE(kwds) != 0) || !PyArg_ParseTuple(args, "O:WatcherBox", &item))
        return NULL;
    WatcherBox *b = (WatcherBox *)type->tp_alloc(type, 0);
    if (b == NULL)
        return NULL;
    if (pthread_mutex_init(&b->mu, NULL) != 0) {
        Py_DECREF(b);
        PyErr_SetString(PyExc_RuntimeError, "WatcherBox: cannot create its lock");
        return NULL;
    }
    b->w = NULL;
    if (box_set(b, item) < 0) {
        Py_DECREF(b);
        return NULL;
    }
    return (PyObject *)b;
}

static int box_traverse(WatcherBox *b, visitproc visit, void *arg)
{
    Py_VISIT(b->item);
    return 0;
}

static int box_clear(WatcherBox *b)
{
    Py_CLEAR(b->item); /* only from the collector or dealloc: no step holds the box then (it holds a reference) */
    PyMem_Free(b->w);
    b->w = NULL;
    b->n = 0;
    b->ready = 0;
    return 0;
}

static void box_dealloc(WatcherBox *b)
{
    PyObject_GC_UnTrack(b);
    box_clear(b);
    pthread_mutex_destroy(&b->mu);
    Py_TYPE(b)->tp_free((PyObject *)b);
}

static Py_ssize_t box_len(WatcherBox *b) { return 1; }

static PyObject *box_item(WatcherBox *b, Py_ssize_t i)
{
    if (i != 0) {
        PyErr_SetString(PyExc_IndexError, "WatcherBox holds one item: box[0]");
        return NULL;
    }
    return Py_NewRef(b->item != NULL ? b->item : Py_None);
}

static int box_ass_item(WatcherBox *b, Py_ssize_t i, PyObject *value)
{
    if (i != 0 || value == NULL) {
        PyErr_SetString(PyExc_IndexError, "WatcherBox holds one item: only box[0] = snapshot");
        return -1;
    }
    return box_set(b, value);
}

/* table() -> ((record, fd, raw, watch), ...) as the step reads it, or None while it reads box[0] with the GIL */
static PyObject *box_table(WatcherBox *b, PyObject *unused)
{
    gravcal_lock_with_gil(&b->mu, 1, -1.0);
    PyObject *out = b->ready ? PyTuple_New(b->n) : Py_NewRef(Py_None);
    for (Py_ssize_t j = 0; b->ready && out != NULL && j < b->n; j++) {
        PyObject *e = Py_BuildValue("(OiOO)", b->w[j].rec, b->w[j].fd, b->w[j].raw ? Py_True : Py_False,
                                    b->w[j].watch);
        if (e == NULL)
            Py_CLEAR(out);
        else
            PyTuple_SET_ITEM(out, j, e);
    }
    pthread_mutex_unlock(&b->mu);
    return out;
}

static PyMethodDef box_methods[] = {
    {"table", (PyCFunction)box_table, METH_NOARGS,
     "table() -> ((record, fd, raw, watch), ...): the C table the step reads without the GIL; None: it reads box[0] "
     "with the GIL (None there, or a malformed snapshot)"},
    {NULL},
};

static PySequenceMethods box_as_sequence = {.sq_length = (lenfunc)box_len, .sq_item = (ssizeargfunc)box_item,
                                            .sq_ass_item = (ssizeobjargproc)box_ass_item};

PyTypeObject GravcalWatcherBoxType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "gravcal.daemon._fastpath.WatcherBox",
    .tp_basicsize = sizeof(WatcherBox),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
    .tp_doc = "WatcherBox(snapshot): the server's watcher snapshot as box[0], and the C table the step reads from it.",
    .tp_new = box_new,
    .tp_traverse = (traverseproc)box_traverse,
    .tp_clear = (inquiry)box_clear,
    .tp_dealloc = (destructor)box_dealloc,
    .tp_as_sequence = &box_as_sequence,
    .tp_methods = box_methods,
};
