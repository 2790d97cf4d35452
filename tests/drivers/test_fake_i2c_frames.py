"""The fake I2C device's FIFO holds the same frames whether it encodes them per sample (the general
path, taken with a SentLog) or takes them from its source block's encoding (the fast path)."""
import numpy as np
import pytest

from gravcal.drivers.codec import FRAME_LEN
from gravcal.drivers.i2c import CTRL_ENABLE, REG_CTRL, REG_FIFO_DATA
from gravcal.drivers.rigs.emulator import SentLog
from gravcal.drivers.rigs.fake_i2c import FakeI2CDevice, ManualClock
from gravcal.drivers.rigs.sources import pattern_blocks


def _fifo_bytes(seed: int, log, steps: np.ndarray, reads: np.ndarray, depth: int) -> bytes:
    clock = ManualClock()
    dev = FakeI2CDevice(pattern_blocks(seed=seed, fs=200.0, duration=30.0, block=97), 200.0, clock=clock,
                        fifo_depth=depth, log=log)
    dev.write_registers(REG_CTRL, bytes([CTRL_ENABLE]))
    out = bytearray()
    for dt, k in zip(steps, reads):
        clock.advance(float(dt))
        out += dev.read_registers(REG_FIFO_DATA, int(k) * FRAME_LEN)
    return bytes(out)


@pytest.mark.parametrize("seed", range(4))
def test_fifo_frames_are_the_same_on_both_paths(seed):
    rng = np.random.default_rng(seed)
    steps = rng.choice([0.005, 0.002, 0.013, 0.1, 0.4], size=600)  # one sample at a time, and bursts
    reads = rng.integers(1, 40, size=600)  # reads that leave the FIFO filling up, and overflowing
    fast = _fifo_bytes(seed, None, steps, reads, depth=32)
    general = _fifo_bytes(seed, SentLog(), steps, reads, depth=32)
    assert len(general) > 1000 * FRAME_LEN
    assert fast == general
