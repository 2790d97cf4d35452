"""Checks of a gyro calibration against known turns (measured data: Ferraris' 360° turns).

A turn about one fixed axis integrates to |integral of omega dt| = the angle turned, whatever
the axis; rotations about other axes during the turn (hand wobble) enter only at second order.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .calibrate import GyroCalibration


@dataclass
class TurnCheck:
    name: str
    angle_deg: float  # |integral of omega| over the section (+ margins) [deg]
    error_deg: float  # angle_deg - expected
    components_deg: np.ndarray  # (3,) the integral per axis [deg]


def turn_angle_deg(omega: np.ndarray, fs: float) -> tuple[float, np.ndarray]:
    """(|integral omega dt| [deg], per-axis integral [deg]) of rates omega (N, 3) [rad/s]."""
    v = np.degrees(np.asarray(omega, float).reshape(-1, 3).sum(axis=0) / fs)
    return float(np.linalg.norm(v)), v


def check_turns(gyro_raw: np.ndarray, sections: dict[str, tuple[int, int]], fs: float, *,
                calibration: GyroCalibration | None = None, nominal_per_rad_s: float | None = None,
                expected_deg: float = 360.0, margin_s: float = 1.0) -> list[TurnCheck]:
    """Integrate each section (sample range, widened by ``margin_s`` on both sides so the
    turn's start and end are inside) with ``calibration`` (bias + sensitivity), or, when it is
    None, with the nominal scale only (raw / nominal_per_rad_s: the data as recorded)."""
    g = np.asarray(gyro_raw, float)
    out = []
    m = int(round(margin_s * fs))
    for name, (a, b) in sections.items():
        seg = g[max(0, a - m): min(g.shape[0], b + m)]
        if calibration is not None:
            omega = calibration.rate(seg)
        elif nominal_per_rad_s:
            omega = seg / float(nominal_per_rad_s)
        else:
            raise ValueError("check_turns needs a calibration or a nominal scale (raw units per rad/s)")
        ang, comp = turn_angle_deg(omega, fs)
        out.append(TurnCheck(name, ang, ang - expected_deg, comp))
    return out
