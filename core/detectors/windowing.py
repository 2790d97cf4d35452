"""The windowing engine both detectors share: still mask -> eroded in-window runs -> Windows, exact
under any split of the stream into blocks (see the package docstring for the rules)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..accelerator import kernels
from ..calibration import Calibration
from ..windows import Window

sosfilt = kernels("gravcal.core._blockkernels").sosfilt

ToG = Calibration | Callable[[np.ndarray], np.ndarray] | None

# Unique entries of the 3x3 outer product d d^T, accumulated as 6 columns.
_I6 = np.array([0, 1, 2, 0, 0, 1])
_J6 = np.array([0, 1, 2, 1, 2, 2])


def _affine_to_g(cal: Calibration) -> Callable[[np.ndarray], np.ndarray]:
    """raw -> g for a Calibration, written elementwise so that the result of each row does
    not depend on how many rows are converted together (BLAS kernels may differ by size)."""
    m = np.linalg.inv(cal.sensitivity)
    o = cal.offset.copy()
    if np.count_nonzero(m - np.diag(np.diag(m))) == 0:
        inv_s = np.diag(m).copy()

        def to_g(raw: np.ndarray) -> np.ndarray:
            out = raw - o
            out *= inv_s
            return out

        return to_g

    def to_g_full(raw: np.ndarray) -> np.ndarray:
        d = raw - o
        out = d[:, 0:1] * m[:, 0]
        out += d[:, 1:2] * m[:, 1]
        out += d[:, 2:3] * m[:, 2]
        return out

    return to_g_full


def _as_to_g(to_g: ToG) -> Callable[[np.ndarray], np.ndarray]:
    if to_g is None:
        return lambda raw: raw
    if isinstance(to_g, Calibration):
        return _affine_to_g(to_g)
    if callable(to_g):
        return lambda raw: np.asarray(to_g(raw), dtype=float).reshape(raw.shape)
    raise TypeError(f"to_g must be a Calibration, a callable raw -> g, or None (got {type(to_g).__name__})")


def _diagonal_affine(to_g: ToG) -> tuple[np.ndarray, np.ndarray] | None:
    """(offset, 1/diag(sensitivity)) when to_g is a Calibration with a diagonal sensitivity:
    the detector then computes the axes in g straight into its workspace, else None."""
    if not isinstance(to_g, Calibration):
        return None
    m = np.linalg.inv(to_g.sensitivity)
    if np.count_nonzero(m - np.diag(np.diag(m))):
        return None
    return to_g.offset.copy(), np.diag(m).copy()


def _filter_rows(sos_hp, sos_lp, v, zi_hp, zi_lp) -> None:
    sosfilt(sos_hp, v, zi_hp)
    np.abs(v, out=v)
    sosfilt(sos_lp, v, zi_lp)  # eq. 2


def _forward_fill(values: np.ndarray, ok: np.ndarray, carry: np.ndarray) -> np.ndarray:
    """Replace rows where ``ok`` is False by the last good row (``carry`` before the block)."""
    idx = np.where(ok, np.arange(1, ok.shape[0] + 1), 0)
    np.maximum.accumulate(idx, out=idx)
    ext = np.concatenate([carry.reshape((1,) + values.shape[1:]), values])
    return ext[idx]


class _Rows:
    """The samples decided by a block, addressed by global sample index from ``d0``: the
    previous block's undecided tail followed by the block, channel-major (raw (3, n), aux
    (k, n), t (n,)), concatenated only where a requested range straddles the two."""

    def __init__(self, p_raw, p_aux, p_t, raw, aux, t, d0: int):
        self._p = (p_raw, p_aux, p_t)
        self._b = (raw, aux, t)
        self.d0, self.np = d0, p_t.shape[0]

    def _get(self, k: int, lo: int, hi: int) -> np.ndarray:
        i, j, P = lo - self.d0, hi - self.d0, self.np
        if j <= P:
            return self._p[k][..., i:j]
        if i >= P:
            return self._b[k][..., i - P:j - P]
        return np.concatenate([self._p[k][..., i:], self._b[k][..., :j - P]], axis=-1)

    def raw(self, lo: int, hi: int) -> np.ndarray:
        return self._get(0, lo, hi)

    def aux(self, lo: int, hi: int) -> np.ndarray:
        return self._get(1, lo, hi)

    def t(self, lo: int, hi: int) -> np.ndarray:
        return self._get(2, lo, hi)

    def t_at(self, i: int) -> float:
        i -= self.d0
        return float(self._p[2][i] if i < self.np else self._b[2][i - self.np])

    def sums(self, ps: np.ndarray, pe: np.ndarray, ref0: np.ndarray | None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per part [ps, pe): its reference ``ref`` (q, 3) = its first sample (``ref0`` for the
        first part when given: a continued window keeps its own), sums of (x - ref) (q, 3), of
        their products (q, 6: _I6/_J6) and of aux (q, k)."""
        q = ps.shape[0]
        k = self._b[1].shape[0]
        refs, s1, s2, sa = np.empty((q, 3)), np.empty((q, 3)), np.empty((q, 6)), np.empty((q, k))
        lens = pe - ps
        if q <= 2 or int(lens.sum()) >= _LOOP_MIN_MEAN_PART * q:
            for j in range(q):  # long parts: contiguous rows, one dot product per sum
                lo, hi = int(ps[j]), int(pe[j])
                x = self.raw(lo, hi)
                refs[j] = ref0 if j == 0 and ref0 is not None else x[:, 0]
                d = x - refs[j][:, None]
                s1[j] = d.sum(axis=1)
                for c in range(6):
                    s2[j, c] = np.dot(d[_I6[c]], d[_J6[c]])
                sa[j] = self.aux(lo, hi).sum(axis=1)
            return refs, s1, s2, sa
        # many short parts: sums over the span at once, shifted by one reference r_b and cut
        # at [lo, hi) pairs by reduceat (the odd results, between parts, are unused), then
        # re-referenced to each part's own ref (exact algebra)
        base, top = int(ps[0]), int(pe[-1])
        span = self.raw(base, top)
        m = span.shape[1]
        refs[:] = span[:, ps - base].T
        if ref0 is not None:
            refs[0] = ref0
        r_b = refs[0]
        rows = np.empty((9, m + 1))
        rows[:, m] = 0.0
        d = rows[:3, :m]
        np.subtract(span, r_b[:, None], out=d)
        with np.errstate(invalid="ignore", over="ignore"):  # NaN/inf samples lie between parts only
            for c in range(6):  # explicit rows: fancy-indexed temporaries cost more than the products
                np.multiply(d[_I6[c]], d[_J6[c]], out=rows[3 + c, :m])
            cuts = np.empty(2 * q, dtype=np.int64)
            cuts[0::2], cuts[1::2] = ps - base, pe - base
            sums = np.add.reduceat(rows, cuts, axis=1)[:, 0::2].T  # (q, 9)
            if k:
                aux_rows = np.zeros((k, m + 1))
                aux_rows[:, :m] = self.aux(base, top)
                sa[:] = np.add.reduceat(aux_rows, cuts, axis=1)[:, 0::2].T
        delta = refs - r_b
        n = lens.astype(float)[:, None]
        b1 = sums[:, :3]
        s1[:] = b1 - n * delta
        s2[:] = (sums[:, 3:] - delta[:, _I6] * b1[:, _J6] - delta[:, _J6] * b1[:, _I6]
                 + n * delta[:, _I6] * delta[:, _J6])
        return refs, s1, s2, sa


