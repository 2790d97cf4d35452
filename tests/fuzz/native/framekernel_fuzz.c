/* libFuzzer harness of drivers/_framekernel.c's C functions, built with AddressSanitizer and UBSan (build.sh).
 *
 * It calls the kernel's static functions directly (the file is included), on buffers allocated to their exact
 * size so that any read or write past them is an ASan report, and checks what C alone can check: the per-frame
 * writer and the whole-read kernels agree, a read is taken whole or not at all, stamps never go backwards.
 * Whether the values equal the Python reference is checked by replaying the corpus it grows through the Python
 * targets of the same name (fuzz_targets.py), which read every input with the same layout:
 *
 *   frame_decoder: byte 0 cut, byte 1 mode (bit 0 seal: every whole 29-byte chunk of the stream gets the sync,
 *                  the length and a valid CRC; bit 1 with it: consecutive raw seq from the first chunk's), then
 *                  the stream.
 *   slcan_lines:   bytes 0-1 the raw seq expected (little-endian), then slcan bytes; base id 0x100, 64 rows.
 *
 * The first input byte past a target's layout chooses nothing else: one binary per target (-DTARGET_SLCAN).
 */
#include "../../../drivers/_framekernel.c"

#include <stdlib.h>

#include "fuzz_check.h"

static double row_t(const unsigned char *row)
{
    double t;
    memcpy(&t, row, 8);
    return t;
}

/* the rows of a read stamped as base.py Driver._stamp says: never before last_t, non-decreasing, the newest
   at t_recv unless last_t is later */
static void check_stamps(const unsigned char *rows, Py_ssize_t k, double t_recv, double last_t0, double last_t)
{
    double prev = last_t0;
    for (Py_ssize_t i = 0; i < k; i++) {
        double t = row_t(rows + i * SAMPLE_SIZE);
        CHECK(t >= prev);
        prev = t;
    }
    CHECK(last_t == prev);
    CHECK(last_t == (t_recv > last_t0 ? t_recv : last_t0));
}

#ifndef TARGET_SLCAN
/* the same sealing as fuzz_targets._seal */
static void seal(unsigned char *s, size_t n, int consecutive)
{
    unsigned int seq0 = n >= FRAME_LEN ? u16le(s + 3) : 0;
    for (size_t j = 0; j + 1 <= n / FRAME_LEN; j++) {
        unsigned char *p = s + j * FRAME_LEN;
        p[0] = 0xA5, p[1] = 0x5A, p[2] = PAYLOAD_LEN;
        if (consecutive) {
            unsigned int q = (seq0 + (unsigned int)j) & 0xFFFF;
            p[3] = q & 0xFF, p[4] = q >> 8;
        }
        unsigned int crc = crc_ccitt(p, FRAME_LEN - 2);
        p[27] = crc >> 8, p[28] = crc & 0xFF;
    }
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    if (size < 2)
        return 0;
    int mode = data[1];
    size_t n = size - 2;
    unsigned char *s = malloc(n ? n : 1);
    memcpy(s, data + 2, n);
    if (mode & 1)
        seal(s, n, mode & 2);

    /* every 29-byte window: intact or not (the stream is allocated to its exact size), and the row of an intact
       one written from a copy of exactly 29 bytes into exactly 56 */
    for (size_t p = 0; p + FRAME_LEN <= n; p++) {
        if (!intact_bytes(s + p, FRAME_LEN))
            continue;
        unsigned char *w = malloc(FRAME_LEN), *row = malloc(SAMPLE_SIZE);
        memcpy(w, s + p, FRAME_LEN);
        to_row_c(w, row, (long long)p, (uint16_t)mode);
        CHECK(isnan(row_t(row)));
        long long seq;
        memcpy(&seq, row + 8, 8);
        CHECK(seq == (long long)p);
        uint32_t tick;
        memcpy(&tick, row + 16, 4);
        CHECK(tick == u32le(w + 5));
        free(row);
        free(w);
    }

    /* the whole stream as one read continuing the first chunk's seq: all of it or nothing, each row the
       per-frame writer's (t aside), stamped in order */
    Py_ssize_t cap = (Py_ssize_t)(n / FRAME_LEN) - (data[0] & 1); /* sometimes one row too few */
    if (cap > 0) {
        unsigned char *rows = malloc((size_t)cap * SAMPLE_SIZE);
        uint32_t *ticks = malloc((size_t)cap * sizeof(uint32_t));
        long long expect = u16le(s + 3);
        double t_recv = 1000.0 + (data[0] >> 1), last_t = 1000.0 + (data[0] & 0x3F), last_t0 = last_t;
        double tick_hz = (data[0] & 0x80) ? 0.0 : 1e6;
        Py_ssize_t k = continuing_c(s, (Py_ssize_t)n, expect, cap, 7, tick_hz, t_recv, &last_t, rows, ticks);
        CHECK(k == 0 || (k * FRAME_LEN == (Py_ssize_t)n && k <= cap));
        if (k == 0) {
            CHECK(last_t == last_t0);
        } else {
            check_stamps(rows, k, t_recv, last_t0, last_t);
            unsigned char one[SAMPLE_SIZE];
            for (Py_ssize_t i = 0; i < k; i++) {
                to_row_c(s + i * FRAME_LEN, one, 7 + i, 0);
                CHECK(memcmp(one + 8, rows + i * SAMPLE_SIZE + 8, SAMPLE_SIZE - 8) == 0);
                CHECK(intact_bytes(s + i * FRAME_LEN, FRAME_LEN));
                CHECK(u16le(s + i * FRAME_LEN + 3) == ((expect + i) & 0xFFFF));
                CHECK(ticks[i] == u32le(s + i * FRAME_LEN + 5));
            }
        }
        free(rows);
        free(ticks);
    }
    free(s);
    return 0;
}

#else
int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    if (size < 2)
        return 0;
    long long expect = data[0] | (data[1] << 8);
    size_t n = size - 2;
    unsigned char *s = malloc(n ? n : 1); /* exactly the bytes: a read past them is a report */
    memcpy(s, data + 2, n);
    /* as fuzz_targets.slcan_lines calls slcan_samples: base 0x100, 64 rows, tick_hz 1e6, t_recv 1000, last_t 0 */
    Py_ssize_t cap = 64;
    unsigned char *rows = malloc(cap * SAMPLE_SIZE);
    uint32_t *ticks = malloc(cap * sizeof(uint32_t));
    double last_t = 0.0;
    Py_ssize_t k = slcan_continuing_c(s, (Py_ssize_t)n, 0x100, expect, cap, 12345, 1e6, 1000.0, &last_t, rows, ticks);
    CHECK(k == 0 || (k * SLCAN_SAMPLE == (Py_ssize_t)n && k <= cap));
    if (k) {
        check_stamps(rows, k, 1000.0, 0.0, last_t);
        for (Py_ssize_t i = 0; i < k; i++) {
            long long seq;
            memcpy(&seq, rows + i * SAMPLE_SIZE + 8, 8);
            CHECK(seq == 12345 + i);
        }
    } else {
        CHECK(last_t == 0.0);
    }
    /* fewer rows than samples: nothing taken, nothing written past the rows */
    if (k > 1) {
        unsigned char *few = malloc((size_t)(k - 1) * SAMPLE_SIZE);
        double lt = 0.0;
        CHECK(slcan_continuing_c(s, (Py_ssize_t)n, 0x100, expect, k - 1, 0, 1e6, 1000.0, &lt, few, ticks) == 0);
        free(few);
    }
    free(rows);
    free(ticks);
    free(s);
    return 0;
}
#endif
