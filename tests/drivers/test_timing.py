"""Time on the acquisition path: one tick rate between emulator and driver, host time that never
runs backwards, and reads that wake on data instead of waiting for a batch."""
from __future__ import annotations

import threading

import numpy as np
import pytest

from gravcal.core.samples import SAMPLE_DTYPE
from gravcal.drivers import open_driver
from gravcal.drivers.base import Driver
from gravcal.drivers.codec import TICK_HZ, encode_frames
from gravcal.drivers.rigs.emulator import PtyLink
from gravcal.drivers.rigs.sources import pattern_blocks, scenario_source
from support.stamp_reference import stamp


@pytest.mark.parametrize("scenario", ["daily_living", "six_position", "pattern"])
def test_emulated_ticks_count_at_the_drivers_tick_rate(scenario):
    fs = 200.0
    b = np.concatenate(list(scenario_source(scenario, seed=1, fs=fs, duration=3.0).blocks))
    dtick = np.diff(b["tick"].astype(np.int64))
    # one sample period in ticks (±1 for rounding): what the driver divides by TICK_HZ
    np.testing.assert_allclose(dtick, TICK_HZ / fs, atol=1.0)


class _Scripted(Driver):
    """A driver whose blocks are given; only the base's time stamping is exercised."""

    bus = "test"
    description = "scripted"

    def _connect(self, *, first):
        pass

    def _disconnect(self):
        pass

    def _read_block(self, deadline):
        return np.zeros(0, SAMPLE_DTYPE)


def _block(ticks):
    b = np.zeros(len(ticks), SAMPLE_DTYPE)
    b["tick"] = np.asarray(ticks, dtype=np.int64) & 0xFFFFFFFF
    return b


def test_host_time_never_runs_backwards():
    drv = _Scripted()
    period = TICK_HZ // 200
    stamped = []
    # a block received late (scheduling), then the next one promptly: back-dating the second by
    # its ticks would put its first sample before the first block's last
    a = _block(np.arange(4) * period)
    drv._stamp(a, 10.050)
    b = _block((4 + np.arange(4)) * period)
    drv._stamp(b, 10.030)
    # a device that restarted its tick counter inside a block
    c = _block([8 * period, 9 * period, 3, 3 + period])
    drv._stamp(c, 10.060)
    stamped = np.concatenate([a["t"], b["t"], c["t"]])
    assert np.all(np.diff(stamped) >= 0), np.diff(stamped)
    # in order reception keeps the tick spacing
    np.testing.assert_allclose(np.diff(a["t"]), 1 / 200)



def test_the_stamps_are_the_references_bit_for_bit():
    """Driver._stamp (in C, the C step's own stamping) writes the numpy reference's stamps
    (tests/support/stamp_reference.py) bit for bit: random reads of 1 to 40 samples, jittered reception,
    tick wraps, backwards ticks (device resets), no tick rate."""
    rng = np.random.default_rng(4)
    for tick_hz in (TICK_HZ, 0.0, 32768.0):
        drv, last = _Scripted(tick_hz=tick_hz or None), -np.inf
        tick, t_recv = int(rng.integers(0, 1 << 32)), 100.0
        for _ in range(300):
            n = int(rng.integers(1, 41))
            steps = rng.choice([5000, 5000, 5000, 4999, 5001, -70000, 1 << 31], n)
            ticks = tick + np.cumsum(steps)
            tick = int(ticks[-1])
            t_recv += n / 200 + rng.normal(0, 0.004)
            got, want = _block(ticks), _block(ticks)
            drv._stamp(got, t_recv)
            last = stamp(want, tick_hz, t_recv, last)
            np.testing.assert_array_equal(got["t"], want["t"])
            assert drv._last_t == last


def _frames(n, start=0):
    b = np.concatenate(list(pattern_blocks(seed=5, fs=200.0, duration=(start + n) / 200.0)))
    return b[start:start + n]


def test_serial_read_returns_each_frame_as_it_arrives(tmp_path):
    link = PtyLink(tmp_path / "ttyT")
    link.connect()
    try:
        with open_driver(link.spec) as drv:
            frames = _frames(6)
            # the first frame of all waits for the second (nothing before it confirms it: drivers/ordering.py)
            link.write(encode_frames(frames[:2]), blocking=True)
            got = [drv.read(max_samples=64, timeout=5.0)]
            for i in range(2, 5):  # one frame on the wire: the read returns it, without waiting for more
                link.write(encode_frames(frames[i:i + 1]), blocking=True)
                got.append(drv.read(max_samples=64, timeout=5.0))
            assert [g.shape[0] for g in got] == [2, 1, 1, 1]
            np.testing.assert_array_equal(np.concatenate(got)["t1"], frames["t1"][:5])
    finally:
        link.close()


def test_serial_latency_budget_groups_frames_arriving_within_it(tmp_path):
    link = PtyLink(tmp_path / "ttyT")
    link.connect()
    try:
        drv = open_driver(link.spec, open=False)
        drv.latency_budget_s = 1.0  # the second frame, 0.2 s later, arrives within it
        with drv:
            frames = _frames(2)
            link.write(encode_frames(frames[:1]), blocking=True)
            later = threading.Timer(0.2, lambda: link.write(encode_frames(frames[1:]), blocking=True))
            later.start()
            got = drv.read(max_samples=64, timeout=5.0)
            later.join()
        np.testing.assert_array_equal(got["t1"], frames["t1"])
    finally:
        link.close()
