"""Misalignment: the channel axes built from mounting angles; in calibration, the symmetric
cross-axis part of K (the 9-parameter model's extra terms on top of order 6)."""
from __future__ import annotations

from typing import Any

import numpy as np

from ..adxl210 import CHANNEL_SOURCE, CHIP_A_NOMINAL, CHIP_B_NOMINAL, N_CHANNELS
from ..base import Term
from ..datasheet import ALIGN_DEG, CHIP_PLACEMENT_DEG, MOUNT_B_DEG
from ..spec import CROSS_PAIRS, CalibrationView, TermSpec
from .axes import Axes


def misaligned_axes(chip_a: Any = (0, 0, 0), chip_b: Any = (0, 0, 0), mount_b: Any = (0, 0, 0),
                    axis_err: Any = np.zeros((4, 2))) -> np.ndarray:
    """Channel axes (4, 3) from mounting angles [rad].

    chip_a, chip_b: rotation vectors of each package on its PCB, in the chip's own frame
    (placement/solder tilt). mount_b: rotation vector of chip B's edge carrier in the board
    frame. axis_err (4, 2): per-channel deviation of the sensitive axis inside the die toward
    the two chip axes perpendicular to it (datasheet "alignment error" / cross-axis sensitivity).
    """
    from scipy.spatial.transform import Rotation  # noqa: PLC0415 (scipy is heavy: the daemon imports this module)

    axis_err = np.asarray(axis_err, dtype=float).reshape(N_CHANNELS, 2)
    r_a = CHIP_A_NOMINAL @ Rotation.from_rotvec(np.asarray(chip_a, float)).as_matrix()
    r_b = (Rotation.from_rotvec(np.asarray(mount_b, float)).as_matrix() @ CHIP_B_NOMINAL
           @ Rotation.from_rotvec(np.asarray(chip_b, float)).as_matrix())
    chips = (r_a, r_b)
    u = np.zeros((N_CHANNELS, 3))
    for c, (chip, axis) in enumerate(CHANNEL_SOURCE):
        others = [i for i in range(3) if i != axis]
        v = np.zeros(3)
        v[axis] = 1.0
        v[others] = np.tan(axis_err[c])  # small tilts toward the other two chip axes
        u[c] = chips[chip] @ (v / np.linalg.norm(v))
    return u


class Misalignment(Axes):
    """The axes projection built from mounting angles.

    params [rad]: ``chip_a`` (3,), ``chip_b`` (3,) package rotation vectors in the chip frame,
    ``mount_b`` (3,) rotation vector of chip B's carrier in the board frame, ``axis_err`` (4, 2)
    in-die axis errors. A model holds either ``axes`` or ``misalignment``, not both; a model
    with neither uses the ideal axes.
    """

    name = "misalignment"

    def __init__(self, chip_a: Any = (0, 0, 0), chip_b: Any = (0, 0, 0), mount_b: Any = (0, 0, 0),
                 axis_err: Any = np.zeros((4, 2))):
        Term.__init__(self, chip_a=chip_a, chip_b=chip_b, mount_b=mount_b,
                      axis_err=np.asarray(axis_err, float).reshape(N_CHANNELS, 2))
        self._u = misaligned_axes(chip_a, chip_b, mount_b, axis_err)

    @property
    def matrix(self) -> np.ndarray:
        return self._u


def _prior(rng: np.random.Generator | None) -> Misalignment:
    if rng is None:
        return Misalignment()
    d = np.deg2rad
    return Misalignment(chip_a=rng.normal(0, d(CHIP_PLACEMENT_DEG), 3), chip_b=rng.normal(0, d(CHIP_PLACEMENT_DEG), 3),
                        mount_b=rng.normal(0, d(MOUNT_B_DEG), 3), axis_err=rng.normal(0, d(ALIGN_DEG), (4, 2)))


def _plant(rng: np.random.Generator, values: np.ndarray, scale: float) -> Misalignment:
    return Misalignment(axis_err=rng.normal(0, 1, (4, 2)) / np.sqrt(2) * scale * 1.5)


SPEC = TermSpec(
    name="misalignment", forward=Misalignment, prior=_prior, group="misalignment",
    plant=_plant, plant_scale=np.deg2rad(1.0),  # rad per in-die axis error (datasheet +-1°)
    diagnosed_by="windows",
    # Reported: the deviation of the angle between axes i and j from 90° [deg], positive when they are closer
    # than 90°. Axis i leaning by a_ij toward j gives K_ij = s_i a_ij; the norm sees only the symmetric part
    # m_ij = (K_ij + K_ji) / 2, and 90° - angle(i, j) = a_ij + a_ji = 2 m_ij / sqrt(s_i s_j) (small angles).
    view=CalibrationView(prefix="m", acts_on="cross", covariate=None, unit="deg_from_orthogonal",
                         convention="90° minus the angle between the two calibrated axes [deg]; positive when the "
                                    "axes are closer than 90°",
                         report_factor=lambda s: 2.0 * np.degrees(1.0) / np.sqrt([s[i] * s[j] for i, j in CROSS_PAIRS])),
)
