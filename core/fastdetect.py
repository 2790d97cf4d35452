"""Offline quasi-static detection from block statistics: one memory pass over a recording.

The streaming detectors (core.detectors) decide sample by sample at the full rate, which for a
week at 100 Hz means 60 M samples through two IIR filters on four channels (~5 s). Offline,
the same decisions can be made on short blocks (default 0.1 s) without losing anything the
estimators use:

1. :func:`block_stats` reads the samples ONCE, in chunks, and keeps per block of ``block_n``
   samples its mean (float64) and its within-block scatter Σ (x - mean)(x - mean)ᵀ (summed in
   float64, stored as float32, 6 entries), plus whether every sample is finite and follows its
   predecessor by a step in (0, 1.5/fs]. One compiled loop per chunk (core/_blockkernels.c)
   reads the channels' strided fields in place (e.g. of a memory-mapped record); two threads
   share the chunks. Pages of a memory-mapped input are released after each chunk
   (:func:`row_releaser`), so memory stays at the statistics (~0.24x the input of a week of
   20-byte samples) instead of growing with the mapped file.
2. :func:`detect_blocks` runs the detector on the block means at fs / block_n:
   "lotters" is Lötters 1998 eq. 1-2 (|a|, 0.5 Hz high-pass, rectifier, 0.5 Hz low-pass, and
   the per-axis chains of QuasiStaticDetector; one compiled loop, SciPy's sosfilt arithmetic),
   which at 10 Hz still resolves the 0.5 Hz corners; "variance" is the per-axis moving std over
   the trailing window_s, exact at block boundaries (from the block means and scatters). A
   block is still when its detection signal is below ``threshold_g``, it is usable (finite, no
   time gap), the filters have settled, and — what the block means cannot see — the per-axis
   std of its own samples is below ``threshold_g`` too (vibration above the block rate's
   Nyquist frequency).
3. The windowing rules are those of the streaming detectors (core.detectors) in blocks: the
   still mask is eroded by ``guard_s``, runs are cut into pieces of ``max_duration_s`` from
   their first block, pieces shorter than ``min_duration_s`` are dropped. Window means and
   covariances are exact functions of the samples (block means and the within-block scatter
   recombined: Σ_w = Σ_b W_b + n_b Σ_b (m_b - m)(m_b - m)ᵀ), not approximations.

Equivalence with the streaming detector (tests/core/test_fastdetect.py): window boundaries agree to
within about one guard plus one block (the detection signal is the same filter chain, sampled
coarser), the calibrations fitted on the two window sets agree within their reported standard
deviations, and the held-out error is not worse. A recording's last ``n mod block_n`` samples
(under 0.1 s) are not used; the streaming detector trims the last guard (0.5 s) anyway.
"""
from __future__ import annotations

import math
import mmap
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from .accelerator import kernels
from .calibration import Calibration
from .detectors import estimate_fs
from .butterworth import butter_sos, sos_rest_state
from .detectors.windowing import settle_samples
from .windows import WindowSet

_kernels = kernels("gravcal.core._blockkernels")
block_pass, chain_lanes, lotters_chain = _kernels.block_pass, _kernels.chain_lanes, _kernels.lotters_chain
variance_chain, window_sums = _kernels.variance_chain, _kernels.window_sums

BLOCK_S = 0.1  # block length [s]: 10 Hz detection, boundaries to 0.1 s
CHUNK_BLOCKS = 4096  # blocks per chunk of the reducing pass (a few 100 kB per channel: stays in the CPU cache)
THREADS = 2  # chunks of the reducing pass are shared between this many threads
GATHER_THREAD_MIN = 1024  # windows from which their times are gathered beside the window sums
GATHER_PIECE = 1024  # window times gathered from a mapped t before its touched pages are released
RELEASE_MARGIN_BYTES = 1 << 17  # beyond fault-around's reach (64 kB) on either side of a piece
CHAIN_LANES_MIN_BLOCKS = 1 << 16  # blocks from which Lötters' four filter chains run as two halves on two threads
# the kernel filters the four channels of order 2 in the lanes of one vector (AVX2): one call then takes less
# time than the longer of two halves on two threads (the week: 0.085 against 0.12 s)
CHAIN_VECTOR = chain_lanes()

_I6 = np.array([0, 1, 2, 0, 0, 1])
_J6 = np.array([0, 1, 2, 1, 2, 2])


