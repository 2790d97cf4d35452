/* The floor under gravcald's CPU for the same traffic (bench/bench_latency.py builds and runs it; not part of
 * gravcal): a process that only waits on the device's tty, reads what arrived and sends one fixed line per frame
 * to each of N clients on a Unix socket. No decoding, correction, formatting or bookkeeping: what remains is the
 * wake-up, the read and the send() calls (each waking a client process), which no daemon design avoids.
 *
 *     bare_relay [--uring] TTY SOCKET NCLIENTS LINE_BYTES FRAME_BYTES [OPEN_COMMAND]
 *     bare_relay [--uring] i2c:DEVICE:POLL_US[:FIRST] SOCKET NCLIENTS LINE_BYTES 29
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
 * i2c:DEVICE:POLL_US: the logger's FIFO on an I2C bus (drivers/i2c.py's register map) read as gravcald's I2C driver
 * reads it without a DRDY line: one I2C_RDWR of STATUS, FIFO_COUNT and the FIFO's first FIRST frames (default 1,
 * the driver's combined poll), then the rest in I2C_RDWR bursts of up to 16, and a sleep of POLL_US when the FIFO
 * was empty and after each drain; FIRST 0: the driver before its combined poll (STATUS and FIFO_COUNT alone, then
 * the bursts; asks again right after a drain). bench_latency.py runs it under umockdev's preload library against
 * the emulated device, as gravcald.
 * It prints "listening" once the socket is bound, "ready" once NCLIENTS are connected, and on SIGTERM the
 * wake-ups, lines and bytes sent.
 */
#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <linux/i2c-dev.h>
#include <linux/i2c.h>
#include <linux/io_uring.h>
#include <sys/epoll.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <sys/socket.h>
#include <sys/syscall.h>
#include <sys/un.h>
#include <termios.h>
#include <time.h>
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

#define I2C_ADDRESS 0x42
#define REG_STATUS 0x02
#define REG_CTRL 0x06
#define REG_FIFO_DATA 0x10
#define CTRL_FIFO_RESET_ENABLE 0x03
#define I2C_BURST_FRAMES 16

static long long i2c_polls, i2c_bursts; /* STATUS reads, FIFO_DATA reads (a combined poll counts in both) */

/* One I2C_RDWR: a write of the register number, then a read of len bytes from it (repeated start). */
static int i2c_read_register(int fd, unsigned char reg, unsigned char *out, unsigned short len)
{
    struct i2c_msg msgs[2] = {{.addr = I2C_ADDRESS, .flags = 0, .len = 1, .buf = &reg},
                              {.addr = I2C_ADDRESS, .flags = I2C_M_RD, .len = len, .buf = out}};
    struct i2c_rdwr_ioctl_data data = {.msgs = msgs, .nmsgs = 2};
    i2c_polls += reg == REG_STATUS;
    i2c_bursts += reg == REG_FIFO_DATA;
    return ioctl(fd, I2C_RDWR, &data) < 0 ? -1 : 0;
}

/* The logger started as the I2C driver starts it: its FIFO emptied, sampling enabled. */
static int i2c_enable(int fd)
{
    unsigned char cmd[2] = {REG_CTRL, CTRL_FIFO_RESET_ENABLE};
    struct i2c_msg msg = {.addr = I2C_ADDRESS, .flags = 0, .len = 2, .buf = cmd};
    struct i2c_rdwr_ioctl_data data = {.msgs = &msg, .nmsgs = 1};
    return ioctl(fd, I2C_RDWR, &data) < 0 ? -1 : 0;
}

/* STATUS, FIFO_COUNT and the FIFO's first `first` frames into out in one I2C_RDWR (repeated starts). Returns the
   frames of out that are the FIFO's: `first` if the count had them, else the count's and any that came in before
   the data phase (the device reads 0x00 past its content; a frame starts with its sync bytes). */
static size_t i2c_status_and_first(int fd, unsigned char st[2], unsigned char *out, size_t first, int frame_bytes)
{
    unsigned char rs = REG_STATUS, rd = REG_FIFO_DATA;
    struct i2c_msg msgs[4] = {{.addr = I2C_ADDRESS, .flags = 0, .len = 1, .buf = &rs},
                              {.addr = I2C_ADDRESS, .flags = I2C_M_RD, .len = 2, .buf = st},
                              {.addr = I2C_ADDRESS, .flags = 0, .len = 1, .buf = &rd},
                              {.addr = I2C_ADDRESS, .flags = I2C_M_RD, .len = (unsigned short)(first * frame_bytes),
                               .buf = out}};
    struct i2c_rdwr_ioctl_data data = {.msgs = msgs, .nmsgs = 4};
    i2c_polls++;
    i2c_bursts++;
    if (ioctl(fd, I2C_RDWR, &data) < 0)
        return (size_t)-1;
    size_t taken = st[1] < first ? st[1] : first;
    while (taken < first && out[taken * (size_t)frame_bytes] != 0)
        taken++;
    return taken;
}

