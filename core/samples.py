"""The sample layout used everywhere: drivers fill it, the ring buffer stores it, the
simulator writes it, the detector and estimators read it.

One row is one sample of the logger board:

- ``t``       host monotonic time [s] (simulated time for the simulator)
- ``seq``     sequence number, unwrapped from the device's 16-bit counter (int64)
- ``tick``    device timer tick (32-bit, wraps)
- ``t1``      ADXL210 duty-cycle high times T1 [timer counts], four channels, see CHANNELS
- ``t2``      ADXL210 periods T2 [timer counts], one per chip, see CHANNEL_CHIP
- ``gyro``    ENC-03J rate output through the board's conditioning stage [ADC counts]
- ``temp``    board temperature [°C]
- ``vsupply`` supply voltage [V]
- ``flags``   bit set of FLAG_* (gaps, reconnects, saturation, ...)

The two biaxial ADXL210 chips form the triad: chip A lies flat and senses x and y, chip B
stands on its edge and senses z and x again. The second x channel (``ax2``) is redundant:
it is not used for the triad, but it is a free consistency check between the chips.
"""
from __future__ import annotations

import numpy as np

CHANNELS: tuple[str, ...] = ("ax", "ay", "az", "ax2")
"""Accelerometer channels in the order of the ``t1`` field."""

CHANNEL_CHIP: np.ndarray = np.array([0, 0, 1, 1])
"""Which chip (index into ``t2``) each channel belongs to: chip A = 0, chip B = 1."""

TRIAD: tuple[int, int, int] = (0, 1, 2)
"""Channels that make the x, y, z triad."""

SAMPLE_DTYPE = np.dtype(
    [
        ("t", "<f8"),
        ("seq", "<i8"),
        ("tick", "<u4"),
        ("t1", "<u4", (4,)),
        ("t2", "<u4", (2,)),
        ("gyro", "<u2"),
        ("temp", "<f4"),
        ("vsupply", "<f4"),
        ("flags", "<u2"),
    ]
)

# Flags. A driver sets them; nothing downstream clears them.
FLAG_GAP_BEFORE = 1 << 0  # one or more samples are missing right before this one (sequence gap)
FLAG_RECONNECT = 1 << 1  # first sample after the device was reopened
FLAG_SATURATED = 1 << 2  # an accelerometer channel is at the end of its range
FLAG_FIFO_OVERFLOW = 1 << 3  # the device FIFO overflowed before this sample (I2C)
FLAG_PARTIAL = 1 << 4  # assembled from an incomplete set of frames (CAN); some fields invalid
FLAG_REPLAYED = 1 << 5  # came from a recording, not a live device

FLAG_NAMES = {
    FLAG_GAP_BEFORE: "gap_before",
    FLAG_RECONNECT: "reconnect",
    FLAG_SATURATED: "saturated",
    FLAG_FIFO_OVERFLOW: "fifo_overflow",
    FLAG_PARTIAL: "partial",
    FLAG_REPLAYED: "replayed",
}


def empty(n: int) -> np.ndarray:
    """A zeroed block of ``n`` samples."""
    return np.zeros(n, dtype=SAMPLE_DTYPE)


def duty_ratios(samples: np.ndarray) -> np.ndarray:
    """Duty cycles T1/T2 of the four channels, shape (N, 4), dimensionless.

    This ratio is the ADXL210's output quantity (A = (T1/T2 - 0.5)/k); using the ratio
    rather than T1 alone cancels the RSET/temperature dependence of the period T2.
    Samples with T2 = 0 (missing) give NaN.
    """
    t1 = samples["t1"].astype(np.float64)
    t2 = samples["t2"].astype(np.float64)[:, CHANNEL_CHIP]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = t1 / t2
    r[t2 == 0] = np.nan
    return r


def raw_triad(samples: np.ndarray) -> np.ndarray:
    """The raw x, y, z triad (duty cycles of channels ax, ay, az), shape (N, 3).

    These are the "raw units" every estimator works in: a = K^-1 (raw - o) with K in
    duty-cycle per g.
    """
    return duty_ratios(samples)[:, list(TRIAD)]


def flag_names(flags: int) -> list[str]:
    """Names of the bits set in ``flags``."""
    return [name for bit, name in FLAG_NAMES.items() if flags & bit]
