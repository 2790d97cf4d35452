/* The C step's shared state with Python (daemon/_clienttable.c, linked into gravcal.daemon._fastpath): each
 * client's record and lock, the server's watcher table, the mutex of the arrays ?POLL reads. */
#ifndef GRAVCAL_CLIENTTABLE_H
#define GRAVCAL_CLIENTTABLE_H

#include <Python.h>
#include <pthread.h>

/* a watcher entry of server.fast_watchers (daemon/fanout.py fast_snapshot) */
enum { ENTRY_CLIENT, ENTRY_RECORD, ENTRY_FD, ENTRY_RAW, ENTRY_WATCH, ENTRY_ACQUIRE, ENTRY_RELEASE, ENTRY_N };

/* Locks. The step delivers, corrects and stages without the GIL; four C mutexes guard what it shares:
 *   WatcherBox.mu    the watcher table (server.fast_box), held by the step from its check through the sends;
 *   ClientRecord.mu  one client's socket and gate (ClientState.lock), tried (never waited for) under the box's;
 *   gravcal_latest_mu  the batch arrays ?POLL reads (FastPath.latest), held around writing or copying them only;
 *   Engine.mu        the engine's parameters (_engine.h), held only to copy them in (set_params) or out.
 * Order: box -> record (trylock); box -> latest; box -> engine. Deadlock freedom rests on three rules: a thread
 * holding the GIL never blocks on a box or record mutex (gravcal_lock_with_gil: trylock, else release the GIL and
 * wait), so the step may take the GIL while holding them; no thread waits for the GIL while holding
 * gravcal_latest_mu; and Engine.mu is a leaf: nothing is taken or waited for while holding it, so the setter may
 * take it holding the GIL and the step holding the box's. tests/daemon/test_fastpath_nogil.py churns all four. */
extern pthread_mutex_t gravcal_latest_mu;

/* take ``m`` from a thread holding the GIL: 1, or 0 when not taken (not blocking, or ``timeout`` s passed) */
int gravcal_lock_with_gil(pthread_mutex_t *m, int blocking, double timeout);

/* ClientRecord: what the step reads and writes per client, as C fields (no attribute lookup per sample).
 *   policy: the watch policy the step may send under, None while it must not (the client is closed or has
 *     output pending); set by ClientState.regate (daemon/client_limits.py) each time the client's lock is
 *     released by Python, so it is exact whenever the step holds that lock;
 *   sent_messages, sent_bytes, last_progress: what fanout._sent adds to the ClientState for a block taken
 *     whole, accumulated here and folded into the ClientState by take() (under the client's lock). */
typedef struct {
    PyObject_HEAD
    PyObject *policy;
    long long sent_messages, sent_bytes;
    double last_progress;
    pthread_mutex_t mu; /* the client's lock (ClientState.lock): recursive, taken by Python through lock()/unlock()
                           and by the step without the GIL (see "Locks" above) */
} ClientRecord;

/* WatcherBox: server.fast_box, whose one item box[0] is the watcher snapshot (fanout.fast_snapshot, None while
   some watcher is not plain). Setting it (under the GIL) also writes the C table the step reads without the GIL:
   each entry's record, policy, fd and encoding, borrowed from the item (a tuple: immutable, and kept alive by the
   box until it is replaced under ``mu``). ``ready``: the item is a tuple of well-formed entries; otherwise the step
   takes the GIL and reads the item itself (None: not plain; malformed: its TypeError). */
typedef struct {
    ClientRecord *rec;
    PyObject *watch;
    int fd, raw;
} Watcher;

typedef struct {
    PyObject_HEAD
    pthread_mutex_t mu;
    PyObject *item;
    Watcher *w;
    Py_ssize_t n;
    int ready, need[2];
} WatcherBox;

extern PyTypeObject GravcalClientRecordType, GravcalWatcherBoxType;

#endif
