#!/bin/sh
# Builds the libFuzzer harnesses of the C kernels (clang, AddressSanitizer, UBSan) into OUT (default
# /tmp/gravcal-native-fuzz):  sh tests/fuzz/native/build.sh [OUT]
# (ASAN_OPTIONS=detect_leaks=0 for linekernel_fuzz: the embedded interpreter is never finalised), then e.g.
#   OUT/framekernel_fuzz -runs=10000000 -print_final_stats=1 /tmp/fuzzcorpus/frame_decoder_native
set -eu
HERE=$(cd "$(dirname "$0")" && pwd)
OUT=${1:-/tmp/gravcal-native-fuzz}
PY=${PYTHON:-python3}
INC=$($PY -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
LIBDIR=$($PY -c 'import sysconfig; print(sysconfig.get_config_var("LIBDIR"))')
PYLIB=$($PY -c 'import sysconfig; print("python" + sysconfig.get_config_var("LDVERSION"))')
mkdir -p "$OUT"
# the modules' Python wrappers are linked (never called; the line kernel's number formatting calls Python)
FLAGS="-g -O1 -ffp-contract=off -fsanitize=fuzzer,address,undefined -fno-sanitize-recover=all -I$INC"
LIBS="-L$LIBDIR -Wl,-rpath,$LIBDIR -l$PYLIB -lm"
clang $FLAGS -I"$HERE/../../../drivers" "$HERE/framekernel_fuzz.c" -o "$OUT/framekernel_fuzz" $LIBS
clang $FLAGS -I"$HERE/../../../drivers" -DTARGET_SLCAN "$HERE/framekernel_fuzz.c" -o "$OUT/slcan_fuzz" $LIBS
clang $FLAGS -I"$HERE/../../../daemon" "$HERE/linekernel_fuzz.c" -o "$OUT/linekernel_fuzz" $LIBS
echo "$OUT/framekernel_fuzz $OUT/slcan_fuzz $OUT/linekernel_fuzz"
