/* The floor under gravcald's CPU for the same traffic (bench/bench_latency.py builds and runs it; not part of
 * gravcal): a process that only waits on the device's tty, reads what arrived and sends one fixed line per frame
 * to each of N clients on a Unix socket. No decoding, correction, formatting or bookkeeping: what remains is the
 * wake-up, the read and the send() calls (each waking a client process), which no daemon design avoids.
 *
 *     bare_relay [--uring] TTY SOCKET NCLIENTS LINE_BYTES FRAME_BYTES [OPEN_COMMAND]
 *
 * --uring: the clients' sends go as one batch through io_uring (one io_uring_enter per wake-up instead of one
 * send() per client), to tell the system calls' own cost from the kernel's work per send (the socket buffer and
 * the client's wake-up), which batching does not remove.
 *
 * TTY is put in raw mode with VMIN = FRAME_BYTES, as gravcald's drivers do, so epoll wakes once a whole frame
 * (serial) or CAN sample (slcan) is there; OPEN_COMMAND (e.g. "O" for slcan) is written first, followed by CR.
 * Each line is JSON, {"class":"IMU","seq":N,"pad":"xx..."} of LINE_BYTES (at least 64): N is the frame's 16-bit
 * sequence number for serial frames (FRAME_BYTES 29; the wire format's bytes 3-4, little-endian), so a client can
 * time it as it times gravcald's lines; -1 for slcan, whose number is not parsed here.
 * It prints "listening" once the socket is bound, "ready" once NCLIENTS are connected, and on SIGTERM the
 * wake-ups, lines and bytes sent.
 */
#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <linux/io_uring.h>
#include <sys/epoll.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <sys/socket.h>
#include <sys/syscall.h>
#include <sys/un.h>
#include <termios.h>
#include <unistd.h>

#define READ_BYTES 65536
#define TTY_CHUNK 64

#define SEQ_HEAD "{\"class\":\"IMU\",\"seq\":"
#define SEQ_DIGITS 5
#define PAD_HEAD ",\"pad\":\""

static volatile sig_atomic_t stop;

static void put_seq(char *out, int seq)
{
    memset(out, ' ', SEQ_DIGITS);
    int v = seq < 0 ? 1 : seq, i = SEQ_DIGITS;
    do
        out[--i] = (char)('0' + v % 10);
    while ((v /= 10) > 0 && i > 0);
    if (seq < 0 && i > 0)
        out[--i] = '-';
}

/* A submission ring of io_uring, set up with the raw system calls (no liburing): the sends of one wake-up are
   queued as one batch with IOSQE_CQE_SKIP_SUCCESS, so only a failed send posts a completion. */
struct send_ring {
    int fd;
    unsigned *sq_tail, *sq_mask, *sq_array, *cq_head, *cq_tail, *cq_mask;
    struct io_uring_sqe *sqes;
    struct io_uring_cqe *cqes;
};

static int send_ring_open(struct send_ring *ring, unsigned entries)
{
    struct io_uring_params p;
    memset(&p, 0, sizeof p);
    ring->fd = (int)syscall(__NR_io_uring_setup, entries, &p);
    if (ring->fd < 0)
        return -1;
    char *sq = mmap(NULL, p.sq_off.array + p.sq_entries * sizeof(unsigned), PROT_READ | PROT_WRITE,
                    MAP_SHARED | MAP_POPULATE, ring->fd, IORING_OFF_SQ_RING);
    char *cq = mmap(NULL, p.cq_off.cqes + p.cq_entries * sizeof(struct io_uring_cqe), PROT_READ | PROT_WRITE,
                    MAP_SHARED | MAP_POPULATE, ring->fd, IORING_OFF_CQ_RING);
    ring->sqes = mmap(NULL, p.sq_entries * sizeof(struct io_uring_sqe), PROT_READ | PROT_WRITE,
                      MAP_SHARED | MAP_POPULATE, ring->fd, IORING_OFF_SQES);
    if (sq == MAP_FAILED || cq == MAP_FAILED || ring->sqes == MAP_FAILED)
        return -1;
    ring->sq_tail = (unsigned *)(sq + p.sq_off.tail);
    ring->sq_mask = (unsigned *)(sq + p.sq_off.ring_mask);
    ring->sq_array = (unsigned *)(sq + p.sq_off.array);
    ring->cq_head = (unsigned *)(cq + p.cq_off.head);
    ring->cq_tail = (unsigned *)(cq + p.cq_off.tail);
    ring->cq_mask = (unsigned *)(cq + p.cq_off.ring_mask);
    ring->cqes = (struct io_uring_cqe *)(cq + p.cq_off.cqes);
    return 0;
}

