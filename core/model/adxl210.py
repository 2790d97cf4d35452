"""The ADXL210 pair's geometry: which board axis each of the four duty-cycle channels senses.

Two biaxial ADXL210 chips form the triad (see ``core/samples.py``): chip A lies flat and
senses board x and y (channels ``ax``, ``ay``); chip B stands on its edge on a small carrier
and senses board z and x again (``az``, ``ax2``). The physical effects of the chips are terms,
one module each, in ``core/model/terms/``; their datasheet values in ``datasheet.py``.
"""
from __future__ import annotations

import numpy as np

N_CHANNELS = 4
N_CHIPS = 2

IDEAL_AXES = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 0, 0]])
"""Nominal sensitive axis of each channel (rows: ax, ay, az, ax2) in the board frame."""

# Chip frame -> board frame rotations of the nominal mounting (columns = chip axes in board).
CHIP_A_NOMINAL = np.eye(3)  # flat: chip x -> board x, chip y -> board y
CHIP_B_NOMINAL = np.array([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]])  # on edge: chip x -> board z, chip y -> board x
# (chip, chip axis) of each channel, in CHANNELS order.
CHANNEL_SOURCE = ((0, 0), (0, 1), (1, 0), (1, 1))

T2_PER_RSET = 1.0 / 125e6  # T2 [s] = RSET [ohm] / 125 Mohm (datasheet)
