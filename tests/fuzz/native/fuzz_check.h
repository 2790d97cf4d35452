/* The native harnesses' assertion: a failed check is a crash libFuzzer keeps, with the condition and place. */
#ifndef GRAVCAL_FUZZ_CHECK_H
#define GRAVCAL_FUZZ_CHECK_H

#include <stdio.h>
#include <stdlib.h>

#define CHECK(cond)                                                                                            \
    do {                                                                                                       \
        if (!(cond)) {                                                                                         \
            fprintf(stderr, "check failed: %s (%s:%d)\n", #cond, __FILE__, __LINE__);                         \
            abort();                                                                                           \
        }                                                                                                      \
    } while (0)

#endif