/* The frames the FIFO holds, read as the I2C driver reads them; waits POLL_US while it is empty. Returns the bytes
   read into buf (whole frames), 0 when none came, -1 on a bus error. */
static ssize_t i2c_read_fifo(int fd, long poll_us, size_t first, unsigned char *buf, size_t cap, int frame_bytes)
{
    static int drained; /* FIRST > 0, as the driver: after a drain (its lines sent since), POLL_US before asking again */
    struct timespec ts = {.tv_sec = poll_us / 1000000, .tv_nsec = (poll_us % 1000000) * 1000};
    if (drained) {
        drained = 0;
        nanosleep(&ts, NULL);
    }
    unsigned char st[2];
    size_t count, n = 0;
    if (first > 0) {
        size_t taken = i2c_status_and_first(fd, st, buf, first, frame_bytes);
        if (taken == (size_t)-1)
            return -1;
        n = taken * (size_t)frame_bytes;
        count = st[1] > taken ? st[1] - taken : 0;
    } else {
        if (i2c_read_register(fd, REG_STATUS, st, 2) < 0)
            return -1;
        count = st[1];
    }
    if (count == 0 && n == 0) {
        nanosleep(&ts, NULL);
        return 0;
    }
    drained = first > 0;
    while (count > 0 && n + (size_t)frame_bytes <= cap) {
        size_t k = count < I2C_BURST_FRAMES ? count : I2C_BURST_FRAMES;
        if (n + k * (size_t)frame_bytes > cap)
            k = (cap - n) / (size_t)frame_bytes;
        if (i2c_read_register(fd, REG_FIFO_DATA, buf + n, (unsigned short)(k * (size_t)frame_bytes)) < 0)
            return -1;
        n += k * (size_t)frame_bytes;
        count -= k;
    }
    return (ssize_t)n;
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
    long poll_us = -1; /* >= 0: an I2C bus, polled */
    long i2c_first = 1;
    char *i2c_dev = NULL;
    if (strncmp(argv[1], "i2c:", 4) == 0) {
        i2c_dev = strdup(argv[1] + 4); /* DEVICE:POLL_US[:FIRST] (DEVICE is a /dev path: no colon) */
        char *colon = strchr(i2c_dev, ':');
        char *second = colon ? strchr(colon + 1, ':') : NULL;
        if (second) {
            *second = '\0';
            i2c_first = atol(second + 1);
        }
        if (colon == NULL || frame_bytes != 29 || i2c_first < 0 || i2c_first > I2C_BURST_FRAMES) {
            fprintf(stderr, "bare_relay: i2c:DEVICE:POLL_US[:FIRST] with FRAME_BYTES 29, FIRST 0..16\n");
            return 2;
        }
        *colon = '\0';
        poll_us = atol(colon + 1);
    }
    int tty = open(i2c_dev ? i2c_dev : argv[1], i2c_dev ? O_RDWR : O_RDWR | O_NOCTTY | O_NONBLOCK);
    struct termios tio;
    if (i2c_dev) {
        if (tty < 0) {
            perror("bare_relay: i2c");
            return 1;
        }
    } else {
        /* as gravcald's drivers: a read never waits */
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
    if (!i2c_dev)
        tcflush(tty, TCIFLUSH);
    else if (i2c_enable(tty) < 0) {
        perror("bare_relay: I2C enable");
        return 1;
    }
    printf("ready\n");
    fflush(stdout);
    static char buf[READ_BYTES];
    char *lines = NULL;
    size_t lines_cap = 0;
    long long wakeups = 0, sent_lines = 0, sent_bytes = 0;
    int carry = 0; /* bytes of a frame not yet complete */
    /* the same wait as gravcald's C step (daemon/_fastpath.c): edge-triggered epoll, so the tty is asked only
       when a frame came in (poll() asks it on every entry and may wait there for the tty's flush work) */
    int ep = i2c_dev ? -1 : epoll_create1(0);
    struct epoll_event ev = {.events = EPOLLIN | EPOLLET, .data.fd = tty};
    if (!i2c_dev && (ep < 0 || epoll_ctl(ep, EPOLL_CTL_ADD, tty, &ev) < 0)) {
        perror("bare_relay: epoll");
        return 1;
    }
    while (!stop) {
        ssize_t n;
        if (i2c_dev) {
            n = i2c_read_fifo(tty, poll_us, (size_t)i2c_first, (unsigned char *)buf, READ_BYTES, frame_bytes);
            if (n < 0) {
                perror("bare_relay: I2C_RDWR");
                return 1;
            }
            if (n == 0)
                continue;
        } else {
            int r = epoll_wait(ep, &ev, 1, 250);
            if (r <= 0)
                continue;
            size_t ask = TTY_CHUNK; /* the same reads as gravcald's C step: never more than the tty holds */
            ssize_t last;
            n = last = read(tty, buf, ask);
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
    printf("wakeups %lld lines %lld bytes %lld polls %lld bursts %lld\n", wakeups, sent_lines, sent_bytes, i2c_polls,
           i2c_bursts);
    return 0;
}
