"""In-use gyro calibration of a recording or a stream: bias + sensitivity with uncertainty.

    quasi-static windows (the accelerometer's detector)
      -> per window: gyro bias (bias.window_bias, high-pass tail fitted), confirmation of
         stillness by the gyro (bias.GyroStillnessGate), recursive bias (GyroBiasEstimator)
      -> consecutive confirmed windows -> pose-to-pose pairs (pose.Pair)
      -> recursive sensitivity (pose.PoseToPose), two passes (the second re-linearises
         around the first's result, so its gate is meaningful)
      -> held-out check: pairs in contiguous folds, each predicted by a fit without its fold

Convention (the same as the accelerometer's): raw = sensitivity @ omega + bias, so
omega [rad/s] = sensitivity^-1 (raw - bias); bias in raw units, sensitivity in raw units per
rad/s. A single-axis gyro (the ENC-03J) has k = 1: bias (1,), sensitivity (1, 1), and its
sensitive axis in the board frame. With a board high-pass (hp_hz) the bias is the
conditioning stage's reference level, and omega from this formula is the high-passed rate.
"""
from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..calibration import Calibration
from ..windows import Window, WindowSet
from .bias import BIAS_FLOOR_RAD_S, GyroBiasEstimator, GyroStillnessGate, require_finite, window_bias
from .conditioning import detrend_from_rest, reconstruct
from .pose import NO_ROTATION, TOO_LONG, Pair, PoseToPose

log = logging.getLogger(__name__)

SCHEMA = "gravcal.gyro/1"
AXES = "xyz"
MIN_BOOTSTRAP_ANGLE = np.deg2rad(15.0)
BOOTSTRAP_PAIRS = 15  # shortest pairs used to refine the start scale (bounds its cost)
# Prior std of a single-axis gyro's scale around a given start (datasheet or configuration): the
# ENC-03J's scale factor is 0.67 mV/(°/s) ± 20 %. With the former ±50 %, one pair that the gyro
# only partly sees (a turn about the vertical combined with a tilt, which keeps gravity's
# component along the axis: the off-axis test passes) could move the scale 2.5x within the gate.
SINGLE_AXIS_PRIOR_REL_STD = 0.25
MAX_BOOTSTRAP_SPREAD = 0.2  # single axis: median deviation of the pairs' ratios allowed for a bootstrapped start


@dataclass
class GyroCalibration:
    """Gyro bias and sensitivity (k = 1 or 3 axes) with their uncertainty and provenance."""

    bias: np.ndarray  # (k,) [raw units]
    bias_std: np.ndarray  # (k,) [raw units]
    sensitivity: np.ndarray | None  # (k, k) [raw units per rad/s]; None: not determined
    sensitivity_cov: np.ndarray | None  # (k*k, k*k) covariance of vec(sensitivity), row-major
    methods: dict[str, str] = field(default_factory=dict)  # parameter group -> method
    axis: np.ndarray | None = None  # (3,) sensitive axis in the board frame (k = 1)
    hp_hz: float | None = None  # board high-pass corner [Hz] (None: DC-coupled)
    n_windows: int = 0
    n_windows_rejected: int = 0  # windows the gyro did not confirm as still
    n_pairs: int = 0
    rejected_pairs: dict[str, int] = field(default_factory=dict)
    observable: bool = False
    message: str = ""
    heldout_rms_deg: float = float("nan")  # gravity-direction error on held-out pairs [deg]
    heldout_rms_deg_start: float = float("nan")  # same with the start sensitivity and bias
    reduced_chi2: float = float("nan")

    @property
    def k(self) -> int:
        return int(np.asarray(self.bias).size)

    @property
    def std(self) -> dict[str, float]:
        """Standard deviations by name: b_x.. (or b for k = 1), S_xy.. (or S) [raw units (per rad/s)]."""
        names = ["b"] if self.k == 1 else [f"b_{a}" for a in AXES]
        out = {n: float(s) for n, s in zip(names, np.atleast_1d(self.bias_std))}
        if self.sensitivity_cov is not None:
            sd = np.sqrt(np.clip(np.diag(self.sensitivity_cov), 0, None))
            snames = ["S"] if self.k == 1 else [f"S_{r}{c}" for r in AXES for c in AXES]
            out.update({n: float(s) for n, s in zip(snames, sd)})
        return out

    def rate(self, raw: np.ndarray) -> np.ndarray:
        """omega [rad/s] (N, k) = sensitivity^-1 (raw - bias) (through the board high-pass, if any)."""
        if self.sensitivity is None:
            raise ValueError(f"gyro sensitivity not determined: {self.message}")
        raw = np.asarray(raw, dtype=float).reshape(-1, self.k)
        return np.linalg.solve(self.sensitivity, (raw - self.bias).T).T

    def to_json_dict(self) -> dict[str, Any]:
        """The ``gyro`` object of ``gravcal calibrate --json`` and of ``?CALIB``."""
        return {
            "schema": SCHEMA,
            "axes": self.k,
            "bias": _finite(np.atleast_1d(self.bias).tolist()),
            "sensitivity": None if self.sensitivity is None else _finite(self.sensitivity.tolist()),
            "std": {k: _finite(v) for k, v in self.std.items()},
            "units": {"bias": "raw", "sensitivity": "raw per rad/s", "convention": "omega = sensitivity^-1 (raw - bias)"},
            "methods": dict(self.methods),
            "axis": None if self.axis is None else self.axis.tolist(),
            "hp_hz": self.hp_hz,
            "n_windows": int(self.n_windows),
            "n_windows_rejected": int(self.n_windows_rejected),
            "n_pairs": int(self.n_pairs),
            "rejected_pairs": dict(self.rejected_pairs),
            "observable": bool(self.observable),
            "heldout_rms_deg": _finite(self.heldout_rms_deg),
            "heldout_rms_deg_start": _finite(self.heldout_rms_deg_start),
            "reduced_chi2": _finite(self.reduced_chi2),
            "message": self.message,
        }