/* the same sends as the send() loop below, in the same order, as one io_uring_enter; returns the bytes sent */
static long long send_ring_batch(struct send_ring *ring, const int *fds, int nclients, const char *data, size_t len)
{
    unsigned tail = *ring->sq_tail;
    for (int i = nclients - 1; i >= 0; i--) {
        unsigned idx = tail++ & *ring->sq_mask;
        struct io_uring_sqe *sqe = &ring->sqes[idx];
        memset(sqe, 0, sizeof *sqe);
        sqe->opcode = IORING_OP_SEND;
        sqe->fd = fds[i];
        sqe->addr = (unsigned long)data;
        sqe->len = (unsigned)len;
        sqe->msg_flags = MSG_DONTWAIT | MSG_NOSIGNAL;
        sqe->flags = IOSQE_CQE_SKIP_SUCCESS;
        ring->sq_array[idx] = idx;
    }
    __atomic_store_n(ring->sq_tail, tail, __ATOMIC_RELEASE);
    if (syscall(__NR_io_uring_enter, ring->fd, (unsigned)nclients, 0, 0, NULL, 0) < 0)
        return 0;
    long long failed = 0;
    unsigned head = *ring->cq_head, end = __atomic_load_n(ring->cq_tail, __ATOMIC_ACQUIRE);
    for (; head != end; head++) { /* only the failed or short sends post a completion */
        int res = ring->cqes[head & *ring->cq_mask].res;
        failed += (long long)len - (res > 0 ? res : 0);
    }
    __atomic_store_n(ring->cq_head, head, __ATOMIC_RELEASE);
    return (long long)nclients * (long long)len - failed;
}

static void on_term(int sig)
{
    (void)sig;
    stop = 1;
}

