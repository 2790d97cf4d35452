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
from typing import Any

import numpy as np

from .lab import SIX_FACES, _plan_loetters, _plan_six_position, _plan_static
from .motion import E_UP, MOVING, STILL, TURN, WALK, Motion, MotionPlan
from .wearer import (
    DAILY_POSTURES,
    SAGITTAL_POSTURES,
    _plan_daily_living,
    _plan_sagittal_postures,
)

__all__ = ["DAILY_POSTURES", "E_UP", "MOVING", "SAGITTAL_POSTURES", "SCENARIOS", "SIX_FACES", "STILL", "TURN", "WALK",
           "Motion", "MotionPlan", "make_motion", "plan_motion"]

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
