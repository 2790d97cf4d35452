"""Motion scenarios: what the body-worn board experiences (specific force, rate, temperature, supply).

A scenario is planned once as a list of segments (cheap, one entry per posture or movement),
then rendered for any range of sample indices, vectorised. Rendering depends only on the
sample indices, so a week can be streamed block by block (``MotionPlan.render``) and gives
exactly the samples of a one-shot render.

Conventions: world frame z up; orientation R maps board -> world; the specific force a still
board measures is +1 g up, so f_board = R^T (e_up + a_lin) [g] with a_lin the linear
acceleration [g] in the world frame. Every segment rotates about one fixed board-frame axis
v: R(t) = R_base exp(phi(t) v), hence omega_board = phi'(t) v exactly [rad/s].

Segment kinds: STILL (quasi-static posture with slow sway, ``still`` truth True), TURN (a
smooth minimum-jerk slerp between postures with a small linear-acceleration bump), WALK
(gait: pitch oscillation and 0.3-1 g accelerations at the step frequency).
"""
from __future__ import annotations

import inspect
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

STILL, TURN, WALK = 0, 1, 2
MOVING = -1  # posture label of samples in transitions
E_UP = np.array([0.0, 0.0, 1.0])
DEG = np.pi / 180.0


@dataclass
class Motion:
    """Samples of a scenario. All arrays have length N (rows)."""

    t: np.ndarray  # (N,) time [s]
    specific_force: np.ndarray  # (N, 3) [g], board frame
    omega: np.ndarray  # (N, 3) angular rate [rad/s], board frame
    temp: np.ndarray  # (N,) board temperature [°C]
    vsupply: np.ndarray  # (N,) supply voltage [V]
    still: np.ndarray  # (N,) bool: truly quasi-static (a posture held, only slow sway)
    posture: np.ndarray  # (N,) int label, MOVING (-1) in transitions; see posture_names
    posture_names: tuple[str, ...] = ()  # names of labels 0.. where the scenario has fixed postures
    fs: float = 100.0  # sample rate [Hz]
    name: str = ""

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def slice(self, i0: int, i1: int) -> "Motion":
        return Motion(self.t[i0:i1], self.specific_force[i0:i1], self.omega[i0:i1], self.temp[i0:i1],
                      self.vsupply[i0:i1], self.still[i0:i1], self.posture[i0:i1], self.posture_names,
                      self.fs, self.name)


