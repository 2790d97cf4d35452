"""The numpy reference of the drivers' host-time stamps (drivers/_framekernel.c ``stamp``), the oracle its tests
compare it to bit for bit: the newest sample of a read at its reception time, earlier ones back from it by their
32-bit tick distance / tick_hz (a backwards step counts 0; tick_hz 0: all at reception), never before the last
stamp nor each other."""
from __future__ import annotations

import numpy as np


def stamp(block: np.ndarray, tick_hz: float, t_recv: float, last_t: float) -> float:
    """Write ``block["t"]``; returns the new last stamp."""
    if block.shape[0] == 1:
        block["t"] = t = max(t_recv, last_t)
        return t
    if tick_hz:
        back = (int(block["tick"][-1]) - block["tick"].astype(np.int64)) & 0xFFFFFFFF
        back = np.where(back > 0x7FFFFFFF, 0, back)  # ticks going backwards: device reset
        t = t_recv - back / float(tick_hz)
    else:
        t = np.full(block.shape[0], t_recv)
    t[0] = max(t[0], last_t)
    block["t"] = np.maximum.accumulate(t)
    return float(block["t"][-1])
