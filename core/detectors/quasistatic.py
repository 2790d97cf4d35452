"""Lötters et al. 1998, section 2: the quasi-static detector on the norm of the triad (eq. 1-2)."""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..windows import Window
from ..butterworth import butter_sos, sos_rest_state
from .windowing import (
    _KEEP_WORKSPACE,
    _THREAD_MIN_BLOCK,
    ToG,
    _as_to_g,
    _diagonal_affine,
    _filter_rows,
    _forward_fill,
    settle_samples,
    _Windower,
)


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

    - at rest the norm carries the ADXL210 noise, ~500 µg/√Hz (ADXL202/210 rev. B; the
      ADXL210E and gravcal's simulator: 200 µg/√Hz, 2.5× less); over the ~50 Hz output
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

    ``threads=2`` filters half the channels of blocks of >= 8192 samples in a second thread
    (same results; for offline use on a machine with a spare core).

    Start-up: the high-pass state starts at steady state for the first finite sample; the
    first ``settle_s`` seconds (default: the time both filters' step responses need to
    settle within 1 %, ≈ 4.7 s at 0.5 Hz) are never still. Non-finite samples are held
    at the last finite norm for the filters and are never still. ``guard_s`` (default
    0.5 s: the delay for the detection signal of a 0.05 g movement to cross 20 mg) trims
    both edges of every still period.
    """

    def __init__(self, fs: float, *, hp_hz: float = 0.5, lp_hz: float = 0.5, threshold_g: float = 0.02,
                 min_duration_s: float = 1.0, max_duration_s: float | None = 60.0, guard_s: float = 0.5,
                 settle_s: float | None = None, order: int = 2, per_axis: bool = True, to_g: ToG = None,
                 threads: int = 1):
        super().__init__(fs, min_duration_s=min_duration_s, max_duration_s=max_duration_s, guard_s=guard_s)
        self.per_axis = bool(per_axis)
        self._channels = 4 if per_axis else 1
        nyq = 0.5 * fs
        if not (0 < hp_hz < nyq and 0 < lp_hz < nyq):
            raise ValueError(f"filter corners must lie in (0, fs/2 = {nyq} Hz), got hp={hp_hz}, lp={lp_hz}")
        if not threshold_g > 0:
            raise ValueError(f"threshold_g must be > 0, got {threshold_g}")
        self.hp_hz, self.lp_hz, self.threshold_g = hp_hz, lp_hz, float(threshold_g)
        self.sos_hp = butter_sos(order, hp_hz, "highpass", fs)
        self.sos_lp = butter_sos(order, lp_hz, "lowpass", fs)
        self.settle_n = (int(round(settle_s * fs)) if settle_s is not None
                         else settle_samples(self.sos_hp, 0.0, fs, hp_hz) + settle_samples(self.sos_lp, 1.0, fs, lp_hz))
        self._sos_hp = np.ascontiguousarray(self.sos_hp)
        self._sos_lp = np.ascontiguousarray(self.sos_lp)
        # high-pass state at rest for a unit input, (1, sections, 2): scaled by the first sample
        self._zi_hp_unit = sos_rest_state(self._sos_hp)[None]
        self._work = np.empty(0)
        # a second thread filters half the channels of large blocks (threads > 1; offline use)
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="gravcal-qsd") if threads > 1 and per_axis else None
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
        self._diag = _diagonal_affine(value)

    def reset(self) -> None:
        """Forget the stream: filters, pending samples, the open window, counters."""
        self._reset_windower()
        self._zi_hp: np.ndarray | None = None  # None until the first finite sample
        self._zi_lp = np.zeros((self._channels, self.sos_lp.shape[0], 2))
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
        u = self._channels_of(raw)  # (channels, n): the norm (eq. 1), then the axes (per_axis)
        with np.errstate(invalid="ignore", over="ignore"):
            if ok is not None or not np.isfinite(np.add.reduce(u[0])):  # a norm may overflow, or to_g give NaN
                fin = np.isfinite(u[0])
                ok = fin if ok is None else ok & fin
        gap = self._count_block(t, ok)

        det = np.empty(n)
        begin = 0
        if self._zi_hp is None and n:
            good = np.zeros(1, dtype=np.int64) if ok is None else np.flatnonzero(ok)[:1]
            if good.shape[0]:
                begin = int(good[0])
                self._start = j0 + begin
                self._zi_hp = self._zi_hp_unit * u[:, begin, None, None]  # (channels, sections, 2)
                self._last_u = u[:, begin].copy()
        det[:begin] = np.inf
        if self._zi_hp is not None and begin < n:
            v = u if begin == 0 else np.ascontiguousarray(u[:, begin:])
            if ok is not None and not ok[begin:].all():
                v = np.ascontiguousarray(_forward_fill(v.T, ok[begin:], self._last_u).T)
            self._last_u = v[:, -1].copy()
            self._filter(v)
            np.maximum.reduce(v, axis=0, out=det[begin:])
        else:
            det[begin:] = np.inf
        self.last_detection = det
        return self._still_windows(t, raw, aux, det < self.threshold_g, ok, gap, j0, self._start, self.settle_n)

    def _filter(self, v: np.ndarray) -> None:
        """HPF -> rectifier -> LPF (eq. 2) of every channel of v (channels, n), in place. With
        ``threads`` > 1 the channels are split between threads (the SciPy kernel releases the
        GIL); each channel's arithmetic is the same either way, so the results are too."""
        h = v.shape[0] // 2
        if self._pool is None or h == 0 or v.shape[1] < _THREAD_MIN_BLOCK:
            _filter_rows(self._sos_hp, self._sos_lp, v, self._zi_hp, self._zi_lp)
            return
        job = self._pool.submit(_filter_rows, self._sos_hp, self._sos_lp, v[h:], self._zi_hp[h:], self._zi_lp[h:])
        _filter_rows(self._sos_hp, self._sos_lp, v[:h], self._zi_hp[:h], self._zi_lp[:h])
        job.result()

    def _channels_of(self, raw: np.ndarray) -> np.ndarray:
        """The filters' input (channels, n), C-contiguous, in a workspace reused across blocks:
        row 0 |to_g(raw)| (eq. 1), rows 1-3 the axes of to_g(raw); elementwise arithmetic only,
        so every sample's value is independent of the block it came in."""
        n = raw.shape[0]
        if self._work.shape[0] < 5 * n:
            work = np.empty(5 * n)
            if n <= _KEEP_WORKSPACE:
                self._work = work
        else:
            work = self._work
        w = work[:5 * n].reshape(5, n)
        x, scratch = w[1:4], w[4]
        if self._diag is not None:
            o, inv_s = self._diag
            for c in range(3):
                np.subtract(raw[:, c], o[c], out=x[c])  # contiguous when raw is channel-major (Fortran order)
                x[c] *= inv_s[c]
        else:
            x[...] = self._to_g(raw).T
        with np.errstate(invalid="ignore", over="ignore"):
            np.multiply(x[0], x[0], out=w[0])
            np.multiply(x[1], x[1], out=scratch)
            w[0] += scratch
            np.multiply(x[2], x[2], out=scratch)
            w[0] += scratch
            np.sqrt(w[0], out=w[0])
        return w[:self._channels]

    def flush(self) -> list[Window]:
        """End of stream: emit the open window (the last guard is trimmed), then start a new
        stream (filters and sample indices restart at 0); stats() keep counting until reset()."""
        out = self._flush_windower()
        counts = self.counts
        self.reset()
        self.counts = counts
        return out
