/* What waking N client processes per sample costs the waker on this machine, by the cheapest means the kernel
 * has (not part of gravcal; bench/bench_fanout_floor.py builds and runs it):
 *
 *     wakeup_fanout send|futex NCLIENTS SECONDS [FS] [LINE_BYTES]
 *
 * send:  one line of LINE_BYTES per sample to each client on its own Unix stream socket (as gravcald and
 *        bench/bare_relay.c do), each client blocked in read();
 * futex: the sample number bumped in shared memory and one FUTEX_WAKE for every waiting client, each blocked
 *        in FUTEX_WAIT: no socket buffer, no copy, one system call for all; what remains is the wake-ups.
 * Samples come from clock_nanosleep at FS Hz (default 200). Prints the waker's CPU over the run (its thread's
 * CPU clock) in % of one core and in us per sample, its involuntary context switches per sample, and how often
 * the clients woke per sample (each client counts its wake-ups that brought a sample; 1 when none slept through).
 */
#define _GNU_SOURCE
#include <limits.h>
#include <linux/futex.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

static long futex(uint32_t *word, int op, uint32_t value)
{
    return syscall(SYS_futex, word, op, value, NULL, NULL, 0);
}

static double seconds_of(const struct timespec *a, const struct timespec *b)
{
    return (double)(b->tv_sec - a->tv_sec) + (double)(b->tv_nsec - a->tv_nsec) / 1e9;
}

int main(int argc, char **argv)
{
    if (argc < 4 || (strcmp(argv[1], "send") != 0 && strcmp(argv[1], "futex") != 0)) {
        fprintf(stderr, "usage: wakeup_fanout send|futex NCLIENTS SECONDS [FS] [LINE_BYTES]\n");
        return 2;
    }
    int use_futex = strcmp(argv[1], "futex") == 0, n = atoi(argv[2]);
    double seconds = atof(argv[3]), fs = argc > 4 ? atof(argv[4]) : 200.0;
    int line_bytes = argc > 5 ? atoi(argv[5]) : 271;
    if (n < 1 || n > 1024 || seconds <= 0 || fs <= 0 || line_bytes < 1 || line_bytes > 65536) {
        fprintf(stderr, "wakeup_fanout: bad NCLIENTS, SECONDS, FS or LINE_BYTES\n");
        return 2;
    }
    uint32_t *shared = mmap(NULL, 4096 + 1024 * sizeof(uint64_t), PROT_READ | PROT_WRITE, MAP_SHARED | MAP_ANONYMOUS, -1, 0);
    if (shared == MAP_FAILED) {
        perror("wakeup_fanout: mmap");
        return 1;
    }
    uint32_t *sample = shared, *stop = shared + 16; /* the stop flag on its own cache line */
    uint64_t *woke = (uint64_t *)(shared + 1024);   /* per client: wake-ups that brought a sample */
    int *fds = calloc((size_t)n, sizeof *fds);
    char *line = malloc((size_t)line_bytes);
    memset(line, 'x', (size_t)line_bytes);
    line[line_bytes - 1] = '\n';
    for (int i = 0; i < n; i++) {
        int sv[2] = {-1, -1};
        if (!use_futex && socketpair(AF_UNIX, SOCK_STREAM, 0, sv) < 0) {
            perror("wakeup_fanout: socketpair");
            return 1;
        }
        pid_t pid = fork();
        if (pid < 0) {
            perror("wakeup_fanout: fork");
            return 1;
        }
        if (pid == 0) { /* a client: sleep until woken, take the sample, sleep again */
            if (use_futex) {
                uint32_t seen = 0;
                while (!__atomic_load_n(stop, __ATOMIC_ACQUIRE)) {
                    uint32_t now = __atomic_load_n(sample, __ATOMIC_ACQUIRE);
                    if (now == seen) {
                        futex(sample, FUTEX_WAIT, now);
                        continue;
                    }
                    if (!__atomic_load_n(stop, __ATOMIC_ACQUIRE))
                        woke[i]++;
                    seen = now;
                }
            } else {
                close(sv[0]);
                char buf[65536];
                while (read(sv[1], buf, sizeof buf) > 0)
                    woke[i]++;
            }
            _exit(0);
        }
        if (!use_futex) {
            close(sv[1]);
            fds[i] = sv[0];
        }
    }
    usleep(200000); /* the clients asleep before the first sample */
    long samples = (long)(seconds * fs), step_ns = (long)(1e9 / fs);
    struct timespec next, cpu0, cpu1;
    struct rusage ru0, ru1;
    clock_gettime(CLOCK_MONOTONIC, &next);
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &cpu0);
    getrusage(RUSAGE_SELF, &ru0);
    for (long k = 0; k < samples; k++) {
        next.tv_nsec += step_ns;
        while (next.tv_nsec >= 1000000000L) {
            next.tv_nsec -= 1000000000L;
            next.tv_sec++;
        }
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL);
        if (use_futex) {
            __atomic_add_fetch(sample, 1, __ATOMIC_RELEASE);
            futex(sample, FUTEX_WAKE, INT_MAX);
        } else {
            for (int i = 0; i < n; i++)
                send(fds[i], line, (size_t)line_bytes, MSG_DONTWAIT | MSG_NOSIGNAL);
        }
    }
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &cpu1);
    getrusage(RUSAGE_SELF, &ru1);
    __atomic_store_n(stop, 1, __ATOMIC_RELEASE);
    __atomic_add_fetch(sample, 1, __ATOMIC_RELEASE);
    futex(sample, FUTEX_WAKE, INT_MAX);
    for (int i = 0; i < n; i++)
        if (!use_futex)
            close(fds[i]);
    while (wait(NULL) > 0)
        ;
    uint64_t wakeups = 0;
    for (int i = 0; i < n; i++)
        wakeups += woke[i];
    double cpu = seconds_of(&cpu0, &cpu1);
    printf("cpu_percent %.4f us_per_sample %.3f involuntary_per_sample %.3f client_wakeups_per_sample %.4f\n",
           cpu / seconds * 100.0, cpu / (double)samples * 1e6,
           (double)(ru1.ru_nivcsw - ru0.ru_nivcsw) / (double)samples, (double)wakeups / (double)n / (double)samples);
    return 0;
}
