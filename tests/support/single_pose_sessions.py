"""One-pose sessions (a temperature chamber, a logger on a desk) written from the physics, with their truth.

Like independent_sessions.py, nothing here calls gravcal's simulator, scenarios or sensor model; the
numbers come from this module's own streams (``SeedSequence([TAG, kind, seed])``). Only the container
(``WindowSet``) is gravcal's.

Physics (a in g, raw in counts), per channel i:

    raw_i(t) = s_i (1 + c_s,i (T - T_ref)) a_i + o_i + c_o,i (T - T_ref) + w_i(t) + n_i(t)

The sensor rests in one pose (gravity along a direction tilted up to 20° from an axis, a random one of
the six) while a chamber steps its temperature between three to four levels, the die following each step
with a time constant of minutes. ``w`` is a slow wander of each channel (an AR(1) of minutes, the drift a
chamber run never quite avoids), ``n`` white noise. A few brief handling moments in other postures
sit at the start and the end. The device states its own calibration ``held_K`` of the gains, off the
truth by ``held_rel_std`` per axis (drawn), with offsets ``held_o`` off by up to 50 mg.

What one pose determines is each channel's reading slope on the temperature; in g per °C along each
axis it is ``truth_mg_per_c`` = (c_o,i + c_s,i s_i a_i) / s_i x 1e3: an offset slope, or, along gravity,
an offset or a gain slope (they read alike).
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
from gravcal.core.windows import WindowSet

TAG = 0x51D0  # this module's stream
T_REF_C = 25.0


@dataclass
class PoseSession:
    windows: WindowSet
    truth_mg_per_c: np.ndarray  # (3,) each axis' reading slope over its true gain [mg/°C]
    held_K: np.ndarray  # the device's own (held) calibration: K [counts per g]
    held_o: np.ndarray  # ... and o [counts]
    held_rel_std: float
    g_dir: np.ndarray  # the pose's gravity in the sensor frame
    n_handling: int  # windows in other postures
    clean_mean: np.ndarray | None = None  # (m, 3) the window means without noise, floor or wander [counts]


def _rng(kind: str, seed: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([TAG, zlib.crc32(kind.encode()), int(seed)]))


def _chamber(rng: np.random.Generator, t: np.ndarray, duration: float) -> np.ndarray:
    """Die temperature [°C]: 3-4 chamber levels between -5 and 40 °C, each followed with a 3-15 min lag."""
    levels = rng.uniform(-5.0, 40.0, int(rng.integers(3, 5)))
    edges = np.linspace(0.0, duration, len(levels) + 1)[:-1]
    tau = rng.uniform(180.0, 900.0)
    temp = np.empty_like(t)
    at = rng.uniform(18.0, 26.0)  # the room, before the first level is reached
    bounds = list(edges[1:]) + [np.inf]
    for e, end, lv in zip(edges, bounds, levels):
        sel = (t >= e) & (t < end)
        temp[sel] = lv + (at - lv) * np.exp(-(t[sel] - e) / tau)
        at = lv + (at - lv) * np.exp(-(min(end, duration) - e) / tau)  # where the die is when the next step starts
    return temp


def _direction(rng: np.random.Generator) -> np.ndarray:
    axis = np.zeros(3)
    axis[rng.integers(3)] = rng.choice([-1.0, 1.0])
    tilt = np.radians(rng.uniform(0.0, 20.0))
    perp = np.cross(axis, rng.normal(size=3))
    perp /= np.linalg.norm(perp)
    return np.cos(tilt) * axis + np.sin(tilt) * perp


def pose_parameters(kind: str, seed: int, held_rel_std: float):
    """The sensor, its pose, its temperature coefficients and the device's held calibration of one session."""
    rng = _rng(kind, seed)
    s = 256.0 * (1 + rng.normal(0, 0.03, 3))
    o = rng.normal(0, 0.08, 3) * s
    c_o = rng.uniform(0.1e-3, 2e-3, 3) * rng.choice([-1, 1], 3) * s  # 0.1-2 mg/°C
    c_s = rng.uniform(0.0, 3e-4, 3) * rng.choice([-1, 1], 3) if kind == "offset_and_gain" else np.zeros(3)
    g = _direction(rng)
    held_K = np.diag(s * (1 + rng.normal(0, held_rel_std, 3))) if held_rel_std > 0 else np.diag(s)
    held_o = o + rng.uniform(-0.05, 0.05, 3) * s
    return rng, s, o, c_o, c_s, g, held_K, held_o