@dataclass
class _OpenWindow:
    """Running sums of the window being accumulated (shifted by ``ref``, its first sample,
    so that raw counts of ~3e4 with a noise of a few counts keep their precision)."""

    ws: int  # global index of its first sample (also its identity)
    n: int  # samples accumulated so far (the window is contiguous: ws .. ws + n - 1)
    ref: np.ndarray  # (3,)
    s1: np.ndarray  # (3,) sum of (x - ref)
    s2: np.ndarray  # (6,) sums of products of (x - ref), entries _I6/_J6
    aux_sum: np.ndarray  # (k,)
    t_first: float
    t_last: float


# Parts of windows at least this long on average get their sums by one matrix product each
# (a Python step per part); shorter ones are summed all at once with np.add.reduceat.
_LOOP_MIN_MEAN_PART = 512
_NO_END = np.iinfo(np.int64).max // 4  # "still run not ended yet"
_DETECT_BLOCK = 1 << 16  # samples per update() in detect()
_THREAD_MIN_BLOCK = 8192  # samples: below this a thread hand-off costs more than it saves
_KEEP_WORKSPACE = 1 << 18  # samples: larger blocks get a temporary workspace, not a kept one


class _Windower:
    """Turns per-sample still flags into Windows (erosion, max/min duration, statistics).

    Works on runs, not samples: a still run [lo, hi) (global sample indices) holds the
    in-window samples [lo + guard, hi - guard); those are cut into pieces of max_n samples
    counted from the first; a piece is emitted once its last sample is decided (``guard``
    samples after it arrived). Only the runs and pieces touched by a block cost Python
    steps; the samples themselves are handled by numpy.
    """

    def __init__(self, fs: float, *, min_duration_s: float, max_duration_s: float | None, guard_s: float):
        if not (fs > 0 and math.isfinite(fs)):
            raise ValueError(f"sample rate fs must be a positive number of Hz, got {fs!r}")
        if min_duration_s < 0 or guard_s < 0:
            raise ValueError("min_duration_s and guard_s must be >= 0")
        self.fs = float(fs)
        self.guard = int(round(guard_s * fs))
        self.min_n = max(2, int(math.ceil(min_duration_s * fs - 1e-9)))  # a covariance needs 2 samples
        if max_duration_s is None or math.isinf(max_duration_s):
            self.max_n = _NO_END
        else:
            self.max_n = int(round(max_duration_s * fs))
            if self.max_n < self.min_n:
                raise ValueError(f"max_duration_s ({max_duration_s} s) is shorter than min_duration_s ({min_duration_s} s)")
        self._reset_windower()

    def _reset_windower(self) -> None:
        self.n_seen = 0  # global index of the next sample
        self._run_lo = -1  # first sample of the still run that includes the last sample seen (-1: not still)
        self._k: int | None = None  # number of aux channels, fixed by the first block
        # the samples not decided yet (the last `guard` ones): [n_seen - len, n_seen)
        self._pend_raw = np.zeros((3, 0))  # channel-major
        self._pend_aux = np.zeros((0, 0))
        self._pend_t = np.zeros(0)
        self._open: _OpenWindow | None = None
        self.counts = {"samples": 0, "nonfinite": 0, "gaps": 0, "windows": 0, "short_dropped": 0}

    # -- the engine ----------------------------------------------------------------------
    def _windows_from_still(self, t: np.ndarray, raw: np.ndarray, aux: np.ndarray, still: np.ndarray) -> list[Window]:
        """t (n,), raw (3, n) and aux (k, n) channel-major (rows contiguous), still (n,) bool."""
        n = still.shape[0]
        g = self.guard
        j0 = self.n_seen
        j1 = self.n_seen = j0 + n
        d0, d1 = max(0, j0 - g), max(0, j1 - g)  # samples [d0, d1) are decided by this block
        src = _Rows(self._pend_raw, self._pend_aux, self._pend_t, raw, aux, t, d0)
        keep = j1 - d1  # the new undecided tail
        if keep == 0:
            self._pend_raw, self._pend_aux, self._pend_t = raw[:, :0], aux[:, :0], t[:0]
        elif n >= keep:
            self._pend_raw, self._pend_aux, self._pend_t = (raw[:, n - keep:].copy(), aux[:, n - keep:].copy(),
                                                            t[n - keep:].copy())
        else:
            self._pend_raw, self._pend_aux, self._pend_t = (src.raw(j1 - keep, j1).copy(), src.aux(j1 - keep, j1).copy(),
                                                            src.t(j1 - keep, j1).copy())
        if n == 0:
            return []

        # still runs of the block: [lo, hi) global; the last one is open when the block ends still
        n_still = int(np.count_nonzero(still))
        if n_still == 0:
            lo, hi = [], []
        elif n_still == n:
            lo, hi = [j0], [j1]
        else:
            e = np.flatnonzero(still[1:] != still[:-1]) + 1
            starts, ends = (e[1::2], e[0::2]) if still[0] else (e[0::2], e[1::2])
            if still[0]:
                starts = np.concatenate([[0], starts])
            if still[-1]:
                ends = np.concatenate([ends, [n]])
            if starts.shape[0] > 8:  # only runs longer than 2 guards hold window samples (and the ends)
                keep_run = ends - starts > 2 * g
                keep_run[0] = keep_run[-1] = True
                starts, ends = starts[keep_run], ends[keep_run]
            lo, hi = (starts + j0).tolist(), (ends + j0).tolist()
        if lo and lo[0] == j0 and self._run_lo >= 0:
            lo[0] = self._run_lo
        open_last = bool(still[-1])
        self._run_lo = lo[-1] if open_last else -1

        # in-window samples decided now, [x0, x1) of each run's eroded interval [lo + g, hi - g),
        # cut into pieces of max_n samples from its first: part [ps, pe) of piece [p, p + max_n)
        m = self.max_n
        parts = []  # (p, ps, pe, complete: the piece's last sample is decided)
        last = len(lo) - 1
        for r in range(len(lo)):
            a = lo[r] + g
            still_open = open_last and r == last
            x0, x1 = max(a, d0), (d1 if still_open else min(hi[r] - g, d1))
            if x1 <= x0:
                continue
            p = a + (x0 - a) // m * m
            while p < x1:
                q = p + m
                pe = min(q, x1)
                parts.append((p, max(p, x0), pe, pe == q or not still_open))
                p = q
        done: list[_OpenWindow] = []
        cont = bool(parts) and self._open is not None and parts[0][0] == self._open.ws
        if not cont:  # the open window is complete once a decided sample follows it
            if self._open is not None and self._open.ws + self._open.n < d1:
                done.append(self._open)
                self._open = None
        # complete pieces below min_n are dropped without sums
        short = [complete and pe - p < self.min_n for p, _, pe, complete in parts]
        if any(short):
            self.counts["short_dropped"] += sum(short)
            if cont and short[0]:
                self._open, cont = None, False
            parts = [x for x, s in zip(parts, short) if not s]
        if not parts:
            return self._emit(done)
        ps = np.array([x[1] for x in parts], dtype=np.int64)
        pe = np.array([x[2] for x in parts], dtype=np.int64)
        # a new piece's first part starts at the piece's first sample: its reference
        refs, s1, s2, sa = src.sums(ps, pe, self._open.ref if cont else None)
        for j, (p, a, b, complete) in enumerate(parts):
            w = _OpenWindow(p, b - a, refs[j], s1[j], s2[j], sa[j], src.t_at(a), src.t_at(b - 1))
            if j == 0 and cont:
                o = self._open
                w = _OpenWindow(o.ws, o.n + w.n, o.ref, o.s1 + w.s1, o.s2 + w.s2, o.aux_sum + w.aux_sum,
                                o.t_first, w.t_last)
                self._open = None
            if complete:
                done.append(w)
            else:
                self._open = w  # only the last part can be incomplete
        return self._emit(done)

    def _emit(self, done: list[_OpenWindow]) -> list[Window]:
        out = []
        for w in done:
            if w.n < self.min_n:
                self.counts["short_dropped"] += 1
                continue
            cov = np.empty((3, 3))
            prod = w.s2 - w.s1[_I6] * w.s1[_J6] / w.n
            cov[_I6, _J6] = prod
            cov[_J6, _I6] = prod
            out.append(Window(start=w.ws, end=w.ws + w.n, t_start=w.t_first, t_end=w.t_last,
                              mean=w.ref + w.s1 / w.n, cov=cov / (w.n - 1), aux_mean=w.aux_sum / w.n))
        self.counts["windows"] += len(out)
        return out

    def _flush_windower(self) -> list[Window]:
        done = [self._open] if self._open is not None else []
        self._open = None
        return self._emit(done)

    # -- input checking shared by the detectors --------------------------------------------
    def _check_block(self, t, raw, aux) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        raw = np.asarray(raw, dtype=float)
        if raw.ndim != 2 or raw.shape[1] != 3:
            raise ValueError(f"raw must have shape (N, 3), got {raw.shape}")
        n = raw.shape[0]
        t = np.asarray(t, dtype=float).reshape(-1)
        if t.shape[0] != n:
            raise ValueError(f"t has {t.shape[0]} samples but raw has {n}")
        if aux is None:
            aux = np.zeros((n, 0 if self._k is None else self._k))
        aux = np.asarray(aux, dtype=float)
        if aux.ndim == 1:
            aux = aux[:, None]
        if aux.shape[0] != n:
            raise ValueError(f"aux has {aux.shape[0]} rows but raw has {n}")
        if self._k is None:
            self._k = aux.shape[1]
            self._pend_aux = np.zeros((self._k, 0))
        elif aux.shape[1] != self._k:
            raise ValueError(f"aux has {aux.shape[1]} channels, earlier blocks had {self._k}")
        # aux channels do not decide whether a sample is usable: a recording without a temperature but with a
        # supply voltage carries NaN in the temperature column, and a window's NaN aux mean says "not measured"
        with np.errstate(over="ignore", invalid="ignore"):  # a finite sum proves every entry finite
            fine = np.isfinite(raw.sum()) and np.isfinite(t.sum())
        if fine:
            return t, raw, aux, None  # ok = None: every sample is finite
        return t, raw, aux, _finite_rows(raw) & np.isfinite(t)

    def _count_block(self, t: np.ndarray, ok: np.ndarray | None) -> np.ndarray | None:
        """Count the block's samples and those not usable (``ok`` False); the gap before each sample
        (``_gaps``)."""
        n = t.shape[0]
        self.counts["samples"] += n
        if ok is not None:
            self.counts["nonfinite"] += int(n - np.count_nonzero(ok))
        return self._gaps(t, ok)

    def _still_windows(self, t: np.ndarray, raw: np.ndarray, aux: np.ndarray, still: np.ndarray,
                       ok: np.ndarray | None, gap: np.ndarray | None, j0: int, start: int | None,
                       settle_n: int) -> list[Window]:
        """The windows a block (first sample j0) completes: ``still``, the detector's verdict per sample
        (cleared in place), holds only at usable samples with no gap before them, from ``settle_n`` samples
        after the detector's first usable sample ``start`` on."""
        if ok is not None:
            still &= ok
        if gap is not None:
            still &= ~gap
        _unsettled(still, j0, start, settle_n)
        return self._windows_from_still(t, *_channel_major(raw, aux), still)

    def _gaps(self, t: np.ndarray, ok: np.ndarray | None) -> np.ndarray | None:
        """gap_before[i]: time jumped by more than 1.5/fs (a dropout) or did not increase.
        None when there is no gap (the common case: one diff, one min and one max)."""
        n = t.shape[0]
        if ok is None and n:  # t all finite
            step = 1.5 / self.fs
            first = t[0] - self._last_t
            if not (math.isfinite(first) and not (first > 0 and first <= step)):  # NaN: stream start
                dt = t[1:] - t[:-1]
                if n == 1 or (dt.min() > 0 and dt.max() <= step):
                    self._last_t = float(t[-1])
                    return None
        t_ok = np.isfinite(t)
        tf = t if t_ok.all() else _forward_fill(t, t_ok, np.asarray(self._last_t))
        prev_t = np.concatenate([[self._last_t], tf[:-1]])
        dt = tf - prev_t
        with np.errstate(invalid="ignore"):
            gap = np.isfinite(prev_t) & ~((dt > 0) & (dt <= 1.5 / self.fs))
        if t.shape[0]:
            self._last_t = float(tf[-1])
        self.counts["gaps"] += int(np.count_nonzero(gap if ok is None else gap & ok))
        return gap

    def stats(self) -> dict[str, int]:
        """Counters since the last reset: samples, nonfinite (rejected samples), gaps,
        windows (emitted), short_dropped (still runs or remainders below min_duration_s)."""
        return dict(self.counts)


