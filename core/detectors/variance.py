"""Per-axis moving variance over a trailing window: a sample is still when every axis's moving std is below the threshold."""
from __future__ import annotations

import numpy as np

from ..windows import Window
from ..accelerator import kernels
from .quasistatic import QuasiStaticDetector
from .windowing import (
    ToG,
    _finite_rows,
    _forward_fill,
    _Windower,
)

moving_std = kernels("gravcal.core.detectors._movingstd").moving_std


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
    finite sample (carried from block to block: block-invariant bit for bit). Non-finite
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
        x = self._to_g(raw)
        with np.errstate(invalid="ignore", over="ignore"):
            if ok is not None or not np.isfinite(np.add.reduce(x, axis=None)):  # to_g may give NaN/inf
                fin = _finite_rows(x)
                ok = fin if ok is None else ok & fin
        gap = self._count_block(t, ok)
        if self._ref is None and n and (ok is None or ok.any()):
            first = 0 if ok is None else int(np.flatnonzero(ok)[0])
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
            if ok is not None and not ok.all():
                y[:] = _forward_fill(y.T, ok, self._last_y).T
        np.multiply(y, y, out=ext[3:, self.w:])
        if n:
            self._last_y = y[:, -1].copy()
        # the running sums carried in self._sum, the per-axis sample variance and its max as a std, one
        # compiled pass (_movingstd.c: numpy's cumsum, maximum and clip, bit for bit)
        det = np.empty(n)
        moving_std(ext, self.w, self._sum, det)
        self._hist = ext[:, n:].copy()
        self.last_detection = det
        return self._still_windows(t, raw, aux, det < self.threshold_g, ok, gap, j0, self._start, self.w - 1)

    flush = QuasiStaticDetector.flush