def _mapped_rows(a: np.ndarray) -> tuple[Any, int, int] | None:
    """(mmap, byte offset of row 0 in it, row stride) of a read-only np.memmap (or a view of one),
    else None: for private memory, MADV_DONTNEED would zero the data."""
    base: Any = a
    while base is not None and not isinstance(base, np.memmap):
        base = getattr(base, "base", None)
    mm = getattr(base, "_mmap", None)
    if mm is None or getattr(base, "mode", None) != "r" or not hasattr(mm, "madvise") or a.ndim == 0:
        return None
    start = np.frombuffer(mm, dtype=np.uint8).__array_interface__["data"][0]
    return mm, a.__array_interface__["data"][0] - start, a.strides[0]


def row_releaser(arrays: Sequence[np.ndarray]) -> Callable[[int, int], None]:
    """``release(lo, hi)``: drop rows [lo, hi) of the memory-mapped ones of ``arrays`` from this
    process's resident set. The data stays in the page cache (reading them again is a minor fault,
    no I/O); only the process stops holding them, so one pass over a mapped 1.2 GB file does not
    leave 1.2 GB in its RSS. Each mapping is resolved once, and fields of the same records (t and
    the triad of one structured .npy) are released once, not once per field."""
    rows: list[tuple[Any, int, int]] = []
    for a in arrays:
        r = _mapped_rows(a) if isinstance(a, np.ndarray) else None
        # another field of records already listed: within one record (stride) of it in the same mapping
        if r is not None and not any(q[0] is r[0] and q[2] == r[2] and abs(q[1] - r[1]) < abs(r[2]) for q in rows):
            rows.append(r)
    page = mmap.PAGESIZE

    def release(lo: int, hi: int) -> None:
        for mm, offset, stride in rows:
            first = (offset + lo * stride) // page * page
            last = min((offset + hi * stride) // page * page, len(mm))
            if last > first >= 0:
                mm.madvise(mmap.MADV_DONTNEED, first, last - first)

    return release


def release_mapped(a: np.ndarray, lo: int, hi: int) -> None:
    """Drop rows [lo, hi) of a read-only memory-mapped array from this process's resident set
    (:func:`row_releaser` for one array and one range); a no-op for anything else."""
    row_releaser([a])(lo, hi)


@dataclass
class BlockStats:
    """Per-block sufficient statistics of a recording (blocks of ``block_n`` samples)."""

    fs: float  # sample rate [Hz]
    block_n: int  # samples per block
    mean: np.ndarray  # (3, nb) float64: block means [raw units] (channel-major: rows contiguous)
    scatter: np.ndarray  # (6, nb) float32: Σ (x - mean)_i (x - mean)_j over the block, entries _I6/_J6
    aux: np.ndarray  # (k, nb) float64: block means of the auxiliary channels
    usable: np.ndarray  # (nb,) bool: every sample finite, every time step in (0, 1.5/fs]

    def __len__(self) -> int:
        return int(self.mean.shape[1])

    @property
    def n_samples(self) -> int:
        return len(self) * self.block_n


def block_length(fs: float, block_s: float = BLOCK_S) -> int:
    return max(1, int(round(block_s * fs)))


def pass_chunks(n: int, block_n: int) -> int:
    """Chunks of block_stats' pass over n samples in blocks of block_n (its progress total)."""
    return -(-(n // block_n) // CHUNK_BLOCKS)


class BlockPass:
    """block_stats' statistics filled chunk by chunk: ``chunk(i, j)`` reduces rows [i, j) (i a
    multiple of block_n, j <= len(blocks) * block_n) and may run in any order and from several
    threads at once (the kernel releases the GIL; chunks write disjoint blocks). The reading scan
    (core.datapass) calls it on the rows it has just scanned; :func:`block_stats` on its own grid."""

    def __init__(self, t: np.ndarray, channel: Callable[[int, int, int], np.ndarray], n: int, fs: float,
                 aux: np.ndarray | None = None, block_n: int | None = None,
                 allocate: Callable[[tuple[int, ...], Any], np.ndarray] | None = None):
        """``allocate(shape, dtype)``: where the statistics go (default np.empty; e.g. memory already
        faulted in, io/prestart.py); every element is written by the chunks, none read first."""
        if not (fs > 0 and math.isfinite(fs)):
            raise ValueError(f"sample rate fs must be a positive number of Hz, got {fs!r}")
        self.t, self.channel, self.fs = t, channel, float(fs)
        self.B = block_n or block_length(fs)
        self.nb = n // self.B
        self.aux = aux[:, None] if aux is not None and np.ndim(aux) == 1 else aux
        k = 0 if self.aux is None else self.aux.shape[1]
        new = allocate or _empty
        self.mean = _checked(new((3, self.nb), np.float64), (3, self.nb), np.float64)
        self.scatter = _checked(new((6, self.nb), np.float32), (6, self.nb), np.float32)
        self.aux_mean = _checked(new((k, self.nb), np.float64), (k, self.nb), np.float64)
        self.usable = _checked(new((self.nb,), np.bool_), (self.nb,), np.bool_)
        self.step = 1.5 / fs

    def chunk(self, i: int, j: int) -> None:
        xs = [_floats(self.channel(c, i, j), (np.float32, np.float64)) for c in range(3)]
        if len({x.dtype for x in xs}) > 1:
            xs = [np.asarray(x, dtype=np.float64) for x in xs]
        # the kernel checks each step into a sample: the chunk's times with the one before it
        tc = _floats(self.t[max(i - 1, 0):j], (np.float64,))
        a = None if self.aux is None else _floats(self.aux[i:j], (np.float64,))
        block_pass(*xs, tc, a, self.B, i // self.B, self.step, self.mean, self.scatter, self.aux_mean,
                   self.usable)  # releases the GIL

    def result(self) -> BlockStats:
        return BlockStats(self.fs, self.B, self.mean, self.scatter, self.aux_mean, self.usable)


def _empty(shape: tuple[int, ...], dtype: Any) -> np.ndarray:
    return np.empty(shape, dtype=dtype)


def _checked(a: np.ndarray, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
    """An allocator's array as the kernel writes it: this shape and dtype, C-contiguous, writable."""
    if not (isinstance(a, np.ndarray) and a.shape == shape and a.dtype == np.dtype(dtype) and a.flags.c_contiguous
            and a.flags.writeable):
        raise ValueError(f"block statistics need a writable C-contiguous {np.dtype(dtype)} array of shape {shape}")
    return a


def block_stats(t: np.ndarray, channel: Callable[[int, int, int], np.ndarray], n: int, fs: float, *,
                aux: np.ndarray | None = None, block_n: int | None = None, threads: int = THREADS,
                release: Sequence[np.ndarray] = (),
                progress: Callable[[int, int], None] | None = None) -> BlockStats:
    """One pass over a recording: ``channel(c, i, j)`` gives raw channel c (0..2) rows [i, j) as
    a 1-D array (any float dtype, any stride, e.g. a field of a memory-mapped .npy); t (n,) [s];
    aux (n,) or (n, k) optional. ``release``: arrays whose mapped pages are dropped per chunk.
    ``progress(done, total)``: called after each chunk with chunks done so far (increasing, from
    whichever thread finished it, one call at a time) and the chunk count."""
    bp = BlockPass(t, channel, n, fs, aux, block_n)
    chunk = CHUNK_BLOCKS * bp.B
    starts = list(range(0, bp.nb * bp.B, chunk))
    done = [0]
    lock = threading.Lock()
    drop = row_releaser(release)

    def work(i: int) -> None:
        j = min(i + chunk, bp.nb * bp.B)
        bp.chunk(i, j)
        drop(i, j)
        if progress is not None:
            with lock:
                done[0] += 1
                progress(done[0], len(starts))

    run_lanes(starts, work, threads)
    return bp.result()


def run_lanes(items: Sequence[Any], work: Callable[[Any], None], threads: int = THREADS) -> None:
    """``work(item)`` for every item, shared between ``threads`` threads (thread r takes items r,
    r + threads, ...: the threads move through a file side by side); the calling thread is one."""
    if threads > 1 and len(items) > 1:
        def lane(r: int) -> None:
            for item in items[r::threads]:
                work(item)

        with ThreadPoolExecutor(threads - 1, thread_name_prefix="gravcal-blocks") as pool:
            jobs = [pool.submit(lane, r) for r in range(1, threads)]
            lane(0)
            for job in jobs:
                job.result()
    else:
        for item in items:
            work(item)


def _floats(a: np.ndarray, kinds: tuple[type, ...]) -> np.ndarray:
    """a itself when it holds native floats of one of ``kinds`` (any stride: the kernel reads it in
    place), else a float64 copy (integer counts, another byte order)."""
    a = np.asarray(a)
    if a.dtype.type in kinds and a.dtype.isnative:
        return a
    return np.asarray(a, dtype=np.float64)


def _to_g_affine(to_g: Calibration | None) -> tuple[np.ndarray, np.ndarray]:
    """(offset, K^-1): a [g] = K^-1 (raw - offset); identity when to_g is None (thresholds in raw units)."""
    if to_g is None:
        return np.zeros(3), np.eye(3)
    if not isinstance(to_g, Calibration):
        raise TypeError(f"block detection needs to_g as a Calibration or None (got {type(to_g).__name__}); "
                        f"use core.detectors for an arbitrary callable")
    return np.asarray(to_g.offset, dtype=float), np.linalg.inv(to_g.sensitivity)


def lotters_still(bs: BlockStats, to_g: Calibration | None = None, *, hp_hz: float = 0.5, lp_hz: float = 0.5,
                  threshold_g: float = 0.02, settle_s: float | None = None, order: int = 2,
                  per_axis: bool = True) -> np.ndarray:
    """Still blocks by Lötters' detector (eq. 1-2, and QuasiStaticDetector's per-axis chains)."""
    fs_b = bs.fs / bs.block_n
    nyq = 0.5 * fs_b
    if not (0 < hp_hz < nyq and 0 < lp_hz < nyq):
        raise ValueError(f"filter corners must lie below the block rate's Nyquist frequency {nyq} Hz "
                         f"(hp={hp_hz}, lp={lp_hz}): use shorter blocks")
    if not threshold_g > 0:
        raise ValueError(f"threshold_g must be > 0, got {threshold_g}")
    o, kinv = _to_g_affine(to_g)
    nb = len(bs)
    still = np.zeros(nb, dtype=bool)
    if not bs.usable.any():
        return still
    b0 = int(np.argmax(bs.usable))  # the first usable block
    sos_hp = butter_sos(order, hp_hz, "highpass", fs_b)
    sos_lp = butter_sos(order, lp_hz, "lowpass", fs_b)
    settle = (int(round(settle_s * fs_b)) if settle_s is not None
              else settle_samples(sos_hp, 0.0, fs_b, hp_hz) + settle_samples(sos_lp, 1.0, fs_b, lp_hz))
    # K^-1 (mean - o), |a| (eq. 1), high-pass, rectifier, low-pass, < threshold (eq. 2) on the norm
    # and (per_axis) the three axes, the within-block std gate; unusable blocks held at the last
    # usable one, the high-pass at rest on the first (core.detectors: the first finite sample)
    args = (np.ascontiguousarray(bs.mean, dtype=np.float64), np.ascontiguousarray(bs.usable),
            np.ascontiguousarray(bs.scatter, dtype=np.float32), np.ascontiguousarray(o, dtype=np.float64),
            np.ascontiguousarray(kinv, dtype=np.float64), sos_hp, sos_lp, np.ascontiguousarray(sos_rest_state(sos_hp)))
    limits = (float(threshold_g), float(threshold_g) ** 2 * bs.block_n, b0)
    if per_axis and nb - b0 >= CHAIN_LANES_MIN_BLOCKS and not (order == 2 and CHAIN_VECTOR):
        # no vector lanes for these filters: the four channels' filters in two halves on two threads (the
        # kernel releases the GIL): (|a|, x) here, (y, z) and the std gate beside it, each block still when
        # both say so
        other = np.empty(nb, dtype=bool)
        with ThreadPoolExecutor(1, thread_name_prefix="gravcal-chain") as pool:
            job = pool.submit(lotters_chain, *args, 4, *limits, other, None, 2, True)
            lotters_chain(*args, 2, *limits, still, None, 0, False)
            job.result()
        np.logical_and(still, other, out=still)
    else:
        lotters_chain(*args, 4 if per_axis else 1, *limits, still)
    still[b0:b0 + settle] = False
    return still


def variance_still(bs: BlockStats, to_g: Calibration | None = None, *, window_s: float = 1.0,
                   threshold_g: float = 0.02) -> np.ndarray:
    """Still blocks by the per-axis moving std (MovingVarianceDetector) over the trailing
    ``window_s`` (a whole number of blocks), exact from the block statistics."""
    wb = max(1, int(round(window_s * bs.fs / bs.block_n)))
    if wb * bs.block_n < 2:
        raise ValueError(f"window_s = {window_s} s holds fewer than 2 samples at fs = {bs.fs} Hz")
    if not threshold_g > 0:
        raise ValueError(f"threshold_g must be > 0, got {threshold_g}")
    _, kinv = _to_g_affine(to_g)
    nb = len(bs)
    if nb < wb:
        return np.zeros(nb, dtype=bool)
    ok = bs.usable
    if not ok.any():
        return np.zeros(nb, dtype=bool)
    # relative to the first usable block (precision of the moving sums); unusable blocks count as
    # zero (they only make their windows not still); the running sums keep wb + 1 blocks, not nb
    still = np.empty(nb, dtype=bool)
    variance_chain(np.ascontiguousarray(bs.mean, dtype=np.float64), np.ascontiguousarray(ok),
                   np.ascontiguousarray(bs.scatter, dtype=np.float32),
                   np.ascontiguousarray(bs.mean[:, int(np.argmax(ok))], dtype=np.float64),
                   np.ascontiguousarray(kinv, dtype=np.float64), wb, bs.block_n, float(threshold_g) ** 2, still)
    return still


def windows_from_still(bs: BlockStats, still: np.ndarray, t: np.ndarray, *, min_duration_s: float = 1.0,
                       max_duration_s: float | None = 60.0, guard_s: float = 0.5) -> WindowSet:
    """Windows from still blocks (the rules of core.detectors, in blocks); statistics exact."""
    if min_duration_s < 0 or guard_s < 0:
        raise ValueError("min_duration_s and guard_s must be >= 0")
    B, fs = bs.block_n, bs.fs
    g = int(round(guard_s * fs / B))
    min_b = max(1, int(math.ceil(min_duration_s * fs / B - 1e-9)), int(math.ceil(2 / B)))
    if max_duration_s is None or math.isinf(max_duration_s):
        max_b = len(bs) + 1
    else:
        max_b = max(1, int(round(max_duration_s * fs / B)))
        if max_b < min_b:
            raise ValueError(f"max_duration_s ({max_duration_s} s) is shorter than min_duration_s ({min_duration_s} s)")
    k = bs.aux.shape[0]
    # still runs [lo, hi), eroded by g blocks each side (the recording's ends count as not still):
    # the changes alternate between a run's start and its end (no temporaries of the block count
    # but the comparison)
    nb = still.shape[0]
    change = np.flatnonzero(still[1:] != still[:-1]) + 1
    e = np.concatenate([[0] if nb and still[0] else [], change, [nb] if nb and still[-1] else []]).astype(np.int64)
    lo, hi = e[0::2] + g, e[1::2] - g
    keep = hi - lo >= min_b
    lo, hi = lo[keep], hi[keep]
    # pieces of max_b blocks from each run's first block; a short remainder is dropped
    pieces = np.maximum(0, (hi - lo + max_b - 1) // max_b)
    run = np.repeat(np.arange(lo.shape[0]), pieces)
    within = np.arange(run.shape[0]) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    ps = lo[run] + within * max_b
    pe = np.minimum(ps + max_b, hi[run])
    keep = pe - ps >= min_b
    ps, pe = ps[keep], pe[keep]
    m = ps.shape[0]
    if m == 0:
        return WindowSet(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0), np.zeros(0), np.zeros((0, k)),
                         np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    start, end = ps * B, pe * B
    mean, scat, aux, t_ends = _window_sums_and_times(bs, ps, pe, t, start, end - 1)
    n = (pe - ps).astype(np.int64) * B
    cov = np.empty((m, 3, 3))
    cov[:, _I6, _J6] = scat.T / (n - 1)[:, None]
    cov[:, _J6, _I6] = scat.T / (n - 1)[:, None]
    t_mid = 0.5 * (t_ends[0] + t_ends[1])
    return WindowSet(mean.T.copy(), cov, n.astype(float), t_mid, aux.T.copy(), start.astype(np.int64),
                     end.astype(np.int64))


def _window_sums_and_times(bs: BlockStats, ps: np.ndarray, pe: np.ndarray, t: np.ndarray, first: np.ndarray,
                           last: np.ndarray) -> tuple[np.ndarray, ...]:
    """_window_sums and the times of the windows' first and last samples (float64). With many windows
    the times are gathered on a second thread while the sums' kernel runs (it releases the GIL): in a
    memory-mapped t whose pages the reading pass released, each is a page fault (~4 us)."""
    def gather() -> tuple[np.ndarray, np.ndarray]:
        return _take_released(t, first), _take_released(t, last)

    if first.shape[0] < GATHER_THREAD_MIN:
        return (*_window_sums(bs, ps, pe), gather())
    with ThreadPoolExecutor(1, thread_name_prefix="gravcal-times") as pool:
        times = pool.submit(gather)
        sums = _window_sums(bs, ps, pe)
        return (*sums, times.result())


def _take_released(t: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """t[idx] as float64. From a memory-mapped t, in pieces of GATHER_PIECE whose
    pages are released after: a fault maps the file's pages around the row too (fault-around, up to
    64 kB), and a week's ~24 000 window edges left 0.6x the file resident (RssFile 59 -> 736 MB)."""
    mapped = _mapped_rows(t)
    if mapped is None or idx.shape[0] == 0:
        return np.asarray(t[idx], dtype=float)
    margin = -(-RELEASE_MARGIN_BYTES // max(abs(mapped[2]), 1))  # rows beside a piece that fault-around mapped
    out = np.empty(idx.shape[0])
    for s in range(0, idx.shape[0], GATHER_PIECE):
        part = idx[s:s + GATHER_PIECE]
        out[s:s + part.shape[0]] = t[part]
        release_mapped(t, max(0, int(part.min()) - margin), min(t.shape[0], int(part.max()) + 1 + margin))
    return out


def _window_sums(bs: BlockStats, ps: np.ndarray, pe: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean (3, m), scatter (6, m) and aux mean (k, m) of the samples of block ranges [ps, pe):
    per window, sums of the block means minus the window's first one and of their products,
    Σ (m_b - m)(m_b - m)ᵀ = Σ d dᵀ - (Σ d)(Σ d)ᵀ / n_b for d = m_b - r with any r (one compiled loop)."""
    m, k = ps.shape[0], bs.aux.shape[0]
    mean, scat, aux = np.empty((3, m)), np.empty((6, m)), np.empty((k, m))
    window_sums(np.ascontiguousarray(bs.mean, dtype=np.float64), np.ascontiguousarray(bs.scatter, dtype=np.float32),
                np.ascontiguousarray(bs.aux, dtype=np.float64), np.ascontiguousarray(ps, dtype=np.int64),
                np.ascontiguousarray(pe, dtype=np.int64), bs.block_n, mean, scat, aux)
    return mean, scat, aux


METHODS = ("lotters", "variance")
_WINDOW_KW = ("min_duration_s", "max_duration_s", "guard_s")


def detect_blocks(bs: BlockStats, t: np.ndarray, method: str = "lotters", to_g: Calibration | None = None,
                  **kw: Any) -> WindowSet:
    """Quasi-static windows from block statistics. ``kw``: the streaming detector's keywords
    (threshold_g, guard_s, min/max_duration_s, hp_hz/lp_hz/per_axis/settle_s/order for
    "lotters", window_s for "variance"); ``threads`` is accepted and ignored. Defaults are the
    streaming detectors' (guard_s 0.5 s for lotters, 0.25 s for variance)."""
    if method not in METHODS:
        raise ValueError(f"unknown detector method {method!r}; choose one of {sorted(METHODS)}")
    kw = dict(kw)
    kw.pop("threads", None)
    win = {key: kw.pop(key) for key in _WINDOW_KW if key in kw}
    win.setdefault("guard_s", 0.5 if method == "lotters" else 0.25)
    if method == "lotters":
        still = lotters_still(bs, to_g, **kw)
    else:
        still = variance_still(bs, to_g, **kw)
    return windows_from_still(bs, still, t, **win)


def detect(t: np.ndarray, raw: np.ndarray, *, method: str = "lotters", fs: float | None = None,
           to_g: Calibration | None = None, aux: np.ndarray | None = None, block_s: float = BLOCK_S,
           **kw: Any) -> WindowSet:
    """All quasi-static windows of an in-memory (or memory-mapped) recording t (N,), raw (N, 3):
    the offline counterpart of core.detectors.detect."""


    t = np.asarray(t) if not isinstance(t, np.ndarray) else t
    raw = np.asarray(raw) if not isinstance(raw, np.ndarray) else raw
    if raw.ndim != 2 or raw.shape[1] != 3 or t.shape != (raw.shape[0],):
        raise ValueError(f"t (N,) and raw (N, 3) expected, got t {t.shape} and raw {raw.shape}")
    fs = estimate_fs(t) if fs is None else float(fs)
    bs = block_stats(t, lambda c, i, j: raw[i:j, c], raw.shape[0], fs, aux=aux, block_n=block_length(fs, block_s))
    return detect_blocks(bs, t, method, to_g, **kw)
