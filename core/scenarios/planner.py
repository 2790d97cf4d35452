"""Building a plan segment by segment: still postures, smooth turns, gait."""
from __future__ import annotations

from typing import Any

import numpy as np

from .motion import _Q, DEG, E_UP, MOVING, STILL, TURN, WALK, MotionPlan, _unit
from .quaternion import align_quat


class _Planner:
    """Appends segments while tracking the current orientation; stops at ``duration``."""

    def __init__(self, duration: float, fs: float, rng: np.random.Generator, r0: _Q):
        if not (duration > 0 and np.isfinite(duration)):
            raise ValueError(f"scenario duration must be a positive number of seconds, got {duration!r}")
        if not (fs > 0 and np.isfinite(fs)):
            raise ValueError(f"sample rate fs must be positive [Hz], got {fs!r}")
        self.duration, self.fs, self.rng, self.cur = float(duration), float(fs), rng, r0
        self.n = int(round(duration * fs))
        self.rows: list[tuple] = []
        self.t_end = 0.0

    @property
    def full(self) -> bool:
        return self.t_end >= self.duration

    def _add(self, kind, dur, base, axis, amp, freq, lin, heading, posture):
        start = int(round(self.t_end * self.fs))
        self.t_end += dur
        if int(round(self.t_end * self.fs)) > start:  # skip segments shorter than a sample
            self.rows.append((start, dur, kind, base.as_quat(), axis, amp, freq, lin, heading, posture))

    def still(self, dur: float, posture: int, sway_deg: float = 0.5, sway_acc_g: float = 0.002) -> None:
        r = self.rng
        axis = _unit(r.normal(size=3))
        freq = max(1, round(r.uniform(0.2, 0.6) * dur)) / dur  # whole sway cycles
        amp = r.uniform(0.3, 1.0) * sway_deg * DEG
        lin = _unit(r.normal(size=3)) * sway_acc_g * r.uniform(0.5, 1.0)
        self._add(STILL, dur, self.cur, axis, amp, freq, lin, 0.0, posture)

    def turn(self, target: _Q, dur: float | None = None, bump_g: float = 0.1) -> None:
        rel = (self.cur.inv() * target).as_rotvec()
        ang = float(np.linalg.norm(rel))
        axis = rel / ang if ang > 1e-12 else np.array([1.0, 0, 0])
        if dur is None:
            dur = 0.8 + 1.5 * ang / np.pi + self.rng.uniform(0, 0.7)
        lin = np.array([bump_g * self.rng.uniform(0.5, 1.0), 0.0, 0.5 * bump_g * self.rng.uniform(-1, 1)])
        self._add(TURN, dur, self.cur, axis, ang, 0.0, lin, self.rng.uniform(0, 2 * np.pi), MOVING)
        self.cur = target

    def walk(self, dur: float, posture: int, heading: float, pitch_axis_world: np.ndarray, amp_deg: float,
             step_hz: float, vert_g: float, fwd_g: float, lat_g: float, stride: bool = False) -> None:
        axis = _unit(self.cur.inv().apply(pitch_axis_world))
        f = step_hz / 2 if stride else step_hz  # arm swing follows the stride
        freq = max(1, round(f * dur)) / dur
        self._add(WALK, dur, self.cur, axis, amp_deg * DEG, freq, np.array([vert_g, fwd_g, lat_g]), heading, posture)

    def plan(self, name: str, posture_names: tuple[str, ...], temp: dict, supply: dict) -> MotionPlan:
        if not self.rows:
            raise ValueError(f"scenario {name!r}: duration {self.duration} s is shorter than one sample")
        cols = list(zip(*self.rows))
        return MotionPlan(
            name=name, fs=self.fs, n=self.n, start=np.array(cols[0], dtype=np.int64), dur=np.array(cols[1], float),
            kind=np.array(cols[2], dtype=np.int8), base=np.array(cols[3], float), axis=np.array(cols[4], float),
            amp=np.array(cols[5], float), freq=np.array(cols[6], float), lin=np.array(cols[7], float),
            heading=np.array(cols[8], float), posture=np.array(cols[9], dtype=np.int32),
            posture_names=posture_names, temp_profile=temp, supply_profile=supply)


def _rz(a: float) -> _Q:
    return _Q.from_rotvec([0.0, 0.0, a])


def _ry(a: float) -> _Q:
    return _Q.from_rotvec([0.0, a, 0.0])


def _tilt(rng: np.random.Generator, max_deg: float) -> _Q:
    """A random small rotation, angle uniform up to max_deg."""
    return _Q.from_rotvec(_unit(rng.normal(size=3)) * rng.uniform(0, max_deg) * DEG)


def _mount(orientation: int | str | None, rotvec: Any) -> _Q:
    """Board -> body rotation. 1: board z up when standing; 2: gravity equal on x, y, z (Lötters Fig. 5)."""
    if rotvec is not None:
        return _Q.from_rotvec(np.asarray(rotvec, float).reshape(3))
    if orientation in (1, "1", None):
        return _Q.identity()
    if orientation in (2, "2"):
        return _Q(align_quat(E_UP, np.ones(3) / np.sqrt(3)))
    raise ValueError(f"orientation must be 1 (z along gravity) or 2 (gravity equal on three axes), got {orientation!r}")


def _lognormal_s(rng: np.random.Generator, median: float, lo: float, hi: float) -> float:
    return float(np.clip(median * np.exp(rng.normal(0, 0.8)), lo, hi))
