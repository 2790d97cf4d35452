"""Window-level sessions with planted sensor-model effects (for the hidden-effect tests and the bench).

A session is an hour (by default) of daily-living-like quasi-static windows: mostly upright
postures with tilts, some sitting/bending and lying, a body-worn temperature profile, windows of
2-20 s. The window means come from the sensor model itself (core/model terms, run on one
"sample" per window with the window's time and temperature: the deterministic part of those
terms), so a planted effect is exactly the model's term with its datasheet-style parameters;
then the noise of a window mean (white, ADXL210 density at 100 Hz, over n samples) and a
quasi-static floor (residual body motion, ``floor_g`` RMS along the gravity direction) are added.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from gravcal.core.calibration import Calibration
from gravcal.core.model import Context, SensorModel
from gravcal.core.model.datasheet import D0_TYP, NOISE_DENSITY_UG, SENS_TYP
from gravcal.core.model.spec import planted_values
from gravcal.core.model.terms import CALIBRATION_TERMS, REGISTRY, Axes, DutyCycle, term_spec
from gravcal.core.samples import TRIAD
from gravcal.core.windows import WindowSet

PLANT = {name: REGISTRY[name].plant_scale for name in CALIBRATION_TERMS if REGISTRY[name].plant is not None}
"""Planted magnitude scale per term (per axis, random sign x U(1, 2) by seed): each term's ``plant_scale``,
at or above the floor of an hour of daily living documented in docs/measured-data.md."""


@dataclass
class Session:
    ws: WindowSet
    start: Calibration  # a start like the pipeline's (the effect-free truth at 25 °C, perturbed 1 %)
    model: SensorModel
    planted: dict[str, dict[str, Any]]


def _directions(rng: np.random.Generator, m: int) -> np.ndarray:
    """Gravity directions in the sensor frame for daily-living postures (waist-worn)."""
    kind = rng.choice(4, size=m, p=[0.55, 0.2, 0.15, 0.10])  # upright, sitting/bent, lying back/front, lying side
    base = np.array([[0, 0, 1.0], [0.5, 0, 0.87], [1.0, 0, 0], [0, 1.0, 0]])
    sign = np.where(rng.random(m) < 0.5, -1.0, 1.0)
    v = base[kind].copy()
    v[kind >= 2] *= sign[kind >= 2, None]
    v += rng.normal(0, 0.15, (m, 3))  # tilt spread ~9°
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def plant_terms(effects: dict[str, float], rng: np.random.Generator) -> dict[str, Any]:
    """Model terms for the effects (name -> magnitude scale; per channel random sign x U(1, 2))."""
    terms: dict[str, Any] = {}
    for name, mag in effects.items():
        spec = term_spec(name)
        v = planted_values(rng, mag)
        if spec.plant is None:
            raise ValueError(f"cannot plant {name!r}: plantable terms are {', '.join(PLANT)}")
        terms[spec.name] = spec.plant(rng, v, mag)
    return terms


def window_session(seed: int, effects: dict[str, float] | None = None, *, duration_s: float = 3600.0,
                   n_windows: int = 200, floor_g: float = 1e-3, temp_c: tuple[float, float] = (24.0, 34.0),
                   supply_v: tuple[float, float] = (3.05, 3.3), fs: float = 100.0) -> Session:
    """One session with ``effects`` planted (name -> magnitude scale, see PLANT); {} or None: control.

    The supply [V] sags from ``supply_v[1]`` toward ``supply_v[0]`` and back under load (its own random
    stream: the other draws do not depend on it)."""
    rng = np.random.default_rng(seed)
    effects = dict(effects or {})
    planted = plant_terms(effects, rng)
    m = n_windows
    t = np.sort(rng.uniform(0, duration_s, m))
    n = np.round(fs * rng.uniform(2.0, 20.0, m))
    # body-worn temperature: skin-warmed plateau, cooler spells outdoors, slow wander
    lo, hi = temp_c
    phase = rng.uniform(0, 2 * np.pi)
    temp = lo + (hi - lo) * (0.5 + 0.5 * np.sin(2 * np.pi * t / duration_s * rng.uniform(0.8, 1.6) + phase))
    temp += rng.normal(0, 0.2, m)
    u = _directions(rng, m)
    u_moved = u + rng.normal(0, floor_g, (m, 3))  # residual body motion: ~floor_g on the norm
    supply_rng = np.random.default_rng([seed, 2])
    vlo, vhi = supply_v
    vsupply = vhi - (vhi - vlo) * np.abs(np.sin(np.pi * t / duration_s * supply_rng.uniform(1.0, 2.5)
                                                 + supply_rng.uniform(0, np.pi)))
    vsupply += supply_rng.normal(0, 0.005, m)
    projection = [v for v in planted.values() if isinstance(v, Axes)]
    terms = (projection or [Axes()]) + [v for v in planted.values() if not isinstance(v, Axes)]
    terms.append(DutyCycle(d0=np.full(4, D0_TYP), k=np.full(4, SENS_TYP)))
    model = SensorModel(terms)
    ctx = Context(t=t, temp=temp, vsupply=vsupply, fs=fs, rng=np.random.default_rng(seed + 1))
    x = model.run_stage("board", u_moved, ctx)
    x = model.run_stage("channel", x, ctx)
    duty = model.run_stage("duty", x, ctx)[:, list(TRIAD)]
    sigma = NOISE_DENSITY_UG * 1e-6 * np.sqrt(fs / 2) * SENS_TYP  # per-sample std [duty]
    cov = np.broadcast_to(np.eye(3) * sigma**2, (m, 3, 3)).copy()
    mean = duty + rng.normal(0, 1, (m, 3)) * sigma / np.sqrt(n)[:, None]
    ws = WindowSet(mean, cov, n, t, np.column_stack([temp, vsupply]), np.arange(m) * 10_000, np.arange(m) * 10_000 + n.astype(int))
    K = np.diag(np.full(3, SENS_TYP)) * (1 + rng.normal(0, 0.01, (3, 3)))
    start = Calibration("start", np.full(3, D0_TYP) + rng.normal(0, 0.01 * SENS_TYP, 3), K)
    info = {k: v.to_dict()["params"] for k, v in planted.items()}
    return Session(ws, start, model, info)
