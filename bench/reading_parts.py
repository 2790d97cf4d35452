"""Where the reading pass of `gravcal calibrate FILE.npy` spends its CPU, part by part, on one thread.

    python bench/reading_parts.py FILE.npy [--repeat 5]

Each part alone, minimum of the repeats (CPU seconds, user + system; one thread, so wall ~ CPU on a
free core): "pass" core.datapass.scan_columns as calibrate runs it (repeated runs, block
statistics) into block memory already faulted in (as io/prestart.py prepares it); "file
pages" only faulting in the mapped file's pages (one read a page) and releasing them chunk by chunk
(MADV_DONTNEED, as the pass does); "scan kernel" and "block kernel" the two compiled loops over the
chunks with the pages already mapped (warm, nothing released); "python" the pass less those three.
"zeroing" is the first touch of fresh memory the size of the block statistics (the prestart's
private mapping with huge pages, io/_pages.c populate): it varies several-fold on this VM from
run to run. Prints one JSON object; the record layout of the file must be the plain one (t float64,
ax ay az float32).
"""
from __future__ import annotations

import argparse
import json
import mmap
import os
import resource

import numpy as np

from gravcal.core import datapass, fastdetect
from gravcal.core._blockkernels import block_pass
from gravcal.core._scankernel import scan_chunk
from gravcal.io._pages import populate
from gravcal.io.recordings import SCAN_CHUNK


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    arr = np.load(args.file, mmap_mode="r")
    t, n = arr["t"], arr.shape[0]
    raw = np.ndarray((n, 3), np.float32, buffer=arr, offset=arr.dtype.fields["ax"][1], strides=(arr.strides[0], 4))
    fs = datapass.fs_from(datapass.step_medians(t.view(np.ndarray), SCAN_CHUNK))
    B = fastdetect.block_length(fs)
    nb, chunk = n // B, fastdetect.CHUNK_BLOCKS * B
    held: dict = {}

    def allocate(shape, dtype):  # faulted in once, reused: the prestart's memory
        key = (tuple(shape), np.dtype(dtype).str)
        if key not in held:
            held[key] = np.ones(shape, dtype)
        return held[key]

    out = (np.empty((3, nb)), np.empty((6, nb), np.float32), np.empty((0, nb)), np.empty(nb, bool))
    tv, rv = t.view(np.ndarray), raw.view(np.ndarray)
    release = fastdetect.row_releaser([t])
    page = mmap.PAGESIZE
    bytes_ = np.frombuffer(arr._mmap, np.uint8)

    def whole_pass():
        datapass.scan_columns(t, raw, [], None, chunk=SCAN_CHUNK, repeats=True, blocks=True, threads=1,
                              allocate=allocate)

    def file_pages():
        for i in range(0, n, chunk):
            lo, hi = arr.offset + i * arr.strides[0], arr.offset + min(i + chunk, n) * arr.strides[0]
            int(bytes_[lo // page * page:hi:page].sum())
            release(i, min(i + chunk, n))

    def scan_kernel():
        st = np.array([np.inf] * 3 + [-np.inf] * 3 + [0.0] * 6 + [np.inf, 1.0])
        runs = np.empty((chunk // 10 + 2, 2), np.int64)
        for i in range(0, n, chunk):
            j = min(i + chunk, n)
            prev = None if i == 0 else np.array([tv[i - 1], *rv[i - 1]])
            scan_chunk(tv[i:j], rv[i:j, 0], rv[i:j, 1], rv[i:j, 2], prev, st, runs, 10)

    def block_kernel():
        for i in range(0, nb * B, chunk):
            j = min(i + chunk, nb * B)
            block_pass(rv[i:j, 0], rv[i:j, 1], rv[i:j, 2], tv[max(i - 1, 0):j], None, B, i // B, 1.5 / fs, *out)

    def zeroing():
        size = nb * (3 * 8 + 6 * 4 + 1)
        mm = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
        mm.madvise(mmap.MADV_HUGEPAGE)
        populate(mm, 0, size)
        mm.close()

    spent: dict[str, list[float]] = {}
    parts = {"pass": whole_pass, "file pages": file_pages, "scan kernel": scan_kernel, "block kernel": block_kernel,
             "zeroing": zeroing}
    whole_pass()  # first touch of the held block memory, and the file in the page cache
    for r in range(args.repeat):
        for name, fn in (parts.items() if r % 2 == 0 else reversed(parts.items())):
            if name in ("scan kernel", "block kernel"):
                int(bytes_[::page].sum())  # every page mapped: the kernels alone
            c = _cpu()
            fn()
            spent.setdefault(name, []).append(_cpu() - c)
            release(0, n)
    best = {k: round(min(v), 3) for k, v in spent.items()}
    best["python"] = round(best["pass"] - best["file pages"] - best["scan kernel"] - best["block kernel"], 3)
    print(json.dumps({"cpu_s_min": best, "rows": n, "block_n": B, "load_avg": round(os.getloadavg()[0], 2),
                      "zeroing_gb_per_s": round(nb * 49 / best["zeroing"] / 1e9, 2) if best["zeroing"] else None}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
