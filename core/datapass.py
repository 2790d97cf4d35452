"""One pass over a recording's columns: what reading validates and, optionally, the block statistics.

Reading a recording (io/recordings.py) needs, over every row, each channel's extremes and how
many samples sit exactly on them (saturation), the smallest time step, whether every value is
finite and the exactly repeated rows (filler). The block detector (core.fastdetect) needs the
0.1 s block statistics of the same rows. :func:`scan_columns` reads each chunk once for both,
while it is in the CPU cache, and shares the chunks between two threads (the compiled scan and
block loops run without the GIL). The results do not depend on the chunking or the threads: the
extremes and counts merge exactly, repeated runs are joined across chunk borders in row order,
and the sample rate comes from the same sampled chunks before the pass (so the block length and
the time-step limit are known while it runs).
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from . import fastdetect
from .accelerator import kernels
from .fastdetect import BlockPass, BlockStats, block_length, row_releaser, run_lanes
from .repeats import MIN_RUN, RunCollector
from .samples import FLAG_SATURATED

scan_chunk = kernels("gravcal.core._scankernel").scan_chunk

MEDIAN_EVERY = 64  # the sample rate is the median of the median steps of every 64th chunk


@dataclass
class ScanStats:
    """What one pass over the columns finds."""

    finite: bool = True
    min_dt: float = math.inf  # smallest time step (<= 0: time not increasing somewhere)
    dt_medians: list[float] = field(default_factory=list)  # median step of sampled chunks
    lo: np.ndarray = field(default_factory=lambda: np.full(3, np.inf))  # per-channel minimum
    hi: np.ndarray = field(default_factory=lambda: np.full(3, -np.inf))  # per-channel maximum
    n_lo: np.ndarray = field(default_factory=lambda: np.zeros(3, np.int64))  # samples exactly at the minimum
    n_hi: np.ndarray = field(default_factory=lambda: np.zeros(3, np.int64))  # samples exactly at the maximum
    n_flagged: int = 0  # samples flagged saturated by the logger
    repeats: RunCollector | None = None  # exactly repeated rows, when asked for
    blocks: BlockStats | None = None  # block statistics of every row at fs_from(dt_medians), when asked for


FS_DIGITS = 9
"""Significant digits of the sample rate: a float64 time of a week (6e5 s) resolves ~1e-10 s, 1e-8 of a
100 Hz step, so digits past the ninth are rounding noise of the time stamps (100.00000000009095 Hz)."""


def fs_from(dt_medians: Sequence[float]) -> float:
    """The sample rate [Hz] of the sampled median steps, to FS_DIGITS significant digits (nan when they give
    none: no steps, or a median step that is not positive, as in a file whose times repeat)."""
    if not len(dt_medians):
        return math.nan
    step = float(np.median(dt_medians))
    return float(f"{1.0 / step:.{FS_DIGITS}g}") if step > 0 else math.nan


def step_medians(t: np.ndarray, chunk: int) -> list[float]:
    """Median time step of every MEDIAN_EVERY-th chunk of ``chunk`` rows (with the step into the
    chunk's first row); NaN where a chunk holds a NaN time."""
    n = int(t.shape[0])
    out = []
    with np.errstate(invalid="ignore"):  # inf - inf: a non-finite time the pass reports as such
        for i in range(0, n, chunk * MEDIAN_EVERY):
            tc = np.asarray(t[max(i - 1, 0):min(i + chunk, n)], dtype=np.float64)
            if tc.shape[0] > 1:
                out.append(float(np.median(np.diff(tc))))
    return out


def _fresh_state() -> np.ndarray:
    st = np.empty(14)  # scan_chunk's: min[3], max[3], count at min[3], count at max[3], smallest step, finite
    st[0:3], st[3:6], st[6:12], st[12], st[13] = np.inf, -np.inf, 0.0, np.inf, 1.0
    return st


def _merge(states: list[np.ndarray], sc: ScanStats) -> None:
    """Per-thread scan states into ``sc``: extremes, the counts of the threads that reached them."""
    s = np.array(states)
    sc.lo, sc.hi = s[:, 0:3].min(axis=0), s[:, 3:6].max(axis=0)
    sc.n_lo = np.where(s[:, 0:3] == sc.lo, s[:, 6:9], 0).sum(axis=0).astype(np.int64)
    sc.n_hi = np.where(s[:, 3:6] == sc.hi, s[:, 9:12], 0).sum(axis=0).astype(np.int64)
    sc.min_dt = float(s[:, 12].min())


def scan_columns(t: np.ndarray, raw: np.ndarray, extra: list[np.ndarray], flags: np.ndarray | None, *,
                 chunk: int, progress: Callable[[int, int], None] | None = None, repeats: bool = False,
                 blocks: bool = False, aux: np.ndarray | None = None,
                 threads: int | None = None, min_run: int = MIN_RUN,
                 allocate: Callable[[tuple[int, ...], Any], np.ndarray] | None = None) -> ScanStats:
    """One pass over t (n,) [s] and raw (n, 3) (any float or integer dtype, any stride, e.g. fields
    of a memory-mapped .npy, whose pages are released chunk by chunk), ``extra`` columns checked
    for finiteness, ``flags`` (the logger's, FLAG_SATURATED counted). ``repeats``: collect the
    exactly repeated rows. ``blocks``: also the block statistics (core.fastdetect.block_stats of
    the same columns with ``aux``, at the sample rate of ``dt_medians``), in chunks of
    fastdetect.CHUNK_BLOCKS blocks instead of ``chunk`` rows. Stops at the first chunk holding a
    non-finite value (``finite`` False, nothing else filled in): the caller drops those rows and
    scans again. ``progress(done, total)``: chunks done, one call at a time. ``allocate(shape, dtype)``:
    where the block statistics go (core.fastdetect.BlockPass)."""
    n = int(t.shape[0])
    threads = fastdetect.THREADS if threads is None else threads
    drop = row_releaser([c for c in (t, raw, *extra, flags, aux) if c is not None])
    # plain views of np.memmap columns: slicing a memmap runs its Python __getitem__ (~6 us a slice)
    t, raw, aux, flags, *extra = (a.view(np.ndarray) if isinstance(a, np.memmap) else a
                                  for a in (t, raw, aux, flags, *extra))
    sc = ScanStats(repeats=RunCollector(min_run) if repeats else None)
    sc.dt_medians = step_medians(t, chunk)
    drop(0, n)  # the sampled chunks' pages
    fs = fs_from(sc.dt_medians)
    bp = None
    if blocks and math.isfinite(fs) and fs > 0:
        bp = BlockPass(t, lambda c, i, j: raw[i:j, c], n, fs, aux, block_length(fs), allocate)
        chunk = fastdetect.CHUNK_BLOCKS * bp.B
    starts = list(range(0, n, chunk))
    native = raw.dtype.type in (np.float32, np.float64) and raw.dtype.isnative
    t_native = t.dtype.type is np.float64 and t.dtype.isnative
    local = threading.local()
    states: list[np.ndarray] = []
    pieces: dict[int, tuple[np.ndarray, np.ndarray, int]] = {}
    lock, stop, done = threading.Lock(), threading.Event(), [0, 0]  # done: chunks, flagged samples

    def work(i: int) -> None:
        if stop.is_set():
            return
        if not hasattr(local, "state"):
            # room for every run chunk_runs keeps: runs of >= min_run steps are min_run + 1 steps apart
            local.state = _fresh_state()
            local.runs = np.empty((min(n, chunk) // min_run + 2, 2), dtype=np.int64) if repeats else None
            with lock:
                states.append(local.state)
        j = min(i + chunk, n)
        tc = t[i:j] if t_native else np.asarray(t[i:j], dtype=np.float64)
        block = raw[i:j] if native else np.asarray(raw[i:j], dtype=np.float64)
        prev = None if i == 0 else np.array([t[i - 1], *raw[i - 1]], dtype=np.float64)  # the row before
        n_runs, n_repeats = scan_chunk(tc, block[:, 0], block[:, 1], block[:, 2], prev, local.state, local.runs,
                                       min_run)  # releases the GIL
        if not (local.state[13] and all(np.isfinite(np.asarray(e[i:j], dtype=np.float64)).all() for e in extra)):
            stop.set()
            return
        n_flag = 0 if flags is None else int(np.count_nonzero(np.asarray(flags[i:j]).astype(np.int64) & FLAG_SATURATED))
        if local.runs is not None:  # the chunk's steps: its rows against the row before (the first has none at 0)
            pieces[i] = (local.runs[:n_runs, 0].copy(), local.runs[:n_runs, 1].copy(), n_repeats)
        if bp is not None and i < bp.nb * bp.B:
            bp.chunk(i, min(j, bp.nb * bp.B))
        # a memory-mapped input stays in the page cache but leaves this process's resident set:
        # the pass must not hold the whole file
        drop(i, j)
        with lock:
            done[0] += 1
            done[1] += n_flag
            if progress is not None:
                progress(done[0], len(starts))

    run_lanes(starts, work, threads)
    if stop.is_set():
        sc.finite = False
        return sc
    _merge(states or [_fresh_state()], sc)
    sc.n_flagged = done[1]
    if sc.repeats is not None:
        for i in starts:  # in row order: runs join across chunk borders
            st, ln, k = pieces[i]
            sc.repeats.add_runs(st, ln, k, max(i - 1, 0), min(i + chunk, n) - i - (i == 0))
    sc.blocks = None if bp is None else bp.result()
    return sc
