"""Reading a driver until an emulator process's stream has ended (the cross-process driver tests)."""
from __future__ import annotations

import time

import numpy as np

from gravcal.drivers.rigs.hil import EmulatorProcess


def read_all(drv, emu: EmulatorProcess, deadline_s: float = 45.0) -> np.ndarray:
    """Read until the emulator's stream has ended and the port has gone quiet (or the deadline passed)."""
    got, end = [], time.monotonic() + deadline_s
    while time.monotonic() < end:
        b = drv.read(max_samples=512, timeout=0.3)
        got.append(b)
        if emu.wait_done(0) and b.shape[0] == 0:
            break
    return np.concatenate(got)
