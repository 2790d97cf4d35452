/* Fault in fresh anonymous memory ahead of its first write, without the GIL.
 *
 * io/prestart.py maps the block statistics' memory of `gravcal calibrate FILE.npy` while the
 * interpreter still imports numpy and gravcal (one core idle) and has a background thread fault it in
 * with populate(): the kernel's zeroing of ~290 MB for a week at 100 Hz then no longer happens inside
 * the reading pass's two threads. madvise(MADV_POPULATE_WRITE) (Linux >= 5.14) faults pages in as a
 * write would, without changing their contents, so it is safe while other threads write the same
 * pages. No fallback that writes: a missing MADV_POPULATE_WRITE returns False and the pages are
 * faulted in by their first write, as without this helper.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <errno.h>
#include <stdint.h>
#include <sys/mman.h>
#include <unistd.h>

#ifndef MADV_POPULATE_WRITE
#define MADV_POPULATE_WRITE 23
#endif

static PyObject *populate(PyObject *self, PyObject *args) {
    Py_buffer buf;
    Py_ssize_t offset, length;
    if (!PyArg_ParseTuple(args, "w*nn", &buf, &offset, &length))
        return NULL;
    if (!PyBuffer_IsContiguous(&buf, 'C')) {
        PyBuffer_Release(&buf);
        PyErr_SetString(PyExc_ValueError, "populate: the buffer must be contiguous");
        return NULL;
    }
    if (offset < 0 || length < 0 || offset > buf.len || length > buf.len - offset) {
        PyErr_Format(PyExc_ValueError, "populate: bytes [%zd, %zd + %zd) lie outside the buffer of %zd bytes",
                     offset, offset, length, buf.len);
        PyBuffer_Release(&buf);
        return NULL;
    }
    /* only whole pages inside [offset, offset + length): a page partly outside may be another object's */
    uintptr_t page = (uintptr_t)sysconf(_SC_PAGESIZE);
    uintptr_t lo = (uintptr_t)buf.buf + (uintptr_t)offset;
    uintptr_t hi = lo + (uintptr_t)length;
    lo = (lo + page - 1) / page * page;
    hi = hi / page * page;
    int rc = 0, err = 0;
    if (hi > lo) {
        Py_BEGIN_ALLOW_THREADS
        rc = madvise((void *)lo, (size_t)(hi - lo), MADV_POPULATE_WRITE);
        err = errno;
        Py_END_ALLOW_THREADS
    }
    PyBuffer_Release(&buf);
    if (rc != 0) {
        if (err == EINVAL || err == ENOSYS)  /* a kernel before 5.14: the first writes fault the pages in */
            Py_RETURN_FALSE;
        errno = err;
        return PyErr_SetFromErrno(PyExc_OSError);
    }
    Py_RETURN_TRUE;
}

static PyMethodDef methods[] = {
    {"populate", populate, METH_VARARGS,
     "populate(buffer, offset, length) -> bool: fault in the whole pages of bytes [offset, offset + length) of a "
     "writable buffer as a write would (contents unchanged; MADV_POPULATE_WRITE, GIL released). False when the "
     "kernel lacks it."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_pages", "Fault in fresh memory ahead of its use.", -1,
                                    methods};

PyMODINIT_FUNC PyInit__pages(void) { return PyModule_Create(&module); }
