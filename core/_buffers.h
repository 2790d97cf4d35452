/* Buffer-protocol helpers shared by gravcal's compiled kernels (core/_blockkernels.c,
 * core/_scankernel.c, core/_fitsums.c, core/estimators/_jacobians.c): native float / bool / int64
 * buffers checked for format, dimensions, length and contiguity, with a clear Python exception
 * naming the argument when they are not.
 * Include after Python.h. */
#ifndef GRAVCAL_BUFFERS_H
#define GRAVCAL_BUFFERS_H

#include <string.h>

/* 'f', 'd' or '?' for a native single-item format of the right size, else 0 */
static inline char kind_of(const Py_buffer *v)
{
    const char *f = v->format ? v->format : "B";
    if (*f == '@' || *f == '=')
        f++;
#if PY_LITTLE_ENDIAN
    else if (*f == '<')
        f++;
#else
    else if (*f == '>' || *f == '!')
        f++;
#endif
    if (f[0] == 0 || f[1] != 0)
        return 0;
    if (f[0] == 'f' && v->itemsize == 4)
        return 'f';
    if (f[0] == 'd' && v->itemsize == 8)
        return 'd';
    if (f[0] == '?' && v->itemsize == 1)
        return '?';
    if ((f[0] == 'q' || f[0] == 'l') && v->itemsize == 8)
        return 'q';
    return 0;
}

static inline const char *kind_name(char k)
{
    return k == 'f' ? "float32" : k == 'd' ? "float64" : k == 'q' ? "int64" : "bool";
}

/* a strided read-only view of ndim 1 or 2 (ndim_max 2 also accepts 1-D as (n, 1)) holding
 * items of one of the kinds in `kinds`; sets an exception and returns -1 on failure */
static inline int get_strided(PyObject *obj, Py_buffer *v, const char *name, const char *kinds, int ndim_max)
{
    if (PyObject_GetBuffer(obj, v, PyBUF_RECORDS_RO) < 0) {
        PyErr_Clear();
        PyErr_Format(PyExc_TypeError, "%s must be an array of floats (buffer protocol)", name);
        return -1;
    }
    char k = kind_of(v);
    if (k == 0 || strchr(kinds, k) == NULL) {
        PyErr_Format(PyExc_TypeError, "%s must hold native %s, got format '%s'", name,
                     kinds[1] ? "float32 or float64" : kind_name(kinds[0]), v->format ? v->format : "B");
        PyBuffer_Release(v);
        return -1;
    }
    if (v->ndim < 1 || v->ndim > ndim_max) {
        PyErr_Format(PyExc_ValueError, "%s must be %d-D, got %d-D", name, ndim_max, v->ndim);
        PyBuffer_Release(v);
        return -1;
    }
    return 0;
}

/* a writable (or read-only) C-contiguous buffer of `count` items of kind `kind` */
static inline int get_contiguous(PyObject *obj, Py_buffer *v, const char *name, char kind, Py_ssize_t count,
                          int writable)
{
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, v, flags) < 0) {
        PyErr_Clear();
        PyErr_Format(PyExc_TypeError, "%s must be a C-contiguous%s %s array", name, writable ? " writable" : "",
                     kind_name(kind));
        return -1;
    }
    if (kind_of(v) != kind) {
        PyErr_Format(PyExc_TypeError, "%s must hold %s, got format '%s'", name, kind_name(kind),
                     v->format ? v->format : "B");
        PyBuffer_Release(v);
        return -1;
    }
    if (count >= 0 && v->len != count * v->itemsize) {
        PyErr_Format(PyExc_ValueError, "%s must hold %zd items, got %zd", name, count, v->len / v->itemsize);
        PyBuffer_Release(v);
        return -1;
    }
    return 0;
}

static inline void release_all(Py_buffer *v, int n)
{
    for (int i = 0; i < n; i++)
        if (v[i].obj != NULL)
            PyBuffer_Release(&v[i]);
}

#define AT(view, i) ((const char *)(view).buf + (i) * (view).strides[0])

/* Items of strided views may sit at any address (a record of t float64 and three float32 is 20 bytes: most
 * rows' t is not 8-byte aligned): loaded through memcpy, which compilers turn into one plain load where the
 * CPU allows unaligned ones, and which is defined behaviour where it does not. */
static inline double load_double(const char *p)
{
    double v;
    memcpy(&v, p, sizeof v);
    return v;
}

static inline float load_float(const char *p)
{
    float v;
    memcpy(&v, p, sizeof v);
    return v;
}

#define LOAD(T, p) load_##T((const char *)(p))

/* Get a C-contiguous float64 buffer of exactly n doubles (writable if asked); 0 on success. */
static inline int get_doubles(PyObject *obj, Py_buffer *view, Py_ssize_t n, int writable, const char *name)
{
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) < 0) {
        PyErr_Clear();
        PyErr_Format(PyExc_TypeError, "%s must be a C-contiguous%s float64 array", name, writable ? " writable" : "");
        return -1;
    }
    const char *f = view->format;
    if (f != NULL && (f[0] == '<' || f[0] == '=' || f[0] == '@'))
        f++;
    if (view->itemsize != 8 || f == NULL || strcmp(f, "d") != 0) {
        PyBuffer_Release(view);
        PyErr_Format(PyExc_TypeError, "%s must be float64", name);
        return -1;
    }
    if (view->len != n * 8) {
        PyBuffer_Release(view);
        PyErr_Format(PyExc_ValueError, "%s holds %zd values, expected %zd", name, view->len / 8, n);
        return -1;
    }
    return 0;
}

#endif
