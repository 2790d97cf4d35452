"""Re-mount detection: the sensor was taken off and put back on the body rotated.

What a re-mount breaks. For raw = K a + o the gravity norm |K^-1 (raw - o)| does not depend on how
the housing sits on the body (a rotation of a leaves |a| unchanged), so K and o -- orders offsets, 6,
9, and 12, whose frame R0 is the sensor's axes relative to its own housing -- stay valid: a re-mount
never makes the calibration wrong, and the estimators must not react to it (they do not: the windows
still lie on the same ellipsoid). What it breaks is every *posture* interpretation: the sensor-frame
direction of gravity when the wearer stands (what "upright" means downstream), the posture cells of
the window store, and any body-frame use of the calibrated axes. So it is detected from the posture
statistics and reported (the daemon's CALIB/?STATUS ``remount`` events), not corrected.

The detector (:class:`RemountDetector`) arms once its reference spans a day of sensor time and keeps a duration-weighted histogram of the quasi-static gravity
directions (sensor frame, ~10° cells) -- the *reference posture set*: cells holding at least
``set_fraction`` of the still time, dilated by ``near_deg`` -- and its dominant direction (upright for a
waist sensor: standing and sitting hold most of the day). Two rules flag a re-mount:

1. *fast* (moderate rotations): over the last ``novel_s`` of sensor time (at least ``min_windows``
   windows out of the set) less than ``fast_fraction`` of the still time fell in the reference set (a
   rotated posture may graze the set now and then), and the dominant direction of the others is between
   ``min_angle_deg`` and ``lying_deg`` from the reference's. Lying down is ~90° from upright and
   also new on a first night, so the rule excludes angles >= ``lying_deg``: from still windows alone a
   90° re-mount of an upright wearer and the original mount of a lying one are the same data.
2. *slow* (any rotation, also those that keep the postures inside the reference set, e.g. a tilt about the
   body's lateral axis that makes standing look like leaning back): once the reference spans ``day_s``,
   over the last ``mode_s`` of sensor time (longer than a night) less than ``mode_fraction`` of the still
   time (at least ``min_recent_s`` of it) fell in the reference's *core* (the cells holding ``core_mass``
   of its still time, dilated by ``core_deg``: the habitual standing, sitting and lying postures), and the
   recent dominant direction is at least ``min_angle_deg`` from the reference's. Within half a day a
   wearer returns to habitual postures; a wearer whose sensor turned does not.

An excursion out of the posture set that lasts at least ``merge_s`` and ends without a detection (the
first night: lying is new) joins the reference; shorter ones do not (a rotated sensor's occasional
posture that happens to look habitual must not teach the reference the new mount).

After a detection the reference restarts from the new windows (the new mount). Events carry the sensor
time, the angle between the old and new dominant directions [deg], and which rule fired.
"""
from __future__ import annotations

import collections
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..crlb import sphere_directions
from ..windows import WindowSet

CELLS = 400  # ~10° cells on the sphere (order.POSTURE_CELLS)


@dataclass
class RemountEvent:
    t: float  # sensor time of the detection [s]
    angle_deg: float  # angle between the old and the new dominant gravity direction (sensor frame)
    rule: str  # "fast" or "slow"
    old_direction: tuple[float, float, float]
    new_direction: tuple[float, float, float]
    since_t: float  # sensor time of the last window in the old posture set

    def to_json_dict(self) -> dict[str, Any]:
        return {"t": round(self.t, 3), "angle_deg": round(self.angle_deg, 2), "rule": self.rule,
                "old_direction": [round(x, 4) for x in self.old_direction],
                "new_direction": [round(x, 4) for x in self.new_direction], "since_t": round(self.since_t, 3)}