# ----------------------------------------------------------------------------------------
# smooth profiles
# ----------------------------------------------------------------------------------------
def _minjerk(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """s(u) = 10u^3 - 15u^4 + 6u^5 on [0, 1] and ds/du (zero velocity and acceleration at the ends)."""
    u = np.clip(u, 0.0, 1.0)
    return u**3 * (10 - 15 * u + 6 * u**2), 30 * u**2 * (1 - u) ** 2


@dataclass
class MotionPlan:
    """Segments of a scenario plus slow exogenous profiles; render any sample range."""

    name: str
    fs: float
    n: int  # total samples
    start: np.ndarray  # (S,) first sample of each segment
    dur: np.ndarray  # (S,) planned duration [s]
    kind: np.ndarray  # (S,) STILL / TURN / WALK
    base: np.ndarray  # (S, 4) quaternion (scipy x, y, z, w) of the orientation at segment start
    axis: np.ndarray  # (S, 3) unit rotation axis, board frame
    amp: np.ndarray  # (S,) rotation amplitude [rad] (TURN: total angle)
    freq: np.ndarray  # (S,) sway/step frequency [Hz], adjusted to whole cycles
    lin: np.ndarray  # (S, 3) linear-acceleration amplitudes [g] (meaning depends on kind)
    heading: np.ndarray  # (S,) walking direction [rad] (WALK); bump direction (TURN)
    posture: np.ndarray  # (S,) label
    posture_names: tuple[str, ...] = ()
    temp_profile: dict[str, Any] = field(default_factory=dict)
    supply_profile: dict[str, Any] = field(default_factory=dict)

    @property
    def _base_t(self) -> np.ndarray:
        """(S, 3, 3) world -> board rotation matrices at segment start (cached)."""
        if getattr(self, "_bt_cache", None) is None:
            self._bt_cache = Rotation.from_quat(self.base).inv().as_matrix().reshape(-1, 3, 3)
        return self._bt_cache

    def render(self, i0: int = 0, i1: int | None = None) -> Motion:
        """Samples i0 <= i < i1 (vectorised; independent of how the range is split)."""
        i1 = self.n if i1 is None else min(int(i1), self.n)
        idx = np.arange(int(i0), i1)
        if idx.size == 0:
            raise ValueError(f"render: empty sample range [{i0}, {i1}) of a {self.n}-sample scenario")
        t = idx / self.fs
        # segment of every sample: idx is contiguous, so repeat segment numbers by their overlap
        s0 = int(np.searchsorted(self.start, idx[0], side="right")) - 1
        s1 = int(np.searchsorted(self.start, idx[-1], side="right"))
        edges = np.clip(np.append(self.start[s0 + 1:s1], i1), idx[0], i1)
        seg = np.repeat(np.arange(s0, s1), np.diff(np.concatenate([[idx[0]], edges])))
        tau = (idx - self.start[seg]) / self.fs  # time in segment [s]
        dur = self.dur[seg]
        kind = self.kind[seg]
        amp = self.amp[seg]
        freq = self.freq[seg]
        phi = np.zeros(idx.size)
        dphi = np.zeros(idx.size)
        acc = np.zeros((idx.size, 3))  # world frame [g]

        m = kind == STILL  # sway: phi = A (1 - cos 2 pi f tau)/2, zero value and slope at the ends
        w = 2 * np.pi * freq[m]
        phi[m] = amp[m] * 0.5 * (1 - np.cos(w * tau[m]))
        dphi[m] = amp[m] * 0.5 * w * np.sin(w * tau[m])
        lm = self.lin[seg[m]]
        acc[m] = lm * np.sin(2 * w * tau[m])[:, None]  # tiny trunk-sway acceleration

        m = kind == TURN
        s, ds = _minjerk(tau[m] / dur[m])
        phi[m] = amp[m] * s
        dphi[m] = amp[m] * ds / dur[m]
        h = self.heading[seg[m]]
        bump = self.lin[seg[m], 0] * np.sin(2 * np.pi * np.clip(tau[m] / dur[m], 0, 1))  # zero net velocity
        acc[m, 0] = bump * np.cos(h)
        acc[m, 1] = bump * np.sin(h)
        acc[m, 2] = self.lin[seg[m], 2] * np.sin(2 * np.pi * np.clip(tau[m] / dur[m], 0, 1))

        m = kind == WALK  # gait, tapered in/out over 1 s so rate and acceleration start at zero
        ramp = np.minimum(1.0, np.minimum(tau[m], dur[m] - tau[m]) / np.minimum(1.0, dur[m] / 2))
        wr, dwr = _minjerk(ramp)
        dwr = dwr * np.where(tau[m] < dur[m] / 2, 1.0, -1.0) / np.minimum(1.0, dur[m] / 2)
        wr = np.where(ramp >= 1.0, 1.0, wr)
        dwr = np.where(ramp >= 1.0, 0.0, dwr)
        w = 2 * np.pi * freq[m]
        osc = np.sin(w * tau[m])
        phi[m] = amp[m] * osc * wr
        dphi[m] = amp[m] * (w * np.cos(w * tau[m]) * wr + osc * dwr)
        lw = self.lin[seg[m]]  # (vertical, forward, lateral) amplitudes [g]
        h = self.heading[seg[m]]
        vert = lw[:, 0] * (np.sin(w * tau[m]) + 0.3 * np.sin(2 * w * tau[m] + 0.7))
        fwd = lw[:, 1] * np.sin(w * tau[m] + 1.2)
        lat = lw[:, 2] * np.sin(0.5 * w * tau[m])  # medio-lateral sway at the stride frequency
        acc[m, 0] = wr * (fwd * np.cos(h) - lat * np.sin(h))
        acc[m, 1] = wr * (fwd * np.sin(h) + lat * np.cos(h))
        acc[m, 2] = wr * vert

        ax = self.axis[seg]
        # f = exp(phi v)^T R_base^T (e_up + acc): gather R_base^T, then Rodrigues with angle -phi.
        # Explicit element sums (no BLAS) keep every row identical whatever the block split.
        x = E_UP + acc
        bt = self._base_t[seg]
        y = bt[:, :, 0] * x[:, 0:1] + bt[:, :, 1] * x[:, 1:2] + bt[:, :, 2] * x[:, 2:3]
        c, s_ = np.cos(phi)[:, None], np.sin(phi)[:, None]
        vy = (ax[:, 0] * y[:, 0] + ax[:, 1] * y[:, 1] + ax[:, 2] * y[:, 2])[:, None]
        f = y * c - np.cross(ax, y) * s_ + ax * (vy * (1.0 - c))
        omega = dphi[:, None] * ax
        still = kind == STILL
        return Motion(t=t, specific_force=f, omega=omega, temp=_profile(self.temp_profile, t),
                      vsupply=_profile(self.supply_profile, t), still=still, posture=self.posture[seg].copy(),
                      posture_names=self.posture_names, fs=self.fs, name=self.name)


def _profile(p: dict[str, Any], t: np.ndarray) -> np.ndarray:
    """end + (start - end) exp(-t/tau) + slope t + sum a_i sin(2 pi t / period_i + phase_i), clipped."""
    y = p["end"] + (p["start"] - p["end"]) * np.exp(-t / p["tau"]) + p.get("slope", 0.0) * t
    for a, period, ph in p.get("waves", []):
        y = y + a * np.sin(2 * np.pi * t / period + ph)
    lo, hi = p.get("clip", (-np.inf, np.inf))
    return np.clip(y, lo, hi)


def _temp_profile(kind: str, rng: np.random.Generator) -> dict[str, Any]:
    if kind == "body":  # logger warms from room to skin temperature, slow diurnal swing
        return {"start": rng.uniform(22.0, 26.0), "end": rng.uniform(31.0, 33.0), "tau": rng.uniform(600, 1500),
                "waves": [(0.6, 86400.0, rng.uniform(0, 2 * np.pi)), (0.3, rng.uniform(2000, 6000),
                                                                       rng.uniform(0, 2 * np.pi))]}
    if kind == "room":
        t0 = rng.uniform(21.0, 25.0)
        return {"start": t0, "end": t0 + rng.uniform(-0.5, 0.5), "tau": 1800.0,
                "waves": [(0.1, rng.uniform(600, 1800), rng.uniform(0, 2 * np.pi))]}
    raise ValueError(f"unknown temperature profile {kind!r}; use 'body' or 'room'")


def _supply_profile(rng: np.random.Generator) -> dict[str, Any]:
    """A 3.0-3.3 V supply: slow battery droop (~0.03 V/day) plus a few mV of ripple."""
    v0 = rng.uniform(3.2, 3.3)
    return {"start": v0, "end": v0, "tau": 1.0, "slope": -0.03 / 86400.0,
            "waves": [(0.004, rng.uniform(20, 60), rng.uniform(0, 2 * np.pi))], "clip": (3.0, 3.3)}


class _Q:
    """One rotation as a unit quaternion (x, y, z, w: scipy's order). Planning composes tens of
    thousands of single rotations; scipy's Rotation costs ~100 µs per product, this ~2 µs."""

    __slots__ = ("q",)

    def __init__(self, q: Any):
        self.q = np.asarray(q, dtype=float)

    @classmethod
    def identity(cls) -> "_Q":
        return cls([0.0, 0.0, 0.0, 1.0])

    @classmethod
    def from_rotvec(cls, v: Any) -> "_Q":
        x, y, z = (float(c) for c in v)
        a = math.sqrt(x * x + y * y + z * z)
        s = math.sin(a / 2) / a if a > 1e-12 else 0.5
        return cls([x * s, y * s, z * s, math.cos(a / 2)])

    @classmethod
    def from_scipy(cls, r: Rotation) -> "_Q":
        return cls(r.as_quat())

    @classmethod
    def random(cls, rng: np.random.Generator) -> "_Q":
        return cls(_unit(rng.normal(size=4)))  # uniform on SO(3)

    def __mul__(self, other: "_Q") -> "_Q":
        x1, y1, z1, w1 = self.q
        x2, y2, z2, w2 = other.q
        return _Q([w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2, w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                   w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2, w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2])

    def inv(self) -> "_Q":
        x, y, z, w = self.q
        return _Q([-x, -y, -z, w])

    def apply(self, v: Any) -> np.ndarray:
        u, w = self.q[:3], self.q[3]
        v = np.asarray(v, float)
        t = 2.0 * np.cross(u, v)
        return v + w * t + np.cross(u, t)

    def as_rotvec(self) -> np.ndarray:
        q = self.q if self.q[3] >= 0 else -self.q
        n = math.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2)
        if n < 1e-15:
            return np.zeros(3)
        return q[:3] / n * (2.0 * math.atan2(n, q[3]))

    def as_quat(self) -> np.ndarray:
        return self.q.copy()