def window_session(seed: int, *, kind: str = "offset", m: int = 200, duration_s: float = 12600.0,
                   noise_g: float = 0.004, floor_g: float = 0.0005, wander_g: float = 0.0003,
                   held_rel_std: float = 0.03, n_handling: int = 6) -> PoseSession:
    """One chamber session as quasi-static windows (their statistics drawn directly, as a detector reports them)."""
    rng, s, o, c_o, c_s, g, held_K, held_o = pose_parameters(kind, seed, held_rel_std)
    fs = 32.0
    n = rng.integers(int(4 * fs), int(20 * fs) + 1, m)
    t0 = np.sort(rng.uniform(300.0, duration_s - 300.0, m))
    t_mid = t0 + 0.5 * (n - 1) / fs
    temp = _chamber(rng, t_mid, duration_s)
    dirs = np.repeat(g[None], m, axis=0)
    h = min(n_handling, m // 10)
    if h:  # handling: brief moments in other postures at the start and the end
        idx = np.r_[np.arange(h // 2), np.arange(m - (h - h // 2), m)]
        other = rng.normal(size=(h, 3))
        dirs[idx] = other / np.linalg.norm(other, axis=1, keepdims=True)
        n[idx] = rng.integers(int(1 * fs), int(4 * fs) + 1, h)
    a = dirs + rng.normal(0, floor_g, (m, 3))
    dT = temp - T_REF_C
    # slow wander: AR(1) with a 10-minute memory sampled at the windows' times
    rho = np.exp(-np.abs(np.diff(t_mid, prepend=t_mid[0])) / 600.0)
    w = np.zeros((m, 3))
    for k in range(m):
        w[k] = (rho[k] * w[k - 1] if k else 0.0) + np.sqrt(1 - rho[k] ** 2) * rng.normal(0, wander_g, 3)
    gain = s * (1 + c_s * dT[:, None])
    mean = gain * a + o + c_o * dT[:, None] + w * s + rng.normal(size=(m, 3)) * (noise_g * s) / np.sqrt(n)[:, None]
    var = (noise_g * s) ** 2
    cov = np.zeros((m, 3, 3))
    cov[:, [0, 1, 2], [0, 1, 2]] = var * rng.chisquare((n - 1)[:, None], (m, 3)) / (n - 1)[:, None]
    start = np.round(t0 * fs).astype(np.int64)
    ws = WindowSet(mean=mean, cov=cov, n=n.astype(float), t=t_mid, aux=np.column_stack([temp, np.full(m, 3.3)]),
                   start=start, end=start + n)
    truth = (c_o + c_s * s * g) / s * 1e3
    clean = gain * dirs + o + c_o * dT[:, None]
    return PoseSession(ws, truth, held_K, held_o, held_rel_std, g, h, clean)


def sample_session(seed: int, *, duration_s: float = 5400.0, fs: float = 16.0, noise_g: float = 0.004,
                   held_rel_std: float = 0.03):
    """One chamber session as samples for the file-level paths: (t [s], raw (N, 3) counts, temp [°C], PoseSession
    without windows). Still throughout, with a minute of handling at either end (three 6 s still moments in other
    postures each, as a chamber's loading and unloading leave)."""
    rng, s, o, c_o, c_s, g, held_K, held_o = pose_parameters("samples", seed, held_rel_std)
    t = np.arange(0.0, duration_s, 1.0 / fs)
    temp = _chamber(rng, t, duration_s)
    a = np.repeat(g[None], t.size, axis=0)
    for lo, hi in ((0.0, 60.0), (duration_s - 60.0, duration_s)):  # handling: turned over and about, with still
        sel = (t >= lo) & (t < hi)                                    # moments of 6 s in other postures between
        ph = 2 * np.pi * (t[sel] - lo) / 20.0
        a[sel] = np.column_stack([np.sin(ph), np.cos(ph) * 0.6, np.cos(ph) * 0.8])
        for k in range(3):
            still = (t >= lo + 10.0 + 15.0 * k) & (t < lo + 16.0 + 15.0 * k)
            d = rng.normal(size=3)
            a[still] = d / np.linalg.norm(d)
    dT = temp - T_REF_C
    raw = s * a + o + c_o * dT[:, None] + rng.normal(0, noise_g, a.shape) * s
    raw = np.round(raw)  # counts
    truth = c_o / s * 1e3
    return t, raw, temp, PoseSession(None, truth, held_K, held_o, held_rel_std, g, 0)