class _Histogram:
    """Duration-weighted directions per cell, with their direction sums (for a refined mode)."""

    def __init__(self, dirs: np.ndarray):
        self.w = np.zeros(len(dirs))
        self.sum = np.zeros((len(dirs), 3))
        self.t_first: float | None = None

    def add(self, cell: int, u: np.ndarray, w: float, t: float) -> None:
        self.w[cell] += w
        self.sum[cell] += w * u
        self.t_first = t if self.t_first is None else self.t_first

    @property
    def total(self) -> float:
        return float(self.w.sum())


class RemountDetector:
    """See the module docstring. ``update(t, direction, weight)`` per quasi-static window (sensor time
    [s], unit gravity direction in the sensor frame under the current calibration, still duration [s]);
    returns a RemountEvent when one is detected, else None."""

    def __init__(self, *, min_ref_s: float = 4 * 3600.0, novel_s: float = 1800.0, min_windows: int = 20,
                 min_angle_deg: float = 20.0, lying_deg: float = 60.0, near_deg: float = 10.0,
                 set_fraction: float = 0.01, day_s: float = 86400.0, mode_s: float = 12 * 3600.0,
                 mode_fraction: float = 0.2, min_recent_s: float = 3600.0, mode_deg: float = 15.0,
                 core_mass: float = 0.8, core_deg: float = 10.0, merge_s: float = 2 * 3600.0,
                 fast_fraction: float = 0.1, ref_span_s: float = 86400.0, max_events: int = 50):
        self.min_ref_s, self.novel_s, self.min_windows = float(min_ref_s), float(novel_s), int(min_windows)
        self.min_angle, self.lying = math.radians(min_angle_deg), math.radians(lying_deg)
        self.set_fraction, self.day_s, self.mode_s = float(set_fraction), float(day_s), float(mode_s)
        self.mode_fraction, self.min_recent_s = float(mode_fraction), float(min_recent_s)
        self.core_mass, self._core_deg, self.merge_s = float(core_mass), float(core_deg), float(merge_s)
        self.fast_fraction, self.ref_span_s = float(fast_fraction), float(ref_span_s)
        self._t_last: float | None = None
        self.dirs = sphere_directions(CELLS)
        cos = self.dirs @ self.dirs.T
        self._near = (cos >= math.cos(math.radians(near_deg))).astype(float)  # dilation of the posture set
        self._mode = (cos >= math.cos(math.radians(mode_deg))).astype(float)  # smoothing for the mode
        self._core_near = (cos >= math.cos(math.radians(self._core_deg))).astype(float)  # dilation of the core
        self.events: collections.deque[RemountEvent] = collections.deque(maxlen=int(max_events))
        self.n_windows = 0
        self._reset(None)

    def _reset(self, t: float | None) -> None:
        self.ref = _Histogram(self.dirs)
        self.novel = _Histogram(self.dirs)  # windows since the last one in the reference set
        self.novel_n = 0
        self.last_in_set_t = t
        self._in_set_cells: np.ndarray | None = None
        self._since_set = 0
        # per hour of sensor time: [hour index, weight near the reference mode, weight, histogram (cells)]
        self.hours: collections.deque[list[Any]] = collections.deque()
        self._core: np.ndarray | None = None
        self.recent: collections.deque[tuple[float, float, float]] = collections.deque()  # (t, in-set w, w)
        self._recent_in = self._recent_all = 0.0

    # -- helpers ----------------------------------------------------------------------------
    def _dominant(self, h: _Histogram) -> np.ndarray:
        smooth = self._mode @ h.w
        c = int(np.argmax(smooth))
        s = self._mode[c] @ h.sum
        n = float(np.linalg.norm(s))
        return s / n if n > 0 else self.dirs[c]

    def _posture_set(self) -> np.ndarray:
        if self._in_set_cells is None or self._since_set >= 50:
            occupied = (self.ref.w >= self.set_fraction * max(self.ref.total, 1e-300)).astype(float)
            self._in_set_cells = (self._near @ occupied) > 0
            self._since_set = 0
        return self._in_set_cells

    @property
    def armed(self) -> bool:
        """The reference holds ``min_ref_s`` of still time over at least ``ref_span_s`` of sensor time (a
        whole day: a reference from one evening and night would call the next morning's standing new)."""
        return (self.ref.total >= self.min_ref_s and self.ref.t_first is not None and self._t_last is not None
                and self._t_last - self.ref.t_first >= self.ref_span_s)

    def status(self) -> dict[str, Any]:
        return {"armed": self.armed, "reference_s": round(self.ref.total, 1), "windows": self.n_windows,
                "novel_windows": self.novel_n, "last_in_posture_set_t": self.last_in_set_t,
                "events": [e.to_json_dict() for e in self.events]}

    # -- per window ----------------------------------------------------------------------------
    def update(self, t: float, direction: np.ndarray, weight: float = 1.0) -> RemountEvent | None:
        u = np.asarray(direction, dtype=float).reshape(3)
        n = float(np.linalg.norm(u))
        if not (math.isfinite(n) and n > 0 and math.isfinite(t)):
            return None
        u = u / n
        w = float(max(weight, 1e-3))
        cell = int(np.argmax(self.dirs @ u))
        self.n_windows += 1
        self._t_last = t
        if not self.armed:
            self.ref.add(cell, u, w, t)
            self.last_in_set_t = t
            return None
        self._since_set += 1
        in_set = bool(self._posture_set()[cell])
        if self._core is None or self._since_set == 1 or self._in_set_cells is None:  # refreshed with the set
            order = np.argsort(self.ref.w)[::-1]
            k = int(np.searchsorted(np.cumsum(self.ref.w[order]), self.core_mass * self.ref.total)) + 1
            top = np.zeros(len(self.dirs))
            top[order[:k]] = 1.0
            self._core = (self._core_near @ top) > 0
        hour = int(t // 3600.0)
        if not self.hours or self.hours[-1][0] != hour:
            self.hours.append([hour, 0.0, 0.0, np.zeros(len(self.dirs)), np.zeros((len(self.dirs), 3))])
        b = self.hours[-1]
        b[1] += w if self._core[cell] else 0.0
        b[2] += w
        b[3][cell] += w
        b[4][cell] += w * u
        while self.hours and self.hours[0][0] < hour - int(self.mode_s // 3600.0) + 1:
            self.hours.popleft()
        # the last novel_s of windows: how much of that still time was in habitual postures
        self.recent.append((t, w if in_set else 0.0, w))
        self._recent_in += w if in_set else 0.0
        self._recent_all += w
        while self.recent and self.recent[0][0] < t - self.novel_s:
            _, wi, wa = self.recent.popleft()
            self._recent_in -= wi
            self._recent_all -= wa
        frac_in = self._recent_in / max(self._recent_all, 1e-300)
        if in_set and frac_in >= 0.5:  # habitual postures: the reference learns, an excursion ends
            self.ref.add(cell, u, w, t)
            if self.novel_n and t - (self.last_in_set_t or t) >= self.merge_s:
                # a long excursion that ended without a detection was a posture (a first night): keep it
                self.ref.w += self.novel.w
                self.ref.sum += self.novel.sum
                self._in_set_cells = self._core = None
            self.novel = _Histogram(self.dirs)
            self.novel_n = 0
            self.last_in_set_t = t
            return self._slow_rule(t)
        if not in_set:
            self.novel.add(cell, u, w, t)
            self.novel_n += 1
        span = t - self.recent[0][0]
        if span >= 0.9 * self.novel_s and self.novel_n >= self.min_windows and frac_in < self.fast_fraction:
            old, new = self._dominant(self.ref), self._dominant(self.novel)
            ang = math.acos(max(-1.0, min(1.0, float(old @ new))))
            if self.min_angle <= ang < self.lying:
                return self._detected(t, old, new, ang, "fast", self.last_in_set_t or t)
        return self._slow_rule(t)

    def _slow_rule(self, t: float) -> RemountEvent | None:
        if self.ref.t_first is None or t - self.ref.t_first < self.day_s + self.mode_s or not self.hours:
            return None
        if (self.hours[-1][0] - self.hours[0][0] + 1) * 3600.0 < self.mode_s:
            return None
        w_near = sum(h[1] for h in self.hours)
        w_all = sum(h[2] for h in self.hours)
        if w_all < self.min_recent_s or w_near >= self.mode_fraction * w_all:
            return None
        recent = _Histogram(self.dirs)
        recent.w = sum(h[3] for h in self.hours)
        recent.sum = sum(h[4] for h in self.hours)
        old, new = self._dominant(self.ref), self._dominant(recent)
        ang = math.acos(max(-1.0, min(1.0, float(old @ new))))
        if ang < self.min_angle:
            return None
        recent.t_first = t
        self.novel = recent  # the new mount's reference
        return self._detected(t, old, new, ang, "slow", self.last_in_set_t or t)

    def _detected(self, t: float, old: np.ndarray, new: np.ndarray, ang: float, rule: str, since: float) -> RemountEvent:
        # the new mount's reference starts from the windows that revealed it and must span a day again
        ev = RemountEvent(float(t), math.degrees(ang), rule, tuple(float(x) for x in old), tuple(float(x) for x in new),
                          float(since))
        self.events.append(ev)
        novel = self.novel
        self._reset(t)
        self.ref = novel  # the new mount's windows so far are its reference
        return ev


# -- window-level sessions (tests, benches) ------------------------------------------------------------
def session_motion(scenario: str = "daily_living", *, seed: int = 0, duration: float = 86400.0,
                   fs_motion: float = 2.0, **scenario_kw: Any) -> Any:
    """The scenario's motion as :func:`session_windows` renders it (pass it there as ``motion``)."""
    from ..scenarios import make_motion  # noqa: PLC0415 (start-up cost: the daemon imports this module, not the simulator)

    return make_motion(scenario, duration=duration, fs=fs_motion, rng=seed, **scenario_kw)


def session_windows(scenario: str = "daily_living", *, seed: int = 0, duration: float = 86400.0, model: Any = None,
                    fs_motion: float = 2.0, sample_fs: float = 200.0, noise_g: float = 0.003,
                    max_window_s: float = 10.0, min_window_s: float = 1.0, temp_c: Any = None,
                    remount_at: float | None = None, remount_rotvec: Any = None, temperature: bool = True,
                    motion: Any = None, **scenario_kw: Any):
    """Quasi-static windows of a simulated session, at window level (fast: a day in ~1 s).

    The scenario (core.scenarios) is rendered at ``fs_motion``; each run of truly still samples is cut into
    windows of at most ``max_window_s``; a window's mean is the true raw = K(T, t) f + o(T, t) of the sensor
    model (core.model.defaults.triad_truth: every catalogue term's linear part, so a planted
    temperature_offset / offset_drift acts) plus the mean of ``sample_fs`` x duration samples of white noise
    ``noise_g`` [g] per axis (cov = the per-sample covariance, n samples). ``temp_c``: a function of time [s]
    replacing the scenario's temperature [°C]. ``remount_at`` [s]: from then on the sensor is rotated on the
    body by ``remount_rotvec`` (f_board -> R^T f_board). ``temperature=False``: windows without aux.
``motion``: the scenario already rendered (``session_motion`` with the same arguments), so sessions that
differ only in sensor, re-mount or temperature share its rendering (the costly part); it is not modified.

    Returns (WindowSet, info) with info["truth"](temp_c, t) -> Calibration and info["f"] the true specific
    forces [g] of the windows (board frame).
    """
    from scipy.spatial.transform import Rotation  # noqa: PLC0415 (start-up cost: scipy.spatial, as below)

    from ..model.defaults import default_model, triad_truth  # noqa: PLC0415 (start-up cost, as make_motion above)

    rng = np.random.default_rng([seed, 7])
    if motion is None:
        motion = session_motion(scenario, seed=seed, duration=duration, fs_motion=fs_motion, **scenario_kw)
    model = default_model(seed) if model is None else model
    still = motion.still
    edges = np.flatnonzero(np.diff(np.concatenate([[0], still.astype(np.int8), [0]])))
    runs = edges.reshape(-1, 2)
    per = max(int(round(max_window_s * fs_motion)), 1)
    lo = max(int(round(min_window_s * fs_motion)), 1)
    R = Rotation.from_rotvec(np.asarray(remount_rotvec, dtype=float)).as_matrix() if remount_rotvec is not None else None
    rows = []  # (i0, i1) of each window in the rendered motion
    for a, b in runs:
        for i0 in range(a, b, per):
            i1 = min(i0 + per, b)
            if i1 - i0 >= lo:
                rows.append((i0, i1))
    m = len(rows)
    cs = np.concatenate([np.zeros((1, 3)), np.cumsum(motion.specific_force, axis=0)])
    ct, cT = np.concatenate([[0.0], np.cumsum(motion.t)]), np.concatenate([[0.0], np.cumsum(motion.temp)])
    i0s, i1s = np.array([r[0] for r in rows], dtype=int).reshape(m), np.array([r[1] for r in rows], dtype=int).reshape(m)
    cnt = (i1s - i0s).astype(float)
    f = (cs[i1s] - cs[i0s]) / np.maximum(cnt, 1)[:, None]
    ts = (ct[i1s] - ct[i0s]) / np.maximum(cnt, 1)
    temps = (np.array([float(temp_c(x)) for x in ts]) if temp_c is not None
             else (cT[i1s] - cT[i0s]) / np.maximum(cnt, 1))
    if R is not None and remount_at is not None:
        f[ts >= remount_at] = f[ts >= remount_at] @ R  # R^T f per row
    # K(T, t), o(T, t) of the model at 257 knots over the session, interpolated (the conditions vary slowly)
    knots = np.linspace(ts.min(), ts.max(), 257) if m else np.zeros(1)
    order_t = np.argsort(ts)
    Tk = np.interp(knots, ts[order_t], temps[order_t]) if m else np.full(1, 25.0)
    Ks, os_ = zip(*[(c.sensitivity, c.offset) for c in (triad_truth(model, temp_c=float(T), t=float(k))
                                                          for T, k in zip(Tk, knots))])
    Ks, os_ = np.array(Ks).reshape(-1, 9), np.array(os_)
    K = np.column_stack([np.interp(ts, knots, Ks[:, j]) for j in range(9)]).reshape(m, 3, 3)
    o = np.column_stack([np.interp(ts, knots, os_[:, j]) for j in range(3)])
    ns = cnt / fs_motion * sample_fs
    sd = noise_g * np.abs(np.diagonal(K, axis1=1, axis2=2))  # per-sample std [raw]
    covs = np.einsum("mi,ij->mij", sd * sd, np.eye(3))
    means = np.einsum("mij,mj->mi", K, f) + o + rng.normal(size=(m, 3)) * sd / np.sqrt(ns)[:, None]
    fs_ = f
    aux = np.asarray(temps, dtype=float).reshape(m, 1) if temperature else np.zeros((m, 0))
    ws = WindowSet(means.reshape(m, 3), covs.reshape(m, 3, 3), ns, ts, aux,
                   np.arange(m, dtype=np.int64), np.arange(m, dtype=np.int64) + 1)
    return ws, {"truth": lambda temp_c=25.0, t=0.0: triad_truth(model, temp_c=temp_c, t=t), "f": np.array(fs_),
                "model": model, "motion_fs": fs_motion}


__all__ = ["RemountDetector", "RemountEvent", "session_motion", "session_windows"]