def _finite(x: Any) -> Any:
    if isinstance(x, list):
        return [_finite(v) for v in x]
    v = float(x)
    return v if math.isfinite(v) else None


# -- building blocks ------------------------------------------------------------------------
def central_half(y: np.ndarray) -> np.ndarray:
    """The central half of a window's samples: its ends may hold the tail of a pose change
    that the accelerometer's detector let in (minimum-jerk ends are slow but not still)."""
    n = y.shape[0]
    return y[n // 4: n - n // 4] if n >= 16 else y


def gravity_direction(mean_raw: np.ndarray, cov_of_mean_raw: np.ndarray, acc: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """Unit gravity direction (body frame) of a window and its covariance (3, 3)."""
    a = acc.apply_reference(mean_raw)
    kinv = np.linalg.inv(acc.sensitivity)
    cov_a = kinv @ cov_of_mean_raw @ kinv.T
    n = float(np.linalg.norm(a))
    u = a / n
    proj = (np.eye(3) - np.outer(u, u)) / n
    return u, proj @ cov_a @ proj.T


def make_pair(gyro: np.ndarray, ws: WindowSet, i: int, j: int, acc: Calibration, *, bias: np.ndarray, fs: float,
              hp_hz: float | None, rails: tuple[float, float] | None = None, offset: int = 0) -> Pair:
    """The pair of windows i -> j (rows of ws); gyro (N, k) holds samples from index ``offset``."""
    a0, a1 = int(ws.start[i]) - offset, int(ws.end[i]) - offset
    b0, b1 = int(ws.start[j]) - offset, int(ws.end[j]) - offset
    if not (0 <= a0 < a1 <= b0 < b1 <= gyro.shape[0]):
        raise ValueError(f"windows {i}, {j} are not increasing sample ranges inside the gyro samples")
    seg = require_finite(gyro[a0:b1], f"of samples {a0 + offset}-{b1 + offset - 1} (a pose change)")
    ni, nj = a1 - a0, b1 - b0
    y = (seg - bias).reshape(seg.shape[0], -1)
    x = reconstruct(y, hp_hz, fs)  # high-pass undone from the start of window i
    # The inverse adds a constant (the high-pass state at window i) and a bias error adds a
    # ramp: a line fitted where the rate is zero removes both. Only the central halves of the
    # windows count as zero-rate: their ends may hold the tail of a pose change (which the
    # window averages B_i, B_j of the prediction integrate). Compared on simulated foot poses
    # (6 seeds): central halves 0.5-0.6° held-out, whole windows 1.1°, the high-pass tail's
    # shape (conditioning.tail_offset) 1.5° (posture sway and quantisation corrupt it).
    rest = np.zeros(b1 - a0, bool)
    rest[ni // 4: ni - ni // 4] = True
    rest[b0 - a0 + nj // 4: b1 - a0 - nj // 4] = True
    x, _ = detrend_from_rest(x, rest)
    rms = np.sqrt(np.mean((x[rest] - x[rest].mean(axis=0)) ** 2, axis=0))
    gi, ci = gravity_direction(ws.mean[i], ws.cov_of_mean[i], acc)
    gj, cj = gravity_direction(ws.mean[j], ws.cov_of_mean[j], acc)
    sat = bool(rails is not None and (np.any(seg <= rails[0]) or np.any(seg >= rails[1])))
    return Pair(u=x, dt=1.0 / fs, g_i=gi, g_j=gj, cov_i=ci, cov_j=cj, rest_rms=rms, n_rest=int(rest.sum()),
                n_i=ni, n_j=nj, saturated=sat, t_i=float(ws.t[i]), t_j=float(ws.t[j]))


def bootstrap_rate_scale(pairs: list[Pair], axis: np.ndarray | None) -> float:
    """Scale-free start [rad/s per raw unit] from pairs: the gravity direction change over the
    integrated gyro signal, median over pairs whose turn is clear (15-150°). Single-axis:
    signed rotation about the axis, so a gyro mounted upside down gets a negative scale."""
    ratios = []
    for p in pairs:
        integral = p.u.sum(axis=0) * p.dt
        if axis is None:
            ang = float(np.arccos(np.clip(p.g_i @ p.g_j, -1, 1)))
            norm = float(np.linalg.norm(integral))
            if MIN_BOOTSTRAP_ANGLE < ang < np.deg2rad(150) and norm > 0:
                ratios.append(ang / norm)
        else:
            pi, pj = p.g_i - (p.g_i @ axis) * axis, p.g_j - (p.g_j @ axis) * axis
            if min(np.linalg.norm(pi), np.linalg.norm(pj)) < 0.5:
                continue
            ang = -float(np.arctan2(axis @ np.cross(pi, pj), pi @ pj))  # g_j = R(-phi) g_i
            if abs(ang) > MIN_BOOTSTRAP_ANGLE and integral[0] != 0:
                ratios.append(ang / float(integral[0]))
    if not ratios:
        raise ValueError("cannot find a start for the gyro scale: no rotation of 15-150° between quasi-static "
                         "windows (pass a start sensitivity)")
    m0 = float(np.median(ratios))
    if axis is not None:
        # single axis: a turn about the vertical combined with a tilt keeps gravity's component
        # along the axis (so it looks like a turn about it) but gives its own ratio; pure turns
        # about the axis agree to a few % (noise, the ends of the windows)
        spread = float(np.median(np.abs(np.asarray(ratios) - m0)) / abs(m0))
        if len(ratios) < 3 or spread > MAX_BOOTSTRAP_SPREAD:
            raise ValueError(
                f"cannot find a start for the gyro scale: {len(ratios)} pose change(s) of 15-150° about the axis"
                + (f", whose angle-to-signal ratios disagree by {spread * 100:.0f} % (median deviation > "
                   f"{MAX_BOOTSTRAP_SPREAD * 100:.0f} %): rotations the gyro only partly sees"
                   if len(ratios) >= 3 else ", need 3") + " (pass a start sensitivity)")
    # refine: the isotropic scale that best predicts the gravity directions (median over pairs;
    # turns about several axes make |integral| exceed the angle, which biases the ratio low)
    probe = PoseToPose("scalar" if axis is not None else "matrix", np.array([m0]) if axis is not None else m0 * np.eye(3),
                       axis=axis)
    sub = sorted(pairs, key=lambda p: p.u.shape[0])[:BOOTSTRAP_PAIRS]

    def cost(log_m: float) -> float:
        m = m0 * np.exp(log_m)
        x = np.array([m]) if axis is not None else (m * np.eye(3)).reshape(9)
        return float(np.median([pair_residual_deg(probe, x, p) for p in sub]))

    from scipy import optimize  # noqa: PLC0415 (offline only: keeps scipy.optimize off the daemon's start)

    res = optimize.minimize_scalar(cost, bounds=(np.log(0.5), np.log(2.0)), method="bounded", options={"xatol": 1e-3})
    return m0 * float(np.exp(res.x))
# -- offline ----------------------------------------------------------------------------------
def calibrate_gyro(t: np.ndarray, gyro_raw: np.ndarray, windows: WindowSet, acc_calibration: Calibration, *,
                   fs: float | None = None, hp_hz: float | None = None, axis: Any = None, start: Any = None,
                   range_rad_s: float = np.inf, rails: tuple[float, float] | None = None,
                   gate_threshold_rad_s: float = GyroStillnessGate.threshold_rad_s, max_gap_s: float = 30.0,
                   min_angle_deg: float = 10.0, floor_deg: float = 0.5, folds: int = 5) -> GyroCalibration:
    """Gyro bias and sensitivity of a recording from its quasi-static windows.

    t (N,) [s]; gyro_raw (N,) single-axis or (N, 3) [raw units]; windows: the accelerometer's
    quasi-static windows (start/end index the same samples); acc_calibration: raw -> g.
    hp_hz: board high-pass [Hz] (ENC-03J board: 0.3) or None; axis: sensitive axis of a
    single-axis gyro (default board y); start: sensitivity [raw per rad/s] (scalar or 3x3) to
    start from, None = bootstrap from the data; range_rad_s: gyro range; rails: (min, max) raw
    values of the ADC. Raises ValueError when there are no windows; returns a calibration with
    ``sensitivity None`` and a message when no sensitivity can be claimed.
    """
    g = np.asarray(gyro_raw, dtype=float)
    k = 1 if g.ndim == 1 or g.shape[1] == 1 else 3
    g = g.reshape(g.shape[0], k)
    if g.ndim != 2 or (g.shape[1] not in (1, 3)):
        raise ValueError(f"gyro_raw must be (N,), (N, 1) or (N, 3), got {np.shape(gyro_raw)}")
    t = np.asarray(t, dtype=float)
    if t.shape[0] != g.shape[0]:
        raise ValueError(f"t has {t.shape[0]} samples, gyro {g.shape[0]}")
    if len(windows) == 0:
        raise ValueError("no quasi-static windows: the gyro bias needs at least one still period")
    if fs is None:
        dt = np.diff(t)
        fs = float(1.0 / np.median(dt[dt > 0]))
    ax = None
    if k == 1:
        ax = np.asarray((0.0, 1.0, 0.0) if axis is None else axis, float)
        ax = ax / np.linalg.norm(ax)
    order = np.argsort(windows.start)
    ws = windows.subset(order)
    methods = {"bias": "quasi-static windows" + (" (high-pass tail fitted)" if hp_hz else "")}

    # bias: every window, recursively
    best = GyroBiasEstimator(k=k)
    wbs = [window_bias(central_half(g[int(ws.start[i]):int(ws.end[i])]), fs, hp_hz) for i in range(len(ws))]
    for i, wb in enumerate(wbs):
        best.update(wb, float(ws.t[i]))
    bias = best.bias.copy()

    def build_pairs(keep: np.ndarray) -> tuple[list[Pair], Counter]:
        idx = np.flatnonzero(keep)
        out, rej = [], Counter()
        for i, j in zip(idx[:-1], idx[1:]):
            if (ws.start[j] - ws.end[i]) / fs > max_gap_s:
                rej[TOO_LONG] += 1
                continue
            if ws.start[j] <= ws.end[i] + 1:
                rej[NO_ROTATION] += 1  # one still period cut in two windows
                continue
            out.append(make_pair(g, ws, int(i), int(j), acc_calibration, bias=bias, fs=fs, hp_hz=hp_hz, rails=rails))
        return out, rej

    keep = np.ones(len(ws), bool)
    pairs, pre_rejected = build_pairs(keep)
    if start is None:
        try:
            m0: Any = bootstrap_rate_scale(pairs, ax)
            if k == 3:
                m0 = m0 * np.eye(3)
        except ValueError as exc:
            return _no_sensitivity(best, k, ax, hp_hz, methods, len(ws), 0, str(exc), pre_rejected)
        methods["start"] = "bootstrap from pose changes"
    else:
        s0 = np.asarray(start, float)
        m0 = 1.0 / float(s0.reshape(-1)[0]) if k == 1 else np.linalg.inv(s0 * np.eye(3) if s0.ndim < 2 else s0)
        methods["start"] = "given"
    scale = abs(m0) if k == 1 else float(np.linalg.norm(m0) / np.sqrt(3.0))
    gate = GyroStillnessGate(fs, 1.0 / scale, hp_hz, gate_threshold_rad_s)
    keep = np.array([gate.confirm(g[int(ws.start[i]):int(ws.end[i])])[0] for i in range(len(ws))])
    n_gated = int((~keep).sum())
    # the bias again, with the rate scale known: gated windows only, slow-rotation floor
    floor = BIAS_FLOOR_RAD_S / scale
    best = GyroBiasEstimator(k=k)
    for i in np.flatnonzero(keep):
        best.update(window_bias(central_half(g[int(ws.start[i]):int(ws.end[i])]), fs, hp_hz, floor), float(ws.t[i]))
    bias = best.bias.copy()
    pairs, pre_rejected = build_pairs(keep)

    def fit(sel: list[Pair], x0: Any, passes: int = 2) -> PoseToPose:
        est = None
        # gated from the first pair (the innovation covariance holds the prior's ±50 %): an ungated
        # pair that the single-axis gyro only partly sees (a turn about the vertical with a tilt,
        # gravity's component along the axis unchanged) set a Lötters session's scale 3.3x off,
        # and pass 2 then kept the pairs that agreed with it (bench_gyro, loetters seed 4)
        for _ in range(passes):  # pass 2 re-linearises around pass 1
            est = PoseToPose("scalar" if k == 1 else "matrix", np.asarray(x0), axis=ax, range_rad_s=range_rad_s,
                             min_angle_rad=np.deg2rad(min_angle_deg), floor_rad=np.deg2rad(floor_deg), gate_after=0,
                             start_rel_std=prior_rel_std)
            for p in sel:
                est.update(p)
            if est.n_pairs == 0:
                break
            x0 = est.x.copy()
        return est

    # the prior: a given start for the ENC-03J is the datasheet's (±20 %): ±25 %; a bootstrapped
    # one (or a triaxial gyro's) only roughly known: ±50 %
    prior_rel_std = SINGLE_AXIS_PRIOR_REL_STD if (k == 1 and start is not None) else 0.5
    est = fit(pairs, m0)
    rejected = dict(pre_rejected + est.rejected)
    cal = GyroCalibration(bias=bias, bias_std=best.std, sensitivity=None, sensitivity_cov=None, methods=methods,
                          axis=ax, hp_hz=hp_hz, n_windows=int(keep.sum()), n_windows_rejected=n_gated,
                          n_pairs=est.n_pairs, rejected_pairs=rejected, observable=est.observable,
                          message=est.message(), reduced_chi2=est.reduced_chi2())
    if not est.observable:
        return cal
    S, cov = est.sensitivity()
    cal.sensitivity, cal.sensitivity_cov = S, cov
    cal.methods["sensitivity"] = "pose-to-pose (gravity direction change vs integrated rate, IEKF)"
    if folds >= 2:  # held-out check (folds < 2: skip it, e.g. in statistical tests)
        cal.heldout_rms_deg, cal.heldout_rms_deg_start = _heldout(pairs, fit, est, m0, folds)
    return cal


def _no_sensitivity(best, k, ax, hp_hz, methods, n_windows, n_pairs, message, rejected) -> GyroCalibration:
    return GyroCalibration(bias=best.bias.copy(), bias_std=best.std, sensitivity=None, sensitivity_cov=None,
                           methods=methods, axis=ax, hp_hz=hp_hz, n_windows=n_windows, n_pairs=n_pairs,
                           rejected_pairs=dict(rejected), observable=False, message=f"no sensitivity: {message}")


def pair_residual_deg(est: PoseToPose, x: np.ndarray, pair: Pair) -> float:
    """Angle [deg] between the measured gravity direction g_j and the one the gyro predicts."""
    g_pred = est._predict(np.asarray(x, float), pair)[0]
    return float(np.degrees(np.arccos(np.clip(g_pred @ pair.g_j, -1.0, 1.0))))


def pairs_rms_deg(gyro_raw: np.ndarray, windows: WindowSet, acc_calibration: Calibration, sensitivity: Any,
                  bias: Any, *, fs: float, hp_hz: float | None = None, axis: Any = None,
                  min_angle_deg: float = 10.0) -> tuple[float, int]:
    """(rms [deg], number of pairs) of the gravity-direction error after each rotation between
    consecutive windows, predicted with a GIVEN sensitivity [raw per rad/s] and bias [raw]:
    how well nominal values (or another calibration) explain the rotations. Pairs without an
    observable rotation (below min_angle_deg across gravity) are skipped."""
    g = np.asarray(gyro_raw, float)
    k = 1 if g.ndim == 1 or g.shape[1] == 1 else 3
    g = g.reshape(g.shape[0], k)
    ws = windows.subset(np.argsort(windows.start))
    s = np.asarray(sensitivity, float)
    if k == 1:
        ax = np.asarray((0.0, 1.0, 0.0) if axis is None else axis, float)
        est = PoseToPose("scalar", np.array([1.0 / float(s.reshape(-1)[0])]), axis=ax / np.linalg.norm(ax))
    else:
        est = PoseToPose("matrix", np.linalg.inv(s * np.eye(3) if s.ndim < 2 else s))
    err = []
    for i in range(len(ws) - 1):
        if ws.start[i + 1] <= ws.end[i] + 1:
            continue
        p = make_pair(g, ws, i, i + 1, acc_calibration, bias=np.asarray(bias, float).reshape(k), fs=fs, hp_hz=hp_hz)
        _, _, C, omega = est._predict(est.x, p)
        if est._angles(C, omega, p.g_i, p.dt)[1] < np.deg2rad(min_angle_deg):
            continue
        err.append(pair_residual_deg(est, est.x, p))
    return (float(np.sqrt(np.mean(np.square(err)))) if err else float("nan")), len(err)


def _heldout(pairs: list[Pair], fit, full: PoseToPose, x_start: Any, folds: int) -> tuple[float, float]:
    """RMS gravity-direction error [deg] of each pair predicted by a fit on the other folds
    (contiguous folds in time); and the same for the start values (before calibration)."""
    usable = [p for p in pairs if full._angles(*full._predict(full.x, p)[2:4], p.g_i, p.dt)[1] >= full.min_angle_rad
              and not p.saturated]
    if len(usable) < 2 * folds:
        return float("nan"), float("nan")
    edges = np.linspace(0, len(usable), folds + 1).astype(int)
    err, err0 = [], []
    x0 = np.asarray(x_start, float).reshape(-1) if np.ndim(x_start) else np.array([float(x_start)])
    for a, b in zip(edges[:-1], edges[1:]):
        est = fit(usable[:a] + usable[b:], full.x.copy(), 1)
        if est.n_pairs == 0:
            continue
        for p in usable[a:b]:
            err.append(pair_residual_deg(est, est.x, p))
            err0.append(pair_residual_deg(est, x0, p))
    if not err:
        return float("nan"), float("nan")
    return float(np.sqrt(np.mean(np.square(err)))), float(np.sqrt(np.mean(np.square(err0))))


# -- online (the daemon) ------------------------------------------------------------------------
class OnlineGyroCalibrator:
    """Streaming gyro calibration next to the accelerometer's detector and estimator.

    Feed every sample block with ``push(gyro_block)`` (the same blocks, in the same order, as
    the detector gets, so window indices match), and every window the detector emits with
    ``window(w, acc_calibration)``. ``calibration`` is the current GyroCalibration; ``rate``
    converts raw gyro samples to rad/s with it (NaN while the sensitivity is unknown).
    Buffer: the samples since the last confirmed window's start while a pair with it is still
    possible, otherwise the last ``max_gap_s + max_window_s`` (a window up to ``max_window_s``
    long, the detector's longest, plus the gap before it); so memory and the cost per block stay
    bounded through hours without a still moment. A gap longer than ``max_gap_s`` ends the pair
    ("too long between windows").
    """

    def __init__(self, fs: float, *, k: int = 1, axis: Any = (0.0, 1.0, 0.0), hp_hz: float | None = None,
                 start_sensitivity: Any, range_rad_s: float = np.inf, rails: tuple[float, float] | None = None,
                 gate_threshold_rad_s: float = GyroStillnessGate.threshold_rad_s, max_gap_s: float = 30.0,
                 max_window_s: float = 60.0, bias_walk_counts_per_sqrt_s: float = 0.0,
                 process_noise_rel_per_sqrt_s: float = 0.0):
        self.fs, self.k, self.hp_hz, self.rails = float(fs), int(k), hp_hz, rails
        self.axis = None if k == 3 else np.asarray(axis, float) / np.linalg.norm(axis)
        s0 = np.asarray(start_sensitivity, float)
        m0 = 1.0 / float(s0.reshape(-1)[0]) if k == 1 else np.linalg.inv(s0 * np.eye(3) if s0.ndim < 2 else s0)
        self.start_scale = float(np.linalg.norm(np.atleast_2d(m0)) / np.sqrt(np.atleast_2d(m0).shape[0]))
        self.gate = GyroStillnessGate(fs, 1.0 / self.start_scale, hp_hz, gate_threshold_rad_s)
        self.bias_est = GyroBiasEstimator(k=self.k, walk_counts_per_sqrt_s=bias_walk_counts_per_sqrt_s)
        # gate from the first pair: online there is no second pass to re-linearise around, and an
        # ungated first pair that the gyro cannot explain set the scale (even its sign) for good
        self.pose = PoseToPose("scalar" if k == 1 else "matrix", np.asarray(m0), axis=self.axis, range_rad_s=range_rad_s,
                               start_rel_std=SINGLE_AXIS_PRIOR_REL_STD if k == 1 else 0.5,
                               gate_after=0)
        self.max_gap_n = int(max_gap_s * fs)
        self.horizon_n = self.max_gap_n + int(max_window_s * fs)  # samples kept without a pending pair
        self._buf = np.zeros((0, self.k))
        self._buf_start = 0  # global index of _buf[0]
        self._n = 0  # global index of the next sample
        self._prev: Window | None = None  # last confirmed window
        self._prev_g: tuple[np.ndarray, np.ndarray] | None = None
        self.n_windows = 0
        self.n_windows_rejected = 0
        self.rejected: Counter[str] = Counter()

    def push(self, gyro_block: np.ndarray) -> None:
        y = np.asarray(gyro_block, float).reshape(-1, self.k)
        self._buf = np.concatenate([self._buf, y])
        block_start = self._n
        self._n += y.shape[0]
        # counted from the start of this block, not its end: the windows the detector emits for this block
        # (any number, a lagging caller hands over seconds at once) end inside it, so each starts at most
        # max_window_s before block_start and needs no older samples of its own ...
        keep_from = block_start - self.horizon_n
        # ... and the last window's samples while a window can still pair with it: beyond max_gap_s +
        # max_window_s after the last window's end the pair is "too long between windows" anyway (counted then)
        if self._prev is not None and block_start - self._prev.end <= self.horizon_n:
            keep_from = min(self._prev.start, keep_from)
        cut = max(0, keep_from - self._buf_start)
        if cut:
            self._buf = self._buf[cut:]
            self._buf_start += cut

    def window(self, w: Window, acc_calibration: Calibration) -> None:
        """Fold in one quasi-static window (its samples must have been pushed)."""
        a, b = w.start - self._buf_start, w.end - self._buf_start
        if a < 0 or b > self._buf.shape[0]:
            self.rejected["window samples no longer buffered"] += 1
            return
        y = self._buf[a:b]
        still, _ = self.gate.confirm(y)
        if not still:
            self.n_windows_rejected += 1
            return
        floor = BIAS_FLOOR_RAD_S / self.start_scale
        if not self.bias_est.update(window_bias(central_half(y), self.fs, self.hp_hz, floor), w.t_mid):
            self.n_windows_rejected += 1
            return
        self.n_windows += 1
        prev, self._prev = self._prev, w
        if prev is None:
            return
        if w.start - prev.end > self.max_gap_n:
            self.rejected[TOO_LONG] += 1
            return
        if w.start <= prev.end + 1:
            self.rejected[NO_ROTATION] += 1
            return
        if prev.start < self._buf_start:  # (push keeps them; a caller that skipped blocks)
            self.rejected["window samples no longer buffered"] += 1
            return
        ws = WindowSet.from_windows([prev, w])
        pair = make_pair(self._buf, ws, 0, 1, acc_calibration, bias=self.bias_est.bias, fs=self.fs,
                         hp_hz=self.hp_hz, rails=self.rails, offset=self._buf_start)
        self.pose.update(pair)

    def feed(self, w: Window, acc_calibration: Calibration) -> bool:
        """The service's rule for one window: used only under a converged accelerometer calibration (the
        pose-to-pose sensitivity compares gravity directions, which a datasheet start gets wrong by up to
        ~0.9 g of offset); a window the gyro cannot use is skipped, never the rest. True when it changed
        the calibration."""
        if not acc_calibration.converged:
            return False
        before = (self.n_windows, self.n_windows_rejected, self.pose.n_pairs)
        try:
            self.window(w, acc_calibration)
        except (ValueError, np.linalg.LinAlgError) as exc:
            log.warning("window skipped by the gyro estimator: %s", exc)
            return False
        return (self.n_windows, self.n_windows_rejected, self.pose.n_pairs) != before

    def correction(self, start: tuple[float, float]) -> tuple[float, float]:
        """(bias [counts], sensitivity [counts per rad/s]) to publish rates with (single axis): the
        estimated bias once a window gave one, the sensitivity once determined, ``start``'s until then."""
        cal = self.calibration
        bias, sens = start
        if cal.n_windows > 0 and np.all(np.isfinite(cal.bias)):
            bias = float(cal.bias[0])
        if cal.sensitivity is not None:
            sens = float(cal.sensitivity[0, 0])
        return bias, sens

    @property
    def calibration(self) -> GyroCalibration:
        est = self.pose
        rejected = dict(self.rejected + est.rejected)
        cal = GyroCalibration(bias=self.bias_est.bias.copy(), bias_std=self.bias_est.std, sensitivity=None,
                              sensitivity_cov=None, methods={"bias": "quasi-static windows (online)"}, axis=self.axis,
                              hp_hz=self.hp_hz, n_windows=self.n_windows, n_windows_rejected=self.n_windows_rejected,
                              n_pairs=est.n_pairs, rejected_pairs=rejected, observable=est.observable,
                              message=est.message(), reduced_chi2=est.reduced_chi2())
        if est.observable:
            cal.sensitivity, cal.sensitivity_cov = est.sensitivity()
            cal.methods["sensitivity"] = "pose-to-pose (online IEKF)"
        return cal

    def rate(self, gyro_block: np.ndarray) -> np.ndarray:
        """(N, k) [rad/s]; NaN until bias and sensitivity are determined."""
        cal = self.calibration
        y = np.asarray(gyro_block, float).reshape(-1, self.k)
        if cal.sensitivity is None or not np.all(np.isfinite(cal.bias)):
            return np.full(y.shape, np.nan)
        return cal.rate(y)


def gyro_report(t: np.ndarray, gyro_raw: np.ndarray, report: Any, *, fs: float | None = None,
                **kw: Any) -> dict[str, Any]:
    """The ``gyro`` object of ``gravcal calibrate --json`` for a recording with gx, gy, gz:
    calibrate_gyro on the windows and accelerometer calibration of a core.pipeline
    CalibrationReport. Never raises for unusable gyro data: the object then carries
    ``sensitivity: null``, ``observable: false`` and the reason in ``message``."""
    try:
        return calibrate_gyro(t, gyro_raw, report.windows, report.calibration, fs=fs, **kw).to_json_dict()
    except ValueError as exc:
        k = int(np.shape(gyro_raw)[1]) if np.ndim(gyro_raw) == 2 else 1
        return {"schema": SCHEMA, "axes": k, "bias": None, "sensitivity": None, "std": {}, "methods": {},
                "observable": False, "message": f"no gyro calibration: {exc}"}