# ----------------------------------------------------------------------------------------
# planning
# ----------------------------------------------------------------------------------------
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


def _unit(v: np.ndarray) -> np.ndarray:
    return np.asarray(v, float) / np.linalg.norm(v)


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
        r, _ = Rotation.align_vectors([E_UP], [np.ones(3) / np.sqrt(3)])
        return _Q.from_scipy(r)
    raise ValueError(f"orientation must be 1 (z along gravity) or 2 (gravity equal on three axes), got {orientation!r}")


def _lognormal_s(rng: np.random.Generator, median: float, lo: float, hi: float) -> float:
    return float(np.clip(median * np.exp(rng.normal(0, 0.8)), lo, hi))


# --- scenarios --------------------------------------------------------------------------
def _plan_static(duration, fs, rng, *, rotvec=None, sway_deg=0.0, temp_profile="room"):
    r0 = _Q.from_rotvec(np.asarray(rotvec, float).reshape(3)) if rotvec is not None else _Q.random(rng)
    p = _Planner(duration, fs, rng, r0)
    p.still(duration, 0, sway_deg=sway_deg, sway_acc_g=0.0)
    return p.plan("static", ("static",), _temp_profile(temp_profile, rng), _supply_profile(rng))


def _plan_loetters(duration, fs, rng, *, orientation=1, theta_max_deg=90.0, p_stand=0.3, still_s=(3.0, 15.0),
                   sway_deg=0.5, mount_rotvec=None, temp_profile="body"):
    """Lötters 1998 sec. 3: postures spread symmetrically up to theta from standing (Fig. 6)."""
    theta_max = float(theta_max_deg)
    if not 0.0 <= theta_max <= 180.0:
        raise ValueError(f"theta_max_deg must be within 0..180°, got {theta_max_deg!r}")
    mount = _mount(orientation, mount_rotvec)
    p = _Planner(duration, fs, rng, mount)
    cos_max = np.cos(theta_max * DEG)
    label = 0
    first = True
    while not p.full:
        if first or rng.random() < p_stand:
            theta, lab = 0.0, 0
        else:  # uniform over the spherical cap of half-angle theta_max
            theta = np.arccos(rng.uniform(cos_max, 1.0))
            label += 1
            lab = label
        az = rng.uniform(0, 2 * np.pi)
        tilt = _Q.from_rotvec(theta * np.array([np.cos(az), np.sin(az), 0.0]))
        target = tilt * _rz(rng.uniform(-np.pi, np.pi)) * mount
        if not first:
            p.turn(target)
        else:
            p.cur = target
        first = False
        # sway tilts a little beyond theta_max; keep it inside so postures respect the cap
        p.still(rng.uniform(*still_s), lab, sway_deg=sway_deg)
    return p.plan("loetters", (), _temp_profile(temp_profile, rng), _supply_profile(rng))


