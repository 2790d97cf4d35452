/* libFuzzer harness of daemon/_linekernel.c (the IMU line of one sample), built with AddressSanitizer and UBSan
 * (build.sh). The kernel's static functions are called directly on an input read as fuzz_targets.imu_line reads
 * it (a SAMPLE_DTYPE row, acc 3 float64, gyro float64, the static code int8, raw bit 0; zero-padded to 90 bytes),
 * so the corpus it grows replays there, where the bytes are compared with the block encoder's. Here: the line is
 * one line of printable ASCII ending "}\n", written within its bounds into a buffer of exactly its length, a
 * buffer one byte short is refused, and the writer without the GIL gives the same bytes or asks for the GIL.
 * Numbers put_f_exact cannot write go to PyOS_double_to_string: Python is initialised once.
 */
#include "../../../daemon/_linekernel.c"

#include <stdlib.h>

#include "fuzz_check.h"

#define INPUT 90

int LLVMFuzzerInitialize(int *argc, char ***argv)
{
    Py_InitializeEx(0);
    return 0;
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    unsigned char in[INPUT] = {0};
    memcpy(in, data, size < INPUT ? size : INPUT);
    unsigned char *row = malloc(SAMPLE_SIZE); /* exact sizes: a read past them is a report */
    double *acc = malloc(3 * sizeof(double)), gyro;
    memcpy(row, in, SAMPLE_SIZE);
    memcpy(acc, in + 56, 24);
    memcpy(&gyro, in + 80, 8);
    long long code = (signed char)in[88];
    int raw = in[89] & 1;

    /* the line into the largest buffer, then (input bits 1 and 2 say which, to keep most inputs to two writes)
       into exactly its length and into one byte less */
    char *big = malloc(IMU_LINE_MAX);
    Py_ssize_t n = line_c(row, acc, gyro, code, raw, big, IMU_LINE_MAX);
    CHECK(n > 0 && !PyErr_Occurred());
    CHECK(n >= 2 && big[n - 2] == '}' && big[n - 1] == '\n' && big[0] == '{');
    for (Py_ssize_t i = 0; i < n - 1; i++)
        CHECK(big[i] >= 0x20 && big[i] < 0x7f);
    char *out = malloc((size_t)n);
    if (in[89] & 2)
        CHECK(line_c(row, acc, gyro, code, raw, out, n) == n && memcmp(out, big, (size_t)n) == 0);
    if (in[89] & 4) {
        CHECK(line_c(row, acc, gyro, code, raw, out, n - 1) == -1 && PyErr_Occurred());
        PyErr_Clear();
    }
    /* without the GIL: the same bytes into exactly their length, or -2 (a number it cannot write) */
    Py_ssize_t m = line_nogil_c(row, acc, gyro, code, raw, out, n);
    CHECK(m == -2 || (m == n && memcmp(big, out, (size_t)n) == 0));
    free(out);
    free(big);
    free(acc);
    free(row);
    return 0;
}
