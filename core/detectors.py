"""Streaming quasi-static detectors: raw triad samples in, quasi-static Windows out.

Two detectors share one windowing engine (:class:`_Windower`):

- :class:`QuasiStaticDetector` — Lötters et al. 1998, section 2: the modulus of the triad
  (eq. 1) goes through a 0.5 Hz high-pass filter, a rectifier and a 0.5 Hz low-pass filter
  (eq. 2); a sample is quasi-static when that detection signal is below a threshold.
- :class:`MovingVarianceDetector` — per-axis moving variance over a trailing window; a
  sample is quasi-static when every axis's moving standard deviation is below a threshold.

Both take raw samples (N, 3) in any units. The detection signal is computed on
``to_g(raw)`` (a :class:`~gravcal.core.calibration.Calibration`, a callable raw -> g, or
identity when None), so thresholds are in g — or in raw units when ``to_g`` is None.
Window means and covariances are always of the RAW samples: the estimators work in raw units.

Windowing rules (identical for both detectors):

- a sample is *still* when it is finite (raw, time and aux), its detection signal is below
  the threshold, the filters have settled since the first finite sample, and it does not
  follow a time gap (a jump larger than 1.5/fs, or time not increasing);
- a sample is *in a window* when every sample within ``guard_s`` of it is still (erosion of
  the still mask; the detection signal lags the motion, so the edges of a still period are
  trimmed). The stream's end counts as not still, so flush() trims the last guard too;
- a run of in-window samples is cut into consecutive windows of ``max_duration_s``
  counted from the run's first sample (so a 3-hour pose yields many windows); windows
  shorter than ``min_duration_s`` (including a short remainder) are dropped.

Streaming is exact: every decision is a function of the sample stream alone, never of how
it was split into blocks. Filter states (sosfilt ``zi``) and running sums (np.cumsum
with the carried sum prepended) evaluate the same floating-point operations in the same
order for any split, so window boundaries are bit-identical; window means/covariances are
accumulated per block with np.add.reduceat and agree to rounding (~1e-15 relative).
A sample is decided ``guard`` samples after it arrives (the erosion looks ahead).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy import signal

from .calibration import Calibration
from .windows import Window, WindowSet

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


def _forward_fill(values: np.ndarray, ok: np.ndarray, carry: np.ndarray) -> np.ndarray:
    """Replace rows where ``ok`` is False by the last good row (``carry`` before the block)."""
    idx = np.where(ok, np.arange(1, ok.shape[0] + 1), 0)
    np.maximum.accumulate(idx, out=idx)
    ext = np.concatenate([carry.reshape((1,) + values.shape[1:]), values])
    return ext[idx]


@dataclass
class _OpenWindow:
    """Running sums of the window being accumulated (shifted by ``ref``, its first sample,
    so that raw counts of ~3e4 with a noise of a few counts keep their precision)."""

    ws: int  # global index of its first sample (also its identity)
    last: int  # global index of its last sample so far
    n: int
    ref: np.ndarray  # (3,)
    s1: np.ndarray  # (3,) sum of (x - ref)
    s2: np.ndarray  # (6,) sums of products of (x - ref), entries _I6/_J6
    aux_sum: np.ndarray  # (k,)
    t_first: float
    t_last: float


class _Windower:
    """Turns per-sample still flags into Windows (erosion, max/min duration, statistics)."""

    def __init__(self, fs: float, *, min_duration_s: float, max_duration_s: float | None, guard_s: float):
        if not (fs > 0 and math.isfinite(fs)):
            raise ValueError(f"sample rate fs must be a positive number of Hz, got {fs!r}")
        if min_duration_s < 0 or guard_s < 0:
            raise ValueError("min_duration_s and guard_s must be >= 0")
        self.fs = float(fs)
        self.guard = int(round(guard_s * fs))
        self.min_n = max(2, int(math.ceil(min_duration_s * fs - 1e-9)))  # a covariance needs 2 samples
        if max_duration_s is None or math.isinf(max_duration_s):
            self.max_n = np.iinfo(np.int64).max // 4
        else:
            self.max_n = int(round(max_duration_s * fs))
            if self.max_n < self.min_n:
                raise ValueError(f"max_duration_s ({max_duration_s} s) is shorter than min_duration_s ({min_duration_s} s)")
        self._reset_windower()

    def _reset_windower(self) -> None:
        self.n_seen = 0  # global index of the next sample
        self._c = 0  # length of the still run ending at the last sample seen
        self._k: int | None = None  # number of aux channels, fixed by the first block
        self._pend_raw = np.zeros((0, 3))
        self._pend_aux = np.zeros((0, 0))
        self._pend_t = np.zeros(0)
        self._prev_in = False  # was the last decided sample in a window?
        self._rs = -1  # first sample of the current in-window run
        self._open: _OpenWindow | None = None
        self.counts = {"samples": 0, "nonfinite": 0, "gaps": 0, "windows": 0, "short_dropped": 0}

    # -- the engine ----------------------------------------------------------------------
    def _windows_from_still(self, t: np.ndarray, raw: np.ndarray, aux: np.ndarray, still: np.ndarray) -> list[Window]:
        n = still.shape[0]
        g = self.guard
        j0 = self.n_seen
        # run length of still samples ending at each sample; "last not-still" index carried
        idx = np.arange(j0, j0 + n, dtype=np.int64)
        last_false = np.where(still, j0 - 1 - self._c, idx)
        np.maximum.accumulate(last_false, out=last_false)
        c = idx - last_false
        if n:
            self._c = int(c[-1])
        self.n_seen += n

        # samples are decided g samples late: in_window[i] <=> still[i-g .. i+g] <=> c[i+g] >= 2g+1
        raw_c = np.concatenate([self._pend_raw, raw]) if self._pend_raw.shape[0] else raw
        aux_c = np.concatenate([self._pend_aux, aux]) if self._pend_aux.shape[0] else aux
        t_c = np.concatenate([self._pend_t, t]) if self._pend_t.shape[0] else t
        first = j0 - self._pend_raw.shape[0]
        nd = max(0, raw_c.shape[0] - g)
        self._pend_raw, self._pend_aux, self._pend_t = raw_c[nd:], aux_c[nd:], t_c[nd:]
        if nd == 0:
            return []
        dec = np.arange(first, first + nd, dtype=np.int64)
        inw = c[dec + g - j0] >= 2 * g + 1
        return self._accumulate(dec, inw, raw_c[:nd], aux_c[:nd], t_c[:nd])

    def _accumulate(self, dec, inw, raw, aux, t) -> list[Window]:
        """Add the decided samples ``dec`` (global indices) with in-window flags ``inw``."""
        prev = np.concatenate([[self._prev_in], inw[:-1]])
        run_start = np.where(inw & ~prev, dec, -1)
        if run_start.shape[0]:
            run_start[0] = max(run_start[0], self._rs if inw[0] and self._prev_in else -1)
        np.maximum.accumulate(run_start, out=run_start)
        self._prev_in = bool(inw[-1])
        self._rs = int(run_start[-1]) if self._prev_in else -1

        pos = np.flatnonzero(inw)
        done: list[_OpenWindow] = []
        if pos.shape[0] == 0:
            if self._open is not None:  # a decided sample that is not in it has arrived
                done.append(self._open)
                self._open = None
            return self._emit(done)

        gi = dec[pos]
        rs = run_start[pos]
        ws = rs + ((gi - rs) // self.max_n) * self.max_n  # window = piece of max_n samples of its run
        seg = np.flatnonzero(np.diff(ws)) + 1
        seg_start = np.concatenate([[0], seg])
        seg_len = np.diff(np.concatenate([seg_start, [pos.shape[0]]]))
        seg_ws = ws[seg_start]
        seg_last = seg_start + seg_len - 1
        lo, hi = pos[seg_start], pos[seg_last] + 1  # each segment is contiguous in the decided samples

        # Sums over all decided samples (no gather), shifted by one block reference r_b and
        # cut at [lo, hi) pairs by reduceat; the odd results (between segments) are unused.
        m = raw.shape[0]
        r_b = raw[pos[0]].copy()
        rows = np.empty((9, m + 1))
        rows[:, m] = 0.0
        d = rows[:3, :m]
        np.subtract(raw.T, r_b[:, None], out=d)
        for k in range(6):  # explicit rows: fancy-indexed temporaries cost more than the products
            np.multiply(d[_I6[k]], d[_J6[k]], out=rows[3 + k, :m])
        cuts = np.empty(2 * lo.shape[0], dtype=np.int64)
        cuts[0::2], cuts[1::2] = lo, hi
        with np.errstate(invalid="ignore"):  # NaN samples lie between segments only
            sums = np.add.reduceat(rows, cuts, axis=1)[:, 0::2].T  # (segments, 9)
        if aux.shape[1]:
            aux_rows = np.empty((aux.shape[1], m + 1))
            aux_rows[:, :m] = aux.T
            aux_rows[:, m] = 0.0
            with np.errstate(invalid="ignore"):
                aux_s = np.add.reduceat(aux_rows, cuts, axis=1)[:, 0::2].T
        else:
            aux_s = np.zeros((lo.shape[0], 0))

        # re-reference each segment's sums to its window's first sample (exact algebra)
        cont = self._open is not None and seg_ws[0] == self._open.ws
        ref = raw[lo].copy()
        if cont:
            ref[0] = self._open.ref
        delta = ref - r_b
        n_seg = seg_len.astype(float)
        b1 = sums[:, :3]
        s1 = b1 - n_seg[:, None] * delta
        s2 = (sums[:, 3:] - delta[:, _I6] * b1[:, _J6] - delta[:, _J6] * b1[:, _I6]
              + n_seg[:, None] * delta[:, _I6] * delta[:, _J6])
        segs = [
            _OpenWindow(int(seg_ws[k]), int(gi[seg_last[k]]), int(seg_len[k]), ref[k], s1[k], s2[k], aux_s[k],
                        float(t[lo[k]]), float(t[hi[k] - 1]))
            for k in range(seg_start.shape[0])
        ]
        if cont:
            o, s = self._open, segs[0]
            segs[0] = _OpenWindow(o.ws, s.last, o.n + s.n, o.ref, o.s1 + s.s1, o.s2 + s.s2, o.aux_sum + s.aux_sum,
                                  o.t_first, s.t_last)
        elif self._open is not None:
            done.append(self._open)
        self._open = None
        done.extend(segs[:-1])
        last = segs[-1]
        if last.n >= self.max_n or dec[-1] > last.last:
            done.append(last)
        else:
            self._open = last
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
            out.append(Window(start=w.ws, end=w.last + 1, t_start=w.t_first, t_end=w.t_last,
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
            self._pend_aux = np.zeros((0, self._k))
        elif aux.shape[1] != self._k:
            raise ValueError(f"aux has {aux.shape[1]} channels, earlier blocks had {self._k}")
        ok = _finite_rows(raw) & np.isfinite(t)
        if aux.shape[1]:
            ok &= _finite_rows(aux)
        return t, raw, aux, ok

    def _gaps(self, t: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """gap_before[i]: time jumped by more than 1.5/fs (a dropout) or did not increase."""
        t_ok = np.isfinite(t)
        tf = t if t_ok.all() else _forward_fill(t, t_ok, np.asarray(self._last_t))
        prev_t = np.concatenate([[self._last_t], tf[:-1]])
        dt = tf - prev_t
        with np.errstate(invalid="ignore"):
            gap = np.isfinite(prev_t) & ~((dt > 0) & (dt <= 1.5 / self.fs))
        if t.shape[0]:
            self._last_t = float(tf[-1])
        self.counts["gaps"] += int(np.count_nonzero(gap & ok))
        return gap

    def stats(self) -> dict[str, int]:
        """Counters since the last reset: samples, nonfinite (rejected samples), gaps,
        windows (emitted), short_dropped (still runs or remainders below min_duration_s)."""
        return dict(self.counts)


class QuasiStaticDetector(_Windower):
    """Lötters' quasi-static moments detector (1998, section 2, eq. 1-2), streaming.

    detection = LPF(|HPF(|to_g(raw)|)|): Butterworth high-pass at ``hp_hz`` and low-pass at
    ``lp_hz`` (second-order sections, state carried across blocks). A sample is still when
    detection < ``threshold_g``.

    Threshold. The paper compares the detector output with T_v = 0.40 V, found
    experimentally for its ICSensors 3021 triad and amplifier chain. In g that is
    T_g = T_v / S_chain with S_chain [V/g] the sensitivity of the voltage the detector saw
    (eq. 1 composes output voltages), which the paper does not report: the number does not
    transfer, only its role does — above the detector's output at rest, below ordinary
    movement. So the default is derived for our sensor instead:

    - at rest the norm carries the ADXL210 noise, ~500 µg/√Hz; over the ~50 Hz output
      bandwidth of a 100 Hz logger that is σ ≈ 500e-6·√(1.57·50) ≈ 4.5 mg rms (duty-cycle
      timer quantisation adds a few mg more). The 0.5 Hz high-pass passes nearly all of it,
      the rectifier gives its mean absolute value √(2/π)·σ ≈ 3.6 mg, and the 0.5 Hz
      low-pass leaves fluctuations of ≈ 0.6σ·√(0.56 Hz / 50 Hz) ≈ 0.3 mg: the output at
      rest is ≈ 4 ± 0.3 mg;
    - body sway while standing or sitting mainly tilts the sensor, which leaves the norm
      unchanged; its linear acceleration (mm at 0.2-0.5 Hz) is ~2 mg, and a residual
      oscillation of amplitude A biases the window's norm only by ~A²/2 (0.2 mg at 20 mg);
    - walking modulates the norm by 0.2-0.5 g, slow daily-living movements by ≥ 50 mg.

    ``threshold_g = 0.02`` (20 mg) sits 5× above the rest level (≈ 50 of its fluctuation
    σ, so noise never breaks a still period), and ≥ 2.5× below slow movement. With
    ``to_g=None`` the threshold is in the raw units.

    Rotation. Once ``to_g`` is a good calibration the norm is 1 g in every orientation, so
    eq. 1 cannot see a slow turn from one posture to the next (the paper ran the detector
    on uncalibrated voltages, whose offsets make the norm orientation-dependent). With
    ``per_axis=True`` (default) the same HPF → rectifier → LPF chain also runs on each
    axis of to_g(raw) and the detection signal is the largest of the four; a 90° turn in
    3 s gives ≈ 0.1 g on the axes. ``per_axis=False`` is the paper's detector exactly.
    On a simulated six-position recording with the true calibration as to_g, the norm
    alone merged turns into windows (window |mean| off 1 g by 0.55 g rms); per-axis
    removed that. Turns slower than ~1°/s pass both detectors: keep max_duration_s short.

    Start-up: the high-pass state starts at steady state for the first finite sample; the
    first ``settle_s`` seconds (default: the time both filters' step responses need to
    settle within 1 %, ≈ 4.7 s at 0.5 Hz) are never still. Non-finite samples are held
    at the last finite norm for the filters and are never still. ``guard_s`` (default
    0.5 s: the delay for the detection signal of a 0.05 g movement to cross 20 mg) trims
    both edges of every still period.
    """

    def __init__(self, fs: float, *, hp_hz: float = 0.5, lp_hz: float = 0.5, threshold_g: float = 0.02,
                 min_duration_s: float = 1.0, max_duration_s: float | None = 60.0, guard_s: float = 0.5,
                 settle_s: float | None = None, order: int = 2, per_axis: bool = True, to_g: ToG = None):
        super().__init__(fs, min_duration_s=min_duration_s, max_duration_s=max_duration_s, guard_s=guard_s)
        self.per_axis = bool(per_axis)
        self._channels = 4 if per_axis else 1
        nyq = 0.5 * fs
        if not (0 < hp_hz < nyq and 0 < lp_hz < nyq):
            raise ValueError(f"filter corners must lie in (0, fs/2 = {nyq} Hz), got hp={hp_hz}, lp={lp_hz}")
        if not threshold_g > 0:
            raise ValueError(f"threshold_g must be > 0, got {threshold_g}")
        self.hp_hz, self.lp_hz, self.threshold_g = hp_hz, lp_hz, float(threshold_g)
        self.sos_hp = signal.butter(order, hp_hz, "highpass", fs=fs, output="sos")
        self.sos_lp = signal.butter(order, lp_hz, "lowpass", fs=fs, output="sos")
        self.settle_n = (int(round(settle_s * fs)) if settle_s is not None
                         else _settle_samples(self.sos_hp, 0.0, fs, hp_hz) + _settle_samples(self.sos_lp, 1.0, fs, lp_hz))
        self.to_g = to_g
        self.reset()

    @property
    def to_g(self) -> ToG:
        return self._to_g_src

    @to_g.setter
    def to_g(self, value: ToG) -> None:
        """Change the raw -> g map (e.g. after a new calibration). The filters see a step
        if the norm changes: that reads as movement for a moment (conservative)."""
        self._to_g = _as_to_g(value)
        self._to_g_src = value

    def reset(self) -> None:
        """Forget the stream: filters, pending samples, the open window, counters."""
        self._reset_windower()
        self._zi_hp: np.ndarray | None = None  # None until the first finite sample
        self._zi_lp = np.zeros((self.sos_lp.shape[0], self._channels, 2))
        self._last_u = np.full(self._channels, np.nan)
        self._start: int | None = None  # global index of the first finite sample
        self._last_t = np.nan
        self.last_detection = np.zeros(0)  # detection signal of the last block [g], for plots

    def update(self, t, raw, aux=None) -> list[Window]:
        """Feed a block: t (N,) [s], raw (N, 3) [raw units], aux (N, k) optional.
        Returns the windows completed by this block (any N >= 0)."""
        t, raw, aux, ok = self._check_block(t, raw, aux)
        n = raw.shape[0]
        j0 = self.n_seen
        self.counts["samples"] += n
        x = self._to_g(raw)
        with np.errstate(invalid="ignore", over="ignore"):
            norm = np.sqrt(x[:, 0] * x[:, 0] + x[:, 1] * x[:, 1] + x[:, 2] * x[:, 2])  # eq. 1
        ok &= np.isfinite(norm)
        self.counts["nonfinite"] += int(n - np.count_nonzero(ok))
        gap = self._gaps(t, ok)

        u = np.empty((self._channels, n))  # channel 0: the norm (eq. 1); 1-3: the axes (per_axis)
        u[0] = norm
        if self.per_axis:
            u[1:] = x.T
        det = np.full(n, np.inf)
        begin = 0
        if self._zi_hp is None and n:
            good = np.flatnonzero(ok)
            if good.shape[0]:
                begin = int(good[0])
                self._start = j0 + begin
                self._zi_hp = signal.sosfilt_zi(self.sos_hp)[:, None, :] * u[None, :, begin, None]
                self._last_u = u[:, begin].copy()
        if self._zi_hp is not None and begin < n:
            u = u[:, begin:]
            if not ok[begin:].all():
                u = _forward_fill(u.T, ok[begin:], self._last_u).T
            self._last_u = u[:, -1].copy()
            h, self._zi_hp = signal.sosfilt(self.sos_hp, u, axis=-1, zi=self._zi_hp)
            np.abs(h, out=h)
            lp, self._zi_lp = signal.sosfilt(self.sos_lp, h, axis=-1, zi=self._zi_lp)  # eq. 2
            det[begin:] = lp.max(axis=0)
        self.last_detection = det

        still = ok & ~gap & (det < self.threshold_g)
        _unsettled(still, j0, self._start, self.settle_n)
        return self._windows_from_still(t, raw, aux, still)

    def flush(self) -> list[Window]:
        """End of stream: emit the open window (the last guard is trimmed), then start a new
        stream (filters and sample indices restart at 0); stats() keep counting until reset()."""
        out = self._flush_windower()
        counts = self.counts
        self.reset()
        self.counts = counts
        return out


class MovingVarianceDetector(_Windower):
    """Per-axis moving variance over a trailing window of ``window_s`` seconds.

    A sample is still when the sample variance (ddof=1) of each axis of to_g(raw) over the
    trailing window is below ``threshold_g``² [g²]. The variance window looks back, so each
    still period loses its first window_s - 1/fs seconds (conservative); ``guard_s`` trims both
    edges as in QuasiStaticDetector. Default ``threshold_g = 0.02`` (20 mg per-axis std): the
    ADXL210 noise is ≈ 4.5 mg rms per axis (see QuasiStaticDetector), whose 1 s moving
    std scatters by only ≈ 7 %; a sway tilt of ~1° (17 mg) still counts as still and biases
    a window mean's norm by < 0.1 mg, while any deliberate movement exceeds 20 mg.

    Moving sums are running sums of (y_j - y_{j-w}) with y = to_g(raw) minus the first
    finite sample (np.cumsum with the carried sum prepended: block-invariant). Non-finite
    samples are held at the last finite value and are never still.
    """

    def __init__(self, fs: float, *, window_s: float = 1.0, threshold_g: float = 0.02, min_duration_s: float = 1.0,
                 max_duration_s: float | None = 60.0, guard_s: float = 0.25, to_g: ToG = None):
        super().__init__(fs, min_duration_s=min_duration_s, max_duration_s=max_duration_s, guard_s=guard_s)
        self.w = int(round(window_s * fs))
        if self.w < 2:
            raise ValueError(f"window_s = {window_s} s holds fewer than 2 samples at fs = {fs} Hz")
        if not threshold_g > 0:
            raise ValueError(f"threshold_g must be > 0, got {threshold_g}")
        self.window_s, self.threshold_g = window_s, float(threshold_g)
        self.to_g = to_g
        self.reset()

    to_g = QuasiStaticDetector.to_g

    def reset(self) -> None:
        """Forget the stream: moving sums, pending samples, the open window, counters."""
        self._reset_windower()
        self._ref: np.ndarray | None = None  # first finite to_g sample
        self._hist = np.zeros((6, self.w))  # last w values of (y, y²) (zeros before the start)
        self._sum = np.zeros(6)  # running sums of y and y² over the trailing window
        self._last_y = np.zeros(3)
        self._start: int | None = None
        self._last_t = np.nan
        self.last_detection = np.zeros(0)  # max per-axis moving std of the last block [g]

    def update(self, t, raw, aux=None) -> list[Window]:
        """Feed a block: t (N,) [s], raw (N, 3) [raw units], aux (N, k) optional.
        Returns the windows completed by this block (any N >= 0)."""
        t, raw, aux, ok = self._check_block(t, raw, aux)
        n = raw.shape[0]
        j0 = self.n_seen
        self.counts["samples"] += n
        x = self._to_g(raw)
        ok &= _finite_rows(x)
        self.counts["nonfinite"] += int(n - np.count_nonzero(ok))
        gap = self._gaps(t, ok)
        if self._ref is None and ok.any():
            first = int(np.flatnonzero(ok)[0])
            self._ref, self._start = x[first].copy(), j0 + first
            self._last_y = np.zeros(3)
        # rows (6, n+w): y then y², the w samples before the block first (ext[:, j] is w before j)
        ext = np.empty((6, self.w + n))
        ext[:, :self.w] = self._hist
        y = ext[:3, self.w:]
        if self._ref is None:
            y[:] = 0.0
        else:
            np.subtract(x.T, self._ref[:, None], out=y)
            if not ok.all():
                y[:] = _forward_fill(y.T, ok, self._last_y).T
        np.multiply(y, y, out=ext[3:, self.w:])
        if n:
            self._last_y = y[:, -1].copy()
        inc = np.empty((6, n + 1))
        inc[:, 0] = self._sum
        np.subtract(ext[:, self.w:], ext[:, :n], out=inc[:, 1:])
        sums = np.cumsum(inc, axis=1)[:, 1:]  # sequential: block-invariant bit for bit
        self._hist = ext[:, n:].copy()
        if n:
            self._sum = sums[:, -1].copy()
        var = (sums[3:] - sums[:3] * sums[:3] / self.w) / (self.w - 1)
        det = np.sqrt(np.clip(np.maximum(np.maximum(var[0], var[1]), var[2]), 0.0, None))
        self.last_detection = det
        still = ok & ~gap & (det < self.threshold_g)
        _unsettled(still, j0, self._start, self.w - 1)
        return self._windows_from_still(t, raw, aux, still)

    flush = QuasiStaticDetector.flush


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


def _settle_samples(sos: np.ndarray, final: float, fs: float, corner_hz: float, tol: float = 0.01) -> int:
    """Samples after which the filter's unit-step response stays within ``tol`` of ``final``."""
    n = int(round(20.0 / corner_hz * fs))
    y = signal.sosfilt(sos, np.ones(n))
    bad = np.flatnonzero(np.abs(y - final) > tol)
    return int(bad[-1] + 1) if bad.shape[0] else 0


