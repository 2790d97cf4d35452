/* A call's windows shared with one helper thread kept for the process's life (share_windows). Part of the
 * _jacobians extension (core/estimators/_jacobians.c). */
#include "_jacobians.h"
#include <pthread.h>
#include <unistd.h>

#define SPLIT_MIN 4096 /* windows from which a call shares them with a helper thread (a week: ~12 000) */

/* The windows are independent (no sum runs across them), so any split of them between threads writes the
 * bits one loop writes. A call shares its windows with one helper thread, kept for the process's life:
 * both take chunks of SHARE_CHUNKS-th of the windows from a counter until none is left; the caller then
 * waits only for a chunk the helper has taken and not finished. A helper that does not get a core (a busy
 * machine) takes nothing, and the caller does every chunk itself, as one loop would, instead of waiting for
 * it. threads: 1, 2, or -1 (2 from SPLIT_MIN windows on when the machine has a second CPU; 1 in the AVX2
 * lanes). Called without the GIL; a call made while another call's windows are being shared runs alone. */
#define SHARE_CHUNKS 32

static pthread_mutex_t share_mu = PTHREAD_MUTEX_INITIALIZER, share_job = PTHREAD_MUTEX_INITIALIZER;
static pthread_cond_t share_wake = PTHREAD_COND_INITIALIZER, share_idle = PTHREAD_COND_INITIALIZER;
static struct {
    LoopFn run;
    void *ctx;
    Py_ssize_t next, m, chunk;
    int open, busy, helper;
} share; /* all fields under share_mu */

static void *helper_main(void *arg)
{
    (void)arg;
    pthread_mutex_lock(&share_mu);
    for (;;) {
        while (!(share.open && share.next < share.m))
            pthread_cond_wait(&share_wake, &share_mu);
        const Py_ssize_t w0 = share.next, w1 = share.m - w0 < share.chunk ? share.m : w0 + share.chunk;
        LoopFn run = share.run;
        void *ctx = share.ctx;
        share.next = w1, share.busy = 1;
        pthread_mutex_unlock(&share_mu);
        run(ctx, w0, w1, 1);
        pthread_mutex_lock(&share_mu);
        share.busy = 0;
        pthread_cond_signal(&share_idle);
    }
    return NULL;
}

static void share_after_fork(void)
{ /* the child has no helper thread (fork copies only the caller): fresh locks, a helper started on demand */
    pthread_mutex_init(&share_mu, NULL), pthread_mutex_init(&share_job, NULL);
    pthread_cond_init(&share_wake, NULL), pthread_cond_init(&share_idle, NULL);
    share.open = share.busy = share.helper = 0;
}

JACOBIANS_INTERNAL void share_windows(LoopFn run, void *ctx, Py_ssize_t m, int threads)
{
    if (threads < 0)
        threads = m >= SPLIT_MIN && sysconf(_SC_NPROCESSORS_ONLN) > 1 ? 2 : 1;
    if (threads == 1 || m < 2 || pthread_mutex_trylock(&share_job) != 0) {
        run(ctx, 0, m, 0);
        return;
    }
    pthread_mutex_lock(&share_mu);
    if (!share.helper) {
        pthread_t t;
        if (pthread_create(&t, NULL, helper_main, NULL) == 0 && pthread_detach(t) == 0)
            share.helper = 1;
    }
    if (!share.helper) { /* no thread could be started: one loop */
        pthread_mutex_unlock(&share_mu);
        pthread_mutex_unlock(&share_job);
        run(ctx, 0, m, 0);
        return;
    }
    share.run = run, share.ctx = ctx, share.next = 0, share.m = m, share.open = 1;
    share.chunk = m / SHARE_CHUNKS > 1 ? m / SHARE_CHUNKS : 1;
    pthread_cond_signal(&share_wake);
    while (share.next < m) {
        const Py_ssize_t w0 = share.next, w1 = m - w0 < share.chunk ? m : w0 + share.chunk;
        share.next = w1;
        pthread_mutex_unlock(&share_mu);
        run(ctx, w0, w1, 0);
        pthread_mutex_lock(&share_mu);
    }
    share.open = 0;
    while (share.busy)
        pthread_cond_wait(&share_idle, &share_mu);
    pthread_mutex_unlock(&share_mu);
    pthread_mutex_unlock(&share_job);
}

JACOBIANS_INTERNAL int threads_arg(int threads)
{
    if (threads != -1 && threads != 1 && threads != 2) {
        PyErr_Format(PyExc_ValueError, "threads must be 1, 2 or -1 (automatic), got %d", threads);
        return -1;
    }
    return 0;
}

JACOBIANS_INTERNAL void share_init(void)
{
    pthread_atfork(NULL, NULL, share_after_fork);
}