int main(int argc, char **argv)
{
    int uring = argc > 1 && strcmp(argv[1], "--uring") == 0;
    argc -= uring;
    argv += uring;
    if (argc < 6) {
        fprintf(stderr, "usage: bare_relay [--uring] TTY SOCKET NCLIENTS LINE_BYTES FRAME_BYTES [OPEN_COMMAND]\n");
        return 2;
    }
    int nclients = atoi(argv[3]), line_bytes = atoi(argv[4]), frame_bytes = atoi(argv[5]);
    if (nclients < 1 || nclients > 1024 || line_bytes < 64 || frame_bytes < 1 || frame_bytes > 255) {
        fprintf(stderr, "bare_relay: bad NCLIENTS, LINE_BYTES or FRAME_BYTES\n");
        return 2;
    }
    int tty = open(argv[1], O_RDWR | O_NOCTTY | O_NONBLOCK); /* as gravcald's drivers: a read never waits */
    struct termios tio;
    if (tty < 0 || tcgetattr(tty, &tio) < 0) {
        perror("bare_relay: tty");
        return 1;
    }
    cfmakeraw(&tio);
    tio.c_cc[VMIN] = (cc_t)frame_bytes;
    tio.c_cc[VTIME] = 0;
    if (tcsetattr(tty, TCSANOW, &tio) < 0) {
        perror("bare_relay: tcsetattr");
        return 1;
    }
    int lst = socket(AF_UNIX, SOCK_STREAM, 0);
    struct sockaddr_un addr = {.sun_family = AF_UNIX};
    if (strlen(argv[2]) >= sizeof addr.sun_path) {
        fprintf(stderr, "bare_relay: socket path too long\n");
        return 2;
    }
    strcpy(addr.sun_path, argv[2]);
    if (lst < 0 || bind(lst, (struct sockaddr *)&addr, sizeof addr) < 0 || listen(lst, nclients) < 0) {
        perror("bare_relay: socket");
        return 1;
    }
    printf("listening\n");
    fflush(stdout);
    int *fds = calloc((size_t)nclients, sizeof *fds);
    for (int i = 0; i < nclients; i++)
        if ((fds[i] = accept(lst, NULL, NULL)) < 0) {
            perror("bare_relay: accept");
            return 1;
        }
    struct send_ring ring = {.fd = -1};
    if (uring && send_ring_open(&ring, (unsigned)nclients) < 0) {
        perror("bare_relay: io_uring");
        return 1;
    }
    signal(SIGTERM, on_term);
    if (argc > 6) { /* e.g. slcan's "O": open the channel, or the adapter sends nothing */
        char cmd[64];
        int k = snprintf(cmd, sizeof cmd, "%s\r", argv[6]);
        if (k <= 0 || write(tty, cmd, (size_t)k) != k) {
            perror("bare_relay: open command");
            return 1;
        }
    }
    tcflush(tty, TCIFLUSH);
    printf("ready\n");
    fflush(stdout);
    static char buf[READ_BYTES];
    char *lines = NULL;
    size_t lines_cap = 0;
    long long wakeups = 0, sent_lines = 0, sent_bytes = 0;
    int carry = 0; /* bytes of a frame not yet complete */
    /* the same wait as gravcald's C step (daemon/_fastpath.c): edge-triggered epoll, so the tty is asked only
       when a frame came in (poll() asks it on every entry and may wait there for the tty's flush work) */
    int ep = epoll_create1(0);
    struct epoll_event ev = {.events = EPOLLIN | EPOLLET, .data.fd = tty};
    if (ep < 0 || epoll_ctl(ep, EPOLL_CTL_ADD, tty, &ev) < 0) {
        perror("bare_relay: epoll");
        return 1;
    }
    while (!stop) {
        int r = epoll_wait(ep, &ev, 1, 250);
        if (r <= 0)
            continue;
        size_t ask = TTY_CHUNK; /* the same reads as gravcald's C step: never more than the tty holds */
        ssize_t n = read(tty, buf, ask), last = n;
        if (n <= 0)
            continue;
        int avail;
        while ((size_t)last == ask && n < READ_BYTES && ioctl(tty, FIONREAD, &avail) == 0 && avail > 0) {
            ask = (size_t)avail < (size_t)(READ_BYTES - n) ? (size_t)avail : (size_t)(READ_BYTES - n);
            last = read(tty, buf + n, ask);
            if (last <= 0)
                break;
            n += last;
        }
        wakeups++;
        int carry_before = carry;
        int k = (int)((carry + n) / frame_bytes);
        carry = (int)((carry + n) % frame_bytes);
        if (k == 0)
            continue;
        size_t need = (size_t)k * (size_t)line_bytes;
        if (need > lines_cap) {
            lines = realloc(lines, need);
            for (size_t i = 0; i < (size_t)k; i++) { /* k lines of line_bytes, padded with x */
                char *l = lines + i * (size_t)line_bytes;
                memset(l, 'x', (size_t)line_bytes);
                memcpy(l, SEQ_HEAD, sizeof SEQ_HEAD - 1);
                memcpy(l + sizeof SEQ_HEAD - 1 + SEQ_DIGITS, PAD_HEAD, sizeof PAD_HEAD - 1);
                memcpy(l + line_bytes - 3, "\"}\n", 3);
            }
            lines_cap = need;
        }
        for (int i = 0; i < k; i++) /* each line's seq, right-aligned in its 5 characters (JSON allows the spaces) */
            put_seq(lines + (size_t)i * (size_t)line_bytes + sizeof SEQ_HEAD - 1,
                    frame_bytes == 29 && carry_before == 0 ? (int)((unsigned char)buf[i * 29 + 3] |
                                                                   (unsigned char)buf[i * 29 + 4] << 8)
                                                           : -1);
        if (uring)
            sent_bytes += send_ring_batch(&ring, fds, nclients, lines, need);
        else
            for (int i = nclients - 1; i >= 0; i--) { /* the first client (bench_latency's timed one) last: the worst */
                ssize_t s = send(fds[i], lines, need, MSG_DONTWAIT | MSG_NOSIGNAL);
                if (s > 0)
                    sent_bytes += s;
            }
        sent_lines += (long long)k * nclients;
    }
    printf("wakeups %lld lines %lld bytes %lld\n", wakeups, sent_lines, sent_bytes);
    return 0;
}