SIX_FACES = ("+x up", "-x up", "+y up", "-y up", "+z up", "-z up")


def _face_rotation(face: int) -> _Q:
    axis = np.zeros(3)
    axis[face // 2] = 1.0 if face % 2 == 0 else -1.0
    if face // 2 == 2:  # align_vectors is ill-defined for antiparallel vectors; z faces explicitly
        return _Q.identity() if face == 4 else _Q.from_rotvec([np.pi, 0, 0])
    r, _ = Rotation.align_vectors([E_UP], [axis])
    return _Q.from_scipy(r)


def _plan_six_position(duration, fs, rng, *, hold_s=(8.0, 15.0), handling_s=(3.0, 6.0), tilt_deg=3.0,
                       temp_profile="room"):
    """Bragge-style: each face up and down in turn, handled between, repeated to fill the duration."""
    order = (4, 5, 0, 1, 2, 3)
    p = _Planner(duration, fs, rng, _face_rotation(order[0]))
    k = 0
    while not p.full:
        face = order[k % 6]
        target = _rz(rng.uniform(-np.pi, np.pi)) * _tilt(rng, tilt_deg) * _face_rotation(face)
        if k:
            p.turn(target, dur=rng.uniform(*handling_s), bump_g=0.3)
        else:
            p.cur = target
        p.still(rng.uniform(*hold_s), face, sway_deg=0.05, sway_acc_g=0.0005)
        k += 1
    return p.plan("six_position", SIX_FACES, _temp_profile(temp_profile, rng), _supply_profile(rng))


DAILY_POSTURES = ("stand", "sit", "lie_back", "lie_left", "lie_right", "lie_front", "walk")
_P = {name: i for i, name in enumerate(DAILY_POSTURES)}


def _body(posture: str, heading: float, rng: np.random.Generator) -> _Q:
    """Body (x forward, y left, z up) -> world for a posture, with natural variation."""
    yaw = _rz(heading)
    if posture in ("stand", "walk"):
        return yaw * _ry(rng.normal(0, 3) * DEG)
    if posture == "sit":
        return yaw * _ry(-rng.uniform(10, 30) * DEG)  # pelvis/trunk leaning back
    roll = {"lie_back": 0.0, "lie_left": np.pi / 2, "lie_right": -np.pi / 2, "lie_front": np.pi}[posture]
    return yaw * _ry(-np.pi / 2) * _rz(roll + rng.normal(0, 8) * DEG) * _tilt(rng, 5)


def _arm(posture: str, rng: np.random.Generator) -> _Q:
    """Forearm (wrist sensor) relative to the body: hanging when standing, resting on the lap
    when sitting, anywhere when lying; varies from one still period to the next."""
    nominal = {"stand": _ry(np.pi / 2), "walk": _ry(np.pi / 2), "sit": _ry(0.3)}.get(posture)
    if nominal is None:
        return _Q.random(rng)
    return nominal * _tilt(rng, 40 if posture == "sit" else 20)


def _plan_daily_living(duration, fs, rng, *, placement="waist", mount_rotvec=None, day_start_h=8.0,
                       bed_episode=None, temp_profile="body"):
    """Stand, sit, walk, lie down (back, sides) with quasi-static periods of varying length.

    Days follow the clock from day_start_h; nights (23:00-07:00) are spent lying with turns.
    Records shorter than 6 h contain one going-to-bed episode (Lötters: needed to calibrate
    all parameters), unless bed_episode=False.
    """
    if placement not in ("waist", "wrist"):
        raise ValueError(f"placement must be 'waist' or 'wrist', got {placement!r}")
    wrist = placement == "wrist"
    mount = _mount(None, mount_rotvec)
    heading = rng.uniform(0, 2 * np.pi)

    def sensor(posture: str) -> _Q:
        body = _body(posture, heading, rng)
        return body * (_arm(posture, rng) if wrist else _Q.identity()) * mount

    p = _Planner(duration, fs, rng, sensor("stand"))
    bed = bool(duration < 6 * 3600) if bed_episode is None else bool(bed_episode)
    bed_at = rng.uniform(0.3, 0.6) * duration if bed else np.inf
    state = "stand"

    def hold(posture: str, total: float, median: float) -> None:
        """Stay in a posture for `total` s as several still periods with small fidgets between."""
        end = p.t_end + total
        while p.t_end < end and not p.full:
            p.still(min(_lognormal_s(rng, median, 2.0, 1800.0), max(end - p.t_end, 0.5)), _P[posture],
                    sway_deg=0.8 if posture in ("stand", "sit") else 0.3)
            if p.t_end < end:
                fidget = p.cur * _tilt(rng, 15 if wrist else 6)
                p.turn(fidget, dur=rng.uniform(0.8, 2.0), bump_g=0.05)

    def lie_down(minutes: tuple[float, float], sides: int) -> None:
        nonlocal state
        p.turn(sensor("sit"), bump_g=0.15)
        p.still(rng.uniform(2, 6), _P["sit"])
        for k in range(sides):
            side = "lie_back" if k == 0 else str(rng.choice(["lie_left", "lie_right", "lie_back", "lie_front"],
                                                            p=[0.35, 0.35, 0.2, 0.1]))
            p.turn(sensor(side), bump_g=0.1)
            hold(side, rng.uniform(*minutes) * 60, median=120.0)
            if p.full:
                return
        p.turn(sensor("sit"), bump_g=0.15)
        p.still(rng.uniform(2, 6), _P["sit"])
        state = "sit"

    while not p.full:
        clock_h = (day_start_h + p.t_end / 3600.0) % 24.0
        if clock_h >= 23.0 or clock_h < 7.0:  # night
            lie_down((10, 60), int(rng.integers(6, 14)))
            continue
        if p.t_end >= bed_at:
            bed_at = np.inf
            lie_down((0.5, 2.0), 3)
            continue
        nxt = {"stand": ["walk", "sit", "stand"], "walk": ["stand", "sit"], "sit": ["stand", "sit"]}[state]
        probs = {"stand": [0.5, 0.3, 0.2], "walk": [0.7, 0.3], "sit": [0.6, 0.4]}[state]
        new = str(rng.choice(nxt, p=probs))
        if new == "walk":
            heading = rng.uniform(0, 2 * np.pi)
            p.turn(sensor("walk"), bump_g=0.1)
            lateral = np.array([-np.sin(heading), np.cos(heading), 0.0])
            step = rng.uniform(1.6, 2.0)
            if wrist:
                p.walk(rng.uniform(10, 120), _P["walk"], heading, lateral, rng.uniform(15, 30), step,
                       rng.uniform(0.4, 0.8), rng.uniform(0.4, 0.8), 0.15, stride=True)
            else:
                p.walk(rng.uniform(10, 120), _P["walk"], heading, lateral, rng.uniform(2, 5), step,
                       rng.uniform(0.3, 0.6), rng.uniform(0.15, 0.3), 0.1)
        else:
            p.turn(sensor(new), bump_g=0.15 if new != state else 0.05)
            hold(new, _lognormal_s(rng, 60.0 if new == "stand" else 300.0, 3.0, 3600.0),
                 median=8.0 if new == "stand" else 40.0)
        state = new
    return p.plan("daily_living", DAILY_POSTURES, _temp_profile(temp_profile, rng), _supply_profile(rng))


SAGITTAL_POSTURES = ("stand", "sit", "bend", "kneel", "prostrate", "lie_back", "lie_left", "lie_right", "lie_front",
                     "walk")
_S = {name: i for i, name in enumerate(SAGITTAL_POSTURES)}


def _rx(a: float) -> _Q:
    return _Q.from_rotvec([a, 0.0, 0.0])


def _plan_sagittal_postures(duration, fs, rng, *, mount_pitch_deg=None, lateral_deg=0.5, p_lie=0.35,
                            still_s=(3.0, 15.0), temp_profile="body"):
    """Posture transitions with the board's y axis medio-lateral (a trunk- or waist-worn logger):
    sit-to-stand, bending to pick something up, lying down and getting up, short walks, turns
    on the spot, as in a mobility/transfer protocol or a morning at home.

    Standing: board x forward, y to the left (medio-lateral: the ENC-03J's sensitive axis),
    z up; the belt clip tilts the board by ``mount_pitch_deg`` about y (drawn within ±15° when
    None). The transitions between stand, sit, bend, lie_back (and back up) are pitch rotations
    about board y (sitting up goes through a forward lean, standing up from a chair too), so the
    gyro sees the whole rotation; rolls to the sides and the front while lying turn about the
    body's long axis (board z: not seen by the gyro, but they give the accelerometer gravity
    along ±y); turns on the spot are about the vertical (gravity unchanged); walking pitches
    the trunk about y by a few degrees at the step frequency. Each posture also tilts sideways
    by N(0, ``lateral_deg``) (a small rotation the gyro cannot see). Peak rates stay below
    ~170 °/s (a 80° bend in 0.9 s), inside the ENC-03J's ±300 °/s.

    A lying episode (lie back, maybe roll to a side and the front, roll back, sit up, stand up)
    follows with probability ``p_lie`` after each standing period, and at the latest after four
    episodes without one (the accelerometer needs gravity along ±y for its calibration).
    """
    mount_pitch = rng.uniform(-15.0, 15.0) if mount_pitch_deg is None else float(mount_pitch_deg)
    if not abs(mount_pitch) <= 60.0:
        raise ValueError(f"mount_pitch_deg must be within ±60° (board y stays medio-lateral), got {mount_pitch_deg!r}")
    if not 0.0 <= float(lateral_deg) <= 5.0:
        raise ValueError(f"lateral_deg must be within 0..5° (a sideways lean, not a roll), got {lateral_deg!r}")
    if not 0.0 <= float(p_lie) <= 1.0:
        raise ValueError(f"p_lie must be a probability, got {p_lie!r}")
    mount = _ry(mount_pitch * DEG)
    heading = rng.uniform(-np.pi, np.pi)

    def lateral() -> _Q:
        return _rx(rng.normal(0.0, lateral_deg) * DEG)

    def trunk(pitch_deg: float, roll: float = 0.0) -> _Q:
        """Sensor orientation: heading, then trunk pitch about the medio-lateral axis, then (lying)
        the roll about the body's long axis, then a small sideways tilt, then the clip."""
        return _rz(heading) * _ry(pitch_deg * DEG) * _rz(roll) * lateral() * mount

    p = _Planner(duration, fs, rng, trunk(rng.normal(0, 2)))

    def hold(posture: str, lo: float | None = None, hi: float | None = None) -> None:
        a, b = still_s
        p.still(rng.uniform(a if lo is None else lo, b if hi is None else hi), _S[posture],
                sway_deg=0.3 if posture.startswith("lie") else 0.6)

    def move(target: _Q, dur: float, bump_g: float = 0.1) -> None:
        p.turn(target, dur=dur, bump_g=bump_g)

    def stand_up() -> None:
        move(trunk(rng.uniform(25, 45)), rng.uniform(0.7, 1.1), 0.15)  # lean forward over the feet, then rise
        move(trunk(rng.normal(0, 2)), rng.uniform(0.8, 1.4), 0.2)

    def sit_down() -> None:
        move(trunk(-rng.uniform(5, 25)), rng.uniform(1.0, 2.0), 0.15)  # leaning back against the backrest

    def lie_episode() -> None:
        sit_down()
        hold("sit", 2.0, 6.0)
        move(trunk(-90 + rng.normal(0, 4)), rng.uniform(1.5, 3.0))  # lie back
        hold("lie_back")
        if rng.random() < 0.7:  # roll onto a side (about the body's long axis), maybe on to the front
            side = rng.choice([-1.0, 1.0])
            name = "lie_left" if side > 0 else "lie_right"
            move(trunk(-90 + rng.normal(0, 4), side * (np.pi / 2 + rng.normal(0, 0.08))), rng.uniform(1.2, 2.5))
            hold(name)
            if rng.random() < 0.3:
                move(trunk(-90 + rng.normal(0, 4), side * (np.pi + rng.normal(0, 0.05))), rng.uniform(1.2, 2.5))
                hold("lie_front")
                move(trunk(-90 + rng.normal(0, 4), side * (np.pi / 2 + rng.normal(0, 0.08))), rng.uniform(1.2, 2.5))
                hold(name, 1.0, 4.0)  # back over the same side
            move(trunk(-90 + rng.normal(0, 4)), rng.uniform(1.5, 3.0))  # back onto the back
            hold("lie_back", 2.0, 8.0)
        move(trunk(-rng.uniform(5, 25)), rng.uniform(1.5, 3.0), 0.2)  # sit up
        hold("sit", 2.0, 8.0)
        stand_up()

    def bend(deep: bool) -> None:
        """Pick something up with bent knees, or reach the floor with straight legs (deep: hip and
        lumbar flexion together take the trunk past horizontal)."""
        move(trunk(rng.uniform(95, 120) if deep else rng.uniform(35, 80)), rng.uniform(1.2, 2.0), 0.15)
        hold("bend", 1.5, 6.0)
        move(trunk(rng.normal(0, 2)), rng.uniform(1.2, 2.0), 0.15)

    def kneel() -> None:
        """Kneel, then the forehead to the floor (looking under a bed, prayer, a stretch)."""
        move(trunk(rng.normal(5, 3)), rng.uniform(1.2, 2.0), 0.2)
        hold("kneel", 1.5, 5.0)
        move(trunk(rng.uniform(120, 150)), rng.uniform(1.5, 2.5), 0.1)
        hold("prostrate", 2.0, 8.0)
        move(trunk(rng.normal(5, 3)), rng.uniform(1.5, 2.5), 0.1)
        hold("kneel", 1.5, 5.0)
        stand_up()

    # episodes between standing periods; a lying one and one with the trunk past horizontal at
    # least every fourth episode (the accelerometer's sensitivities need gravity against +z too)
    since_lie = since_floor = 0
    while not p.full:
        hold("stand")
        if p.full:
            break
        since_lie, since_floor = since_lie + 1, since_floor + 1
        if since_lie >= 4 or rng.random() < p_lie:
            since_lie = 0
            lie_episode()
            continue
        what = "floor" if since_floor >= 4 else rng.choice(["sit", "bend", "floor", "walk", "turn"],
                                                            p=[0.25, 0.3, 0.15, 0.15, 0.15])
        if what == "sit":
            sit_down()
            hold("sit")
            stand_up()
        elif what == "bend":
            deep = rng.random() < 0.5
            since_floor = 0 if deep else since_floor
            bend(deep)
        elif what == "floor":
            since_floor = 0
            kneel() if rng.random() < 0.5 else bend(True)
        elif what == "walk":
            lateral_axis = np.array([-np.sin(heading), np.cos(heading), 0.0])
            p.walk(rng.uniform(5, 25), _S["walk"], heading, lateral_axis, rng.uniform(2, 5), rng.uniform(1.6, 2.0),
                   rng.uniform(0.3, 0.6), rng.uniform(0.15, 0.3), 0.1)
        else:  # turn on the spot: about the vertical, gravity unchanged in the board frame
            turn = rng.uniform(45, 180) * rng.choice([-1.0, 1.0]) * DEG
            heading += turn
            move(_rz(turn) * p.cur, 0.8 + 1.5 * abs(turn) / np.pi + rng.uniform(0, 0.5), 0.05)
    return p.plan("sagittal_postures", SAGITTAL_POSTURES, _temp_profile(temp_profile, rng), _supply_profile(rng))


_PLANNERS = {
    "daily_living": _plan_daily_living,
    "loetters": _plan_loetters,
    "sagittal_postures": _plan_sagittal_postures,
    "six_position": _plan_six_position,
    "static": _plan_static,
}
SCENARIOS: tuple[str, ...] = tuple(_PLANNERS)


def plan_motion(name: str, *, duration: float = 600.0, fs: float = 100.0, rng: Any = None, **kw: Any) -> MotionPlan:
    """Plan a scenario (segments only; cheap even for a week). rng: Generator or seed."""
    if name not in _PLANNERS:
        raise ValueError(f"unknown scenario {name!r}; choose one of {', '.join(SCENARIOS)}")
    allowed = [k for k, prm in inspect.signature(_PLANNERS[name]).parameters.items() if prm.kind == prm.KEYWORD_ONLY]
    unknown = sorted(set(kw) - set(allowed))
    if unknown:
        raise ValueError(f"scenario {name!r} has no option(s) {unknown}; options: {allowed}")
    return _PLANNERS[name](float(duration), float(fs), np.random.default_rng(rng), **kw)


def make_motion(name: str, *, duration: float = 600.0, fs: float = 100.0, rng: Any = None, **kw: Any) -> Motion:
    """Render a whole scenario: names in SCENARIOS; scenario options as keywords.

    daily_living: placement="waist"|"wrist", mount_rotvec, day_start_h, bed_episode.
    loetters: orientation=1|2, theta_max_deg, p_stand, still_s=(min, max), sway_deg.
    six_position: hold_s, handling_s, tilt_deg.   static: rotvec (default random), sway_deg.
    All: temp_profile="body"|"room".
    """
    return plan_motion(name, duration=duration, fs=fs, rng=rng, **kw).render()