def _channel_major(raw: np.ndarray, aux: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """raw (n, 3) -> (3, n) and aux (n, k) -> (k, n) with contiguous rows (views when the input
    is already in Fortran order, e.g. columns read straight from a file)."""
    r = raw.T if raw.T.flags.c_contiguous else np.ascontiguousarray(raw.T)
    a = aux.T if aux.T.flags.c_contiguous else np.ascontiguousarray(aux.T)
    return r, a


def _finite_rows(a: np.ndarray) -> np.ndarray:
    """Rows of (N, k) whose entries are all finite (a column sum is NaN/inf otherwise;
    rows so large that the sum overflows count as non-finite too, harmlessly)."""
    with np.errstate(invalid="ignore", over="ignore"):
        return np.isfinite(a.sum(axis=1) if a.shape[1] != 3 else a[:, 0] + a[:, 1] + a[:, 2])


def _unsettled(still: np.ndarray, j0: int, start: int | None, settle_n: int) -> None:
    """Clear ``still`` for samples before ``start + settle_n`` (block starting at global j0)."""
    if start is None:
        still[:] = False
    else:
        still[:max(0, start + settle_n - j0)] = False


def settle_samples(sos: np.ndarray, final: float, fs: float, corner_hz: float, tol: float = 0.01) -> int:
    """Samples after which the filter's unit-step response stays within ``tol`` of ``final``."""
    n = int(round(20.0 / corner_hz * fs))
    y = np.ones((1, n))
    sosfilt(np.ascontiguousarray(sos, dtype=np.float64), y, np.zeros((1, sos.shape[0], 2)))
    y = y[0]
    bad = np.flatnonzero(np.abs(y - final) > tol)
    return int(bad[-1] + 1) if bad.shape[0] else 0
