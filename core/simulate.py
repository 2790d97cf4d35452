"""The simulator: a motion scenario through the sensor model into SAMPLE_DTYPE rows.

    motion (specific force [g], omega [rad/s], temp, vsupply)
      -> board stage (the axis projection)     -> channel g (N, 4)
      -> channel stage (noise, drift, filter, saturation ...)
      -> duty stage (duty_cycle)               -> T1/T2
      -> counts stage (timer)                  -> t1 (N, 4), t2 (N, 2) counts
      -> gyro stage (ENC-03J path, from omega) -> gyro ADC counts

Randomness: one SeedSequence(seed) spawns three independent streams, for the scenario, for
drawing a default model, and for the sensor's noise. ``simulate_blocks`` runs a private copy
of the model whose terms carry filter and random-walk state from block to block, so any block
size gives the same samples as ``simulate`` for the same seed.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterator

import numpy as np

from .model import SensorModel
from .model.terms import REGISTRY, Axes, projection_matrix
from .model.base import Context
from .model.defaults import default_model, triad_truth
from .samples import FLAG_SATURATED, empty
from .scenarios import Motion, MotionPlan, plan_motion
from .seeding import seed_streams

DEFAULT_BLOCK = 65536  # samples per block: bounds the float intermediates to a few MB


@dataclass
class Simulation:
    samples: np.ndarray  # SAMPLE_DTYPE rows
    motion: Motion  # what the board experienced (truth)
    model: SensorModel  # the sensor model used (parameters; no run state)
    truth: dict[str, Any]  # JSON-able: calibration, model, scenario, seed, fs, conditions


class _Forward:
    """Runs a fresh copy of a model over consecutive motion blocks (explicit carried state)."""

    def __init__(self, model: SensorModel, rng: np.random.Generator, fs: float):
        self.model = SensorModel.from_dict(model.to_dict())  # private copy: fresh term state
        projection_matrix(self.model)  # raises if the model holds two axis projections
        for stage in ("duty", "counts"):
            if not self.model.stage_terms(stage):
                which = " or ".join(n for n, spec in REGISTRY.items() if spec.forward.stage == stage)
                raise ValueError(f"sensor model has no {stage!r}-stage term ({which}); the simulator needs one "
                                 "to produce t1/t2 counts")
        clocks = [t.tick_hz for t in self.model.stage_terms("counts") if t.tick_hz is not None]
        if not clocks:
            raise ValueError("sensor model's counts stage has no timer (a term with tick_hz): the simulator "
                             "needs its clock for the tick field")
        self.has_projection = any(isinstance(t, Axes) for t in self.model.stage_terms("board"))
        self.clock_hz = float(clocks[0])
        self.rng = rng
        self.fs = float(fs)
        self.seq = 0

    def block(self, motion: Motion) -> np.ndarray:
        m = self.model
        n = len(motion)
        ctx = Context(t=motion.t, temp=motion.temp, vsupply=motion.vsupply, fs=self.fs, rng=self.rng,
                      omega=motion.omega)
        x = m.run_stage("board", motion.specific_force, ctx)
        if not self.has_projection:
            x = Axes().forward(x, ctx)  # no axes term: ideal geometry
        x = m.run_stage("channel", x, ctx)
        saturated = np.zeros(n, bool)
        for term in m.stage_terms("channel"):
            rail = term.at_rail(x)
            if rail is not None:
                saturated |= rail
        duty = m.run_stage("duty", x, ctx)
        counts = m.run_stage("counts", duty, ctx)
        if counts.shape != (n, 6):
            raise ValueError(f"counts stage produced shape {counts.shape}, expected ({n}, 6) = t1 x4, t2 x2")
        out = empty(n)
        out["t"] = motion.t
        out["seq"] = self.seq + np.arange(n)
        self.seq += n
        out["tick"] = (np.rint(motion.t * self.clock_hz).astype(np.int64) & 0xFFFFFFFF).astype(np.uint32)
        out["t1"] = np.clip(counts[:, :4], 0, 2**32 - 1).astype(np.uint32)
        out["t2"] = np.clip(counts[:, 4:], 0, 2**32 - 1).astype(np.uint32)
        if m.stage_terms("gyro"):
            out["gyro"] = np.clip(m.run_stage("gyro", motion.omega, ctx), 0, 2**16 - 1).astype(np.uint16)
        out["temp"] = motion.temp
        out["vsupply"] = motion.vsupply
        out["flags"] = np.where(saturated, FLAG_SATURATED, 0).astype(np.uint16)
        return out


def _source(scenario: str | Motion | MotionPlan, rng: np.random.Generator, duration: float, fs: float,
            scenario_kw: dict[str, Any]) -> Motion | MotionPlan:
    if isinstance(scenario, (Motion, MotionPlan)):
        if scenario_kw:
            raise ValueError(f"scenario options {sorted(scenario_kw)} given with a ready-made motion")
        return scenario
    if isinstance(scenario, str):
        return plan_motion(scenario, duration=duration, fs=fs, rng=rng, **scenario_kw)
    raise ValueError(f"scenario must be a scenario name, a Motion or a MotionPlan, not {type(scenario).__name__}")


def simulate(scenario: str | Motion | MotionPlan, model: SensorModel | None = None, *, seed: int = 0,
             duration: float = 600.0, fs: float = 100.0, **scenario_kw: Any) -> Simulation:
    """Simulate a session. ``model=None`` draws ``default_model`` from the seed.

    A Motion/MotionPlan brings its own duration and rate (``duration``/``fs`` are ignored).
    ``truth["calibration"]`` is ``triad_truth`` at the median temperature and supply of the
    quasi-static samples and at the mid time (exact for a model without temperature, supply
    or drift terms; otherwise the conditions are in ``truth["conditions"]``).
    """
    motion_rng, model_rng, sensor_rng = seed_streams(seed)
    src = _source(scenario, motion_rng, duration, fs, scenario_kw)
    motion = src.render() if isinstance(src, MotionPlan) else src
    if model is None:
        model = default_model(model_rng)
    fwd = _Forward(model, sensor_rng, motion.fs)
    blocks = [fwd.block(motion.slice(i, i + DEFAULT_BLOCK)) for i in range(0, len(motion), DEFAULT_BLOCK)]
    samples = np.concatenate(blocks) if blocks else empty(0)
    sel = motion.still if np.any(motion.still) else np.ones(len(motion), bool)
    cond = {"temp_c": float(np.median(motion.temp[sel])), "vsupply": float(np.median(motion.vsupply[sel])),
            "t": float(motion.t[len(motion) // 2]) if len(motion) else 0.0}
    truth = {
        "calibration": triad_truth(model, **cond).to_dict(),
        "conditions": cond,
        "model": model.to_dict(),
        "scenario": scenario if isinstance(scenario, str) else (motion.name or "custom"),
        "scenario_kw": {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in scenario_kw.items()},
        "seed": int(seed),
        "fs": float(motion.fs),
        "duration": len(motion) / motion.fs,
    }
    return Simulation(samples=samples, motion=motion, model=model, truth=truth)


def simulate_blocks(scenario: str | Motion | MotionPlan, model: SensorModel | None = None, *, seed: int = 0,
                    duration: float = 600.0, fs: float = 100.0, block: int = DEFAULT_BLOCK,
                    **scenario_kw: Any) -> Iterator[np.ndarray]:
    """Yield the session of ``simulate`` (same seed -> same samples) in blocks of ``block`` rows.

    Only one block of motion and intermediates is alive at a time, so a week at 100 Hz
    (60 M samples) streams in bounded memory.
    """
    block = int(block)
    if block < 1:
        raise ValueError(f"block must be a positive number of samples, got {block}")
    motion_rng, model_rng, sensor_rng = seed_streams(seed)
    src = _source(scenario, motion_rng, duration, fs, scenario_kw)
    if model is None:
        model = default_model(model_rng)
    n = src.n if isinstance(src, MotionPlan) else len(src)
    fwd = _Forward(model, sensor_rng, src.fs)
    for i in range(0, n, block):
        part = src.render(i, i + block) if isinstance(src, MotionPlan) else src.slice(i, i + block)
        yield fwd.block(part)
