"""A planned motion (segments) and its vectorised rendering; orientation arithmetic (unit quaternions)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .quaternion import inverse_matrices

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
            self._bt_cache = inverse_matrices(self.base)
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


def _unit(v: np.ndarray) -> np.ndarray:
    return np.asarray(v, float) / np.linalg.norm(v)


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