DETECTORS = {"lotters": QuasiStaticDetector, "variance": MovingVarianceDetector}


def estimate_fs(t: np.ndarray) -> float:
    """Sample rate [Hz] from the median time step of finite, increasing timestamps."""
    t = np.asarray(t, dtype=float)
    dt = np.diff(t[np.isfinite(t)])
    dt = dt[dt > 0]
    if dt.shape[0] == 0:
        raise ValueError("cannot estimate the sample rate: fewer than two increasing finite timestamps (pass fs)")
    return float(1.0 / np.median(dt))


def detect(t, raw, *, method: str = "lotters", fs: float | None = None, to_g: ToG = None, aux=None, **kw) -> WindowSet:
    """All quasi-static windows of a recording, as a WindowSet (one block + flush).

    method "lotters" (QuasiStaticDetector) or "variance" (MovingVarianceDetector); fs [Hz]
    is estimated from t when None; ``kw`` go to the detector (threshold_g, guard_s, ...).
    """
    if method not in DETECTORS:
        raise ValueError(f"unknown detector method {method!r}; choose one of {sorted(DETECTORS)}")
    fs = estimate_fs(t) if fs is None else fs
    det = DETECTORS[method](fs, to_g=to_g, **kw)
    windows = det.update(t, raw, aux) + det.flush()
    k = 0 if aux is None else (1 if np.ndim(aux) == 1 else np.shape(aux)[1])
    if not windows:
        return WindowSet(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0), np.zeros(0), np.zeros((0, k)),
                         np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    return WindowSet.from_windows(windows)
