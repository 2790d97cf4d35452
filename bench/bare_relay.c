/* The floor under gravcald's CPU for the same traffic (bench/bench_latency.py builds and runs it; not part of
 * gravcal): a process that only waits on the device's tty, reads what arrived and sends one fixed line per frame
 * to each of N clients on a Unix socket. No decoding, correction, formatting or bookkeeping: what remains is the
 * wake-up, the read and the send() calls (each waking a client process), which no daemon design avoids.
 *
 *     bare_relay TTY SOCKET NCLIENTS LINE_BYTES FRAME_BYTES [OPEN_COMMAND]
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
#include <sys/epoll.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
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

static void on_term(int sig)
{
    (void)sig;
    stop = 1;
}

int main(int argc, char **argv)
{
    if (argc < 6) {
        fprintf(stderr, "usage: bare_relay TTY SOCKET NCLIENTS LINE_BYTES FRAME_BYTES [OPEN_COMMAND]\n");
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
