"""Time per sample / block of the compiled loops (core._blockkernels, core._scankernel; one thread, best of repeats).

    python bench/block_kernels.py FILE.npy [--rows 2000000] [--repeat 7] [--baseline DIR]

FILE.npy: a structured recording (t float64, ax/ay/az), e.g. the benchmark's simulated week. Its
first ``--rows`` rows are copied into memory, so the figures are the loops' own (in cache or
streaming from RAM), without the page faults of a memory-mapped file: block_pass (block_stats'
chunk, ns a sample), scan_chunk (the reading scan with the repeated-run search, ns a sample), both
on the record's fields in place (the datapass case) and on copies of the columns (each its own
stride: the loops for any layout), lotters_chain (ns a block, norm and axes) and window_sums (ns a
block inside windows). ``--baseline DIR``: another build's _blockkernels / _scankernel .so files
(e.g. copied from another tree), timed alternately with this tree's in the same process, the same
outputs checked bit for bit. Prints one JSON object.
"""
from __future__ import annotations

import argparse
import glob
import importlib.util
import json
import os
import time

import numpy as np

from gravcal.core import fastdetect
from gravcal.core import _blockkernels, _scankernel
from gravcal.core._blockkernels import lotters_chain, window_sums
from gravcal.core.butterworth import butter_sos, sos_rest_state


def best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        c = time.perf_counter()
        fn()
        times.append(time.perf_counter() - c)
    return min(times)


def load_build(directory: str) -> tuple:
    """(_blockkernels, _scankernel) modules from the .so files in ``directory``."""
    mods = []
    for name in ("_blockkernels", "_scankernel"):
        path = glob.glob(os.path.join(directory, name + ".*.so"))
        if not path:
            raise SystemExit(f"no {name}.*.so in {directory}")
        spec = importlib.util.spec_from_file_location(name, path[0])
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        mods.append(mod)
    return tuple(mods)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file")
    ap.add_argument("--rows", type=int, default=2_000_000)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--baseline", help="directory with another build's _blockkernels/_scankernel .so files")
    args = ap.parse_args()
    rec = np.array(np.load(args.file, mmap_mode="r")[:args.rows])
    t, x = rec["t"], [rec[c] for c in ("ax", "ay", "az")]
    fs = float(1.0 / np.median(np.diff(t[:1000])))
    B, chunk = fastdetect.block_length(fs), fastdetect.CHUNK_BLOCKS
    nb = len(t) // B
    mean, scat, aux, use = np.empty((3, nb)), np.empty((6, nb), np.float32), np.empty((0, nb)), np.empty(nb, bool)
    L = chunk * B

    copies = rec["t"].copy(), [c.copy() for c in x]  # each column its own stride: the any-layout loops

    def blocks(bk, cols=(t, x), check=False):
        tt, xx = cols
        for i in range(0, nb * B, L):
            j = min(i + L, nb * B)
            bk.block_pass(xx[0][i:j], xx[1][i:j], xx[2][i:j], tt[max(i - 1, 0):j], None, B, i // B, 1.5 / fs, mean,
                          scat, aux, use)
        return mean.tobytes() + scat.tobytes() + use.tobytes() if check else None

    def scan(sk, cols=(t, x), check=False):
        tt, xx = cols
        st = np.array([np.inf] * 3 + [-np.inf] * 3 + [0.0] * 6 + [np.inf, 1.0])
        runs, prev, found = np.empty(((1 << 16) // 10 + 2, 2), np.int64), None, []
        for i in range(0, len(tt), 1 << 16):
            j = min(i + (1 << 16), len(tt))
            n_runs, n_rep = sk.scan_chunk(tt[i:j], xx[0][i:j], xx[1][i:j], xx[2][i:j], prev, st, runs, 10)
            if check:
                found.append((n_rep, runs[:n_runs].tobytes()))
            prev = np.array([tt[j - 1], xx[0][j - 1], xx[1][j - 1], xx[2][j - 1]])
        return (st.tobytes(), found) if check else None

    builds = {"": (_blockkernels, _scankernel)}
    if args.baseline:
        builds["baseline_"] = load_build(args.baseline)
    for bk, sk in builds.values():  # every build and layout gives the same bits
        assert blocks(bk, check=True) == blocks(bk, copies, True) == blocks(_blockkernels, check=True), \
            "block_pass outputs differ"
        assert scan(sk, check=True) == scan(sk, copies, True) == scan(_scankernel, check=True), \
            "scan_chunk outputs differ"
    times: dict[str, list[float]] = {}
    for _ in range(args.repeat):  # the builds alternated
        for tag, (bk, sk) in builds.items():
            for name, fn in ((f"{tag}block_pass", lambda: blocks(bk)), (f"{tag}block_pass_any_layout",
                             lambda: blocks(bk, copies)), (f"{tag}scan_chunk", lambda: scan(sk)),
                             (f"{tag}scan_chunk_any_layout", lambda: scan(sk, copies))):
                times.setdefault(name, []).append(best(fn, 1))

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

    res = {"rows": len(t), "block_n": B}
    for name, ts in times.items():
        res[name + "_ns_per_sample"] = min(ts) / (nb * B if "block" in name else len(t)) * 1e9
    res.update({
        "lotters_chain_ns_per_block": best(chain, args.repeat) / nb * 1e9,
        "window_sums_ns_per_block": best(windows, args.repeat) / int((pe - ps).sum()) * 1e9})
    print(json.dumps({k: round(v, 2) if isinstance(v, float) else v for k, v in res.items()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
