"""Time per sample / block of the compiled loops (core._blockkernels, core._scankernel; one thread, best of repeats).

    python bench/block_kernels.py FILE.npy [--rows 2000000] [--repeat 7]

FILE.npy: a structured recording (t float64, ax/ay/az), e.g. the benchmark's simulated week. Its
first ``--rows`` rows are copied into memory, so the figures are the loops' own (in cache or
streaming from RAM), without the page faults of a memory-mapped file: block_pass (block_stats'
chunk, ns a sample), scan_chunk (the reading scan, ns a sample), lotters_chain (ns a block, norm
and axes) and window_sums (ns a block inside windows). Prints one JSON object.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from gravcal.core import fastdetect
from gravcal.core._blockkernels import block_pass, lotters_chain, window_sums
from gravcal.core._scankernel import scan_chunk
from gravcal.core.detectors.butterworth import butter_sos, sos_rest_state


def best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        c = time.perf_counter()
        fn()
        times.append(time.perf_counter() - c)
    return min(times)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file")
    ap.add_argument("--rows", type=int, default=2_000_000)
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    rec = np.array(np.load(args.file, mmap_mode="r")[:args.rows])
    t, x = rec["t"], [rec[c] for c in ("ax", "ay", "az")]
    fs = float(1.0 / np.median(np.diff(t[:1000])))
    B, chunk = fastdetect.block_length(fs), fastdetect.CHUNK_BLOCKS
    nb = len(t) // B
    mean, scat, aux, use = np.empty((3, nb)), np.empty((6, nb), np.float32), np.empty((0, nb)), np.empty(nb, bool)
    L = chunk * B

    def blocks() -> None:
        for i in range(0, nb * B, L):
            j = min(i + L, nb * B)
            block_pass(x[0][i:j], x[1][i:j], x[2][i:j], t[max(i - 1, 0):j], None, B, i // B, 1.5 / fs, mean, scat,
                       aux, use)

    def scan() -> None:
        st = np.array([np.inf] * 3 + [-np.inf] * 3 + [0.0] * 6 + [np.inf, 1.0])
        runs, prev = np.empty(((1 << 16) // 10 + 2, 2), np.int64), None
        for i in range(0, len(t), 1 << 16):
            j = min(i + (1 << 16), len(t))
            scan_chunk(t[i:j], x[0][i:j], x[1][i:j], x[2][i:j], prev, st, runs, 10)
            prev = np.array([t[j - 1], x[0][j - 1], x[1][j - 1], x[2][j - 1]])

    blocks()
    kinv = np.eye(3)  # the decisions do not change the loop's work
    sos_hp, sos_lp = butter_sos(2, 0.5, "highpass", fs / B), butter_sos(2, 0.5, "lowpass", fs / B)
    still = np.zeros(nb, bool)
    rest = np.ascontiguousarray(sos_rest_state(sos_hp))

    def chain() -> None:
        lotters_chain(mean, use, scat, np.full(3, 0.5), kinv, sos_hp, sos_lp, rest, 4, 0.02, 0.02 ** 2 * B,
                      int(np.argmax(use)), still)

    ps = np.arange(0, nb - 600, 700, dtype=np.int64)
    pe = ps + 600
    out = np.empty((3, len(ps))), np.empty((6, len(ps))), np.empty((0, len(ps)))

    def windows() -> None:
        window_sums(mean, scat, aux, ps, pe, B, *out)

    res = {"rows": len(t), "block_n": B,
           "block_pass_ns_per_sample": best(blocks, args.repeat) / (nb * B) * 1e9,
           "scan_chunk_ns_per_sample": best(scan, args.repeat) / len(t) * 1e9,
           "lotters_chain_ns_per_block": best(chain, args.repeat) / nb * 1e9,
           "window_sums_ns_per_block": best(windows, args.repeat) / int((pe - ps).sum()) * 1e9}
    print(json.dumps({k: round(v, 2) if isinstance(v, float) else v for k, v in res.items()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
