"""Foot-instep motions for the single-axis gyro (Scapellato et al. 2005, Fig. 2).

The board sits on the foot instep: board x forward along the foot, y medio-lateral (the
ENC-03J's sensitive axis), z up from the instep. Motion is in the sagittal plane: the board
pitches about y by theta(t) (board -> world R = R_y(theta), so omega_board = theta' e_y exactly)
and translates in (X forward, Z up). The specific force the board feels is
f_board = R^T (a_world / g + e_up) [g].

Two motions, both returned as ``core.scenarios.Motion`` (simulate() takes them) plus the truth
the tests and reports need:

- ``stair_climb``: foot placements from the ground onto steps of known height h (the
  paper's calibration movement): stance (foot flat on a tread, still), swing (minimum-jerk
  forward/up displacement with a toe-clearance bump; the foot plantarflexes at push-off and
  returns to the tread's pitch at landing, theta(s) = -(A sin^2(pi s) + B sin(2 pi s) sin^2(pi s)),
  A 20-32°, |B| < 10°), stance on the next tread.
- ``foot_poses``: everyday sagittal poses held for a few seconds (foot flat, toes raised,
  heel raised, foot on a footrest, ...) joined by minimum-jerk pitch changes, the raw material
  of the pose-to-pose method.

Derivatives are central differences of the analytic positions with h = 1e-4 s (error ~1e-9
of the signal), so the specific force and the trajectory agree far below the sensor noise.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..model.defaults import default_model, triad_truth
from ..model.enc03j import gyro_truth
from ..samples import raw_triad
from ..scenarios import Motion
from ..simulate import simulate

G = 9.80665  # m/s^2 per g
H_DIFF = 1e-4  # s


def _minjerk(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10 - 15 * s + 6 * s**2)


def _diff(f: Callable[[np.ndarray], np.ndarray], t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    f0, fp, fm = f(t), f(t + H_DIFF), f(t - H_DIFF)
    return f0, (fp - fm) / (2 * H_DIFF), (fp - 2 * f0 + fm) / H_DIFF**2


@dataclass
class Segment:
    t0: float  # start [s]
    dur: float  # [s]
    x0: float  # forward position at start [m]
    z0: float  # height at start [m]
    theta0: float  # pitch at start [rad]
    dx: float = 0.0  # forward displacement [m]
    dz: float = 0.0  # vertical displacement [m]
    clearance: float = 0.0  # toe-clearance bump [m]
    pitch_amp: float = 0.0  # swing pitch excursion A [rad]: A sin^2(pi s)
    pitch_skew: float = 0.0  # its asymmetry B [rad]: B sin(2 pi s) sin^2(pi s)
    dtheta: float = 0.0  # net pitch change (pose transitions) [rad]
    sway: float = 0.0  # pitch sway amplitude while still [rad]
    sway_hz: float = 0.3
    still: bool = True


def _trajectory(segs: list[Segment], t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """X, Z [m], theta [rad] at times t, segment by segment (vectorised per segment)."""
    X, Z, TH = np.zeros_like(t), np.zeros_like(t), np.zeros_like(t)
    starts = np.array([s.t0 for s in segs])
    idx = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(segs) - 1)
    for k, sg in enumerate(segs):
        m = idx == k
        s = (t[m] - sg.t0) / sg.dur
        mj = _minjerk(s)
        sc = np.clip(s, 0, 1)
        X[m] = sg.x0 + sg.dx * mj
        Z[m] = sg.z0 + sg.dz * mj + sg.clearance * np.sin(np.pi * sc) ** 4
        TH[m] = (sg.theta0 + sg.dtheta * mj + sg.pitch_amp * np.sin(np.pi * sc) ** 2
                 + sg.pitch_skew * np.sin(2 * np.pi * sc) * np.sin(np.pi * sc) ** 2
                 + sg.sway * np.sin(np.pi * sc) ** 2 * np.sin(2 * np.pi * sg.sway_hz * (t[m] - sg.t0)))
    return X, Z, TH


def _motion(segs: list[Segment], fs: float, name: str, temp_c: float, vsupply: float) -> Motion:
    n = int(round((segs[-1].t0 + segs[-1].dur) * fs))
    t = np.arange(n) / fs
    (x, vx, ax), (z, vz, az), (th, dth, _) = (_diff(lambda tt, i=i: _trajectory(segs, tt)[i], t) for i in range(3))
    fw = np.column_stack([ax / G, np.zeros(n), az / G + 1.0])  # world specific force [g]
    c, s = np.cos(th), np.sin(th)
    # f_board = R_y(theta)^T f_world
    fb = np.column_stack([c * fw[:, 0] - s * fw[:, 2], fw[:, 1], s * fw[:, 0] + c * fw[:, 2]])
    omega = np.column_stack([np.zeros(n), dth, np.zeros(n)])
    starts = np.array([sg.t0 for sg in segs])
    seg = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(segs) - 1)
    still = np.array([sg.still for sg in segs])[seg]
    return Motion(t=t, specific_force=fb, omega=omega, temp=np.full(n, temp_c), vsupply=np.full(n, vsupply),
                  still=still, posture=np.where(still, seg, -1).astype(np.int32), fs=fs, name=name)


@dataclass
class StairClimb:
    motion: Motion
    stances: list[tuple[int, int]]  # (start, end) sample ranges of the stance phases (truth)
    step_height_m: float
    heights_m: np.ndarray  # true height gained in each swing [m]
    pitch_amp_rad: np.ndarray  # swing pitch amplitude of each swing


def stair_climb(rng: np.random.Generator, *, n_steps: int = 10, step_height_m: float = 0.17, step_depth_m: float = 0.28,
                fs: float = 100.0, stance_s: tuple[float, float] = (1.5, 2.5), swing_s: tuple[float, float] = (0.8, 1.1),
                pitch_amp_deg: tuple[float, float] = (20.0, 32.0), mount_pitch_deg: float = -10.0,
                temp_c: float = 30.0, vsupply: float = 3.3) -> StairClimb:
    """n_steps foot placements onto steps of step_height_m [m] (the foot waits on each tread)."""
    if not (step_height_m > 0 and np.isfinite(step_height_m)):
        raise ValueError(f"step height must be a known positive height [m], got {step_height_m!r}")
    segs: list[Segment] = []
    t = x = z = 0.0
    th0 = np.deg2rad(mount_pitch_deg)  # the instep is inclined on a flat foot
    amps = []
    for k in range(n_steps + 1):
        d = float(rng.uniform(*stance_s))
        segs.append(Segment(t, d, x, z, th0, sway=np.deg2rad(0.2), sway_hz=float(rng.uniform(0.2, 0.5))))
        t += d
        if k == n_steps:
            break
        d = float(rng.uniform(*swing_s))
        a = float(np.deg2rad(rng.uniform(*pitch_amp_deg)))
        b = float(np.deg2rad(rng.uniform(-10.0, 10.0)))
        amps.append(a)
        segs.append(Segment(t, d, x, z, th0, dx=step_depth_m * float(rng.uniform(0.9, 1.1)), dz=step_height_m,
                            clearance=float(rng.uniform(0.03, 0.06)), pitch_amp=-a, pitch_skew=-b, still=False))
        x += segs[-1].dx
        z += step_height_m
        t += d
    motion = _motion(segs, fs, "stair_climb", temp_c, vsupply)
    stances = [(int(round(sg.t0 * fs)), int(round((sg.t0 + sg.dur) * fs))) for sg in segs if sg.still]
    return StairClimb(motion, stances, float(step_height_m), np.full(n_steps, float(step_height_m)), np.array(amps))


def foot_poses(rng: np.random.Generator, *, n_poses: int = 30, fs: float = 100.0, hold_s: tuple[float, float] = (3.0, 8.0),
               move_s: tuple[float, float] = (0.8, 2.0), pitch_range_deg: tuple[float, float] = (-45.0, 35.0),
               min_change_deg: float = 15.0, temp_c: float = 30.0, vsupply: float = 3.3) -> Motion:
    """Everyday sagittal foot poses (pitch drawn in pitch_range_deg) joined by pitch changes of at
    least min_change_deg, with a small lift of the foot during each change and standing sway in
    the holds."""
    lo, hi = pitch_range_deg
    if not 0.0 <= min_change_deg < hi - lo:
        raise ValueError(f"min_change_deg must be within 0 and the pitch range ({hi - lo:g}°), got {min_change_deg!r}")
    segs: list[Segment] = []
    t = 0.0
    th = np.deg2rad(rng.uniform(*pitch_range_deg))
    for k in range(n_poses):
        d = float(rng.uniform(*hold_s))
        segs.append(Segment(t, d, 0.0, 0.0, th, sway=np.deg2rad(rng.uniform(0.1, 0.4)), sway_hz=float(rng.uniform(0.2, 0.5))))
        t += d
        if k == n_poses - 1:
            break
        new = np.deg2rad(rng.uniform(*pitch_range_deg))
        while abs(new - th) < np.deg2rad(min_change_deg):  # a pose change worth the name
            new = np.deg2rad(rng.uniform(*pitch_range_deg))
        d = float(rng.uniform(*move_s))
        segs.append(Segment(t, d, 0.0, 0.0, th, dtheta=new - th, clearance=float(rng.uniform(0.0, 0.05)), still=False))
        th = new
        t += d
    return _motion(segs, fs, "foot_poses", temp_c, vsupply)


@dataclass
class FootSession:
    """A simulated foot-instep recording with everything the gyro methods and their checks need."""

    t: np.ndarray  # (N,) [s]
    acc_raw: np.ndarray  # (N, 3) duty cycles of ax, ay, az (core.samples.raw_triad)
    gyro: np.ndarray  # (N,) ENC-03J ADC counts
    acc_calibration: object  # the true triad calibration (Calibration)
    truth: dict  # gyro_truth(model): bias_counts, sensitivity_counts_per_rad_s, hp_hz, axis, range_rad_s
    motion: Motion
    model: object  # the SensorModel drawn for the seed
    fs: float


def simulate_foot(motion: Motion, seed: int, **model_overrides) -> FootSession:
    """Run ``motion`` through a default_model drawn from ``seed`` (datasheet spreads: the
    ENC-03J scale factor +-20 %, its null voltage, the ADXL210 parts) and collect the truth."""
    model = default_model(np.random.default_rng(seed), **model_overrides)
    sim = simulate(motion, model, seed=seed)
    vs = float(np.median(motion.vsupply))
    return FootSession(t=sim.samples["t"].astype(float), acc_raw=raw_triad(sim.samples),
                       gyro=sim.samples["gyro"].astype(float), acc_calibration=triad_truth(model, float(np.median(motion.temp)), vs),
                       truth=gyro_truth(model, vs), motion=motion, model=model, fs=motion.fs)
