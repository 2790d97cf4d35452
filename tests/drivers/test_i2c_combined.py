"""The I2C driver's combined FIFO read (STATUS, FIFO_COUNT and the first frames in one i2c_rdwr, when DRDY is
high) against its per-register path (STATUS, then bursts): the same samples with the same flags, one bus
transfer per sample, and no frame lost when one comes in between the status and the data phase."""
from __future__ import annotations

import errno
import time

import numpy as np
import pytest
from smbus2 import i2c_msg

from gravcal.core.samples import FLAG_FIFO_OVERFLOW, FLAG_GAP_BEFORE
from gravcal.drivers.i2c import REG_FIFO_COUNT, REG_FIFO_DATA, I2CDriver
from gravcal.drivers.rigs.emulator import CORRUPTED, DROPPED, FIFO_FULL, SENT, Faults, SentLog
from gravcal.drivers.rigs.fake_i2c import FakeI2CDevice, FakeSMBus, ManualClock
from gravcal.drivers.rigs.sources import pattern_blocks

FIELDS = ("seq", "tick", "t1", "t2", "gyro", "temp", "vsupply", "flags")


class CountingBus(FakeSMBus):
    """FakeSMBus counting the driver's i2c_rdwr transfers."""

    transfers = 0

    def i2c_rdwr(self, *msgs) -> None:
        CountingBus.transfers += 1
        super().i2c_rdwr(*msgs)


def run(combined: bool, *, faults: Faults, stalls=(), latency_budget_s=0.0, depth=16, polls=200, dt=0.005,
        drdy=True):
    """A device on a manual clock read by the driver with DRDY (``drdy``; else polled), one read per ``dt``
    (each ``stalls`` read index waits 0.3 s first: the FIFO overflows): (samples, stats, the device's fates,
    transfers)."""
    clock, log = ManualClock(), SentLog()
    dev = FakeI2CDevice(pattern_blocks(seed=4, fs=200, duration=10), 200, clock=clock, log=log, faults=faults,
                        fifo_depth=depth)
    drv = I2CDriver(1, 0x42, smbus_factory=lambda bus: CountingBus(dev, bus),
                    data_ready=dev.data_ready if drdy else None, combined=combined, latency_budget_s=latency_budget_s)
    drv.backoff.initial_s = 0.0  # the manual clock does not move during backoff waits
    got = []
    with drv:
        CountingBus.transfers = 0
        for i in range(polls):
            clock.advance(0.3 if i in stalls else dt)
            with dev._lock:  # the device samples on its clock (a real one does, between bus accesses): DRDY follows
                dev._advance()
            got.append(drv.read(max_samples=4096, timeout=0))
        st = drv.stats()
    return np.concatenate(got), st, dev.fates(), CountingBus.transfers


@pytest.mark.parametrize("budget", [0.0, 0.02])
def test_combined_read_gives_the_per_register_paths_samples_and_flags(budget):
    """Deterministic faults (the host stalls: FIFO overflows; the device stops answering for 0.2 s): both paths
    read the same frames, so the same samples, flags and counters."""
    def faults():
        return Faults(disconnects=[(0.7, 0.2)])

    a, sa, fa, _ = run(True, faults=faults(), stalls=(50, 120), latency_budget_s=budget)
    b, sb, fb, _ = run(False, faults=faults(), stalls=(50, 120), latency_budget_s=budget)
    assert a.shape[0] > 150
    for name in FIELDS:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    for key in ("samples", "gaps", "fifo_overflows", "crc_errors", "disconnects", "reconnects"):
        assert sa[key] == sb[key], key
    np.testing.assert_array_equal(fa["status"], fb["status"])
    assert sa["disconnects"] == 1 and sa["fifo_overflows"] >= 2
    np.testing.assert_array_equal(a["seq"], np.flatnonzero(fa["status"] == SENT))
    np.testing.assert_array_equal((a["flags"] & FLAG_GAP_BEFORE) != 0, np.r_[False, np.diff(a["seq"]) > 1])
    assert np.count_nonzero(a["flags"] & FLAG_FIFO_OVERFLOW) == sa["fifo_overflows"]


def test_combined_read_with_drops_and_bit_errors_keeps_every_intact_sample():
    """Random faults draw from the device's generator per burst, so the two paths meet other faults; each
    path against the device: every sample that went into the FIFO and was not hit arrives, gaps flagged."""
    got, st, fates, _ = run(True, faults=Faults(drop=0.03, ber=2e-4, seed=5), stalls=(50, 120))
    status = fates["status"]
    np.testing.assert_array_equal(got["seq"], np.flatnonzero(status == SENT))
    assert (status == CORRUPTED).any() and (status == DROPPED).any() and (status == FIFO_FULL).any()
    np.testing.assert_array_equal((got["flags"] & FLAG_GAP_BEFORE) != 0, np.r_[False, np.diff(got["seq"]) > 1])
    assert np.count_nonzero(got["flags"] & FLAG_FIFO_OVERFLOW) == st["fifo_overflows"] == 2


@pytest.mark.parametrize("drdy", [True, False], ids=["drdy", "polled"])
def test_one_transfer_per_sample_when_drdy_wakes_or_a_poll_finds_one(drdy):
    got, st, fates, transfers = run(True, faults=Faults(), polls=100, drdy=drdy)
    per_register = run(False, faults=Faults(), polls=100, drdy=drdy)[3]
    n = got.shape[0]
    assert n >= 99  # a frame per 5 ms poll (a rounding of the manual clock may put two in one)
    assert transfers <= n + 2 and per_register >= 2 * n - 2  # STATUS + burst in one transfer, against two


def test_polled_combined_reads_give_the_per_register_paths_samples():
    """Without DRDY, polls between samples find the FIFO empty (a combined poll then reads only padding) and
    stalls fill it past the watermark (the rest in bursts): the samples and flags of the per-register path."""
    a, sa, fa, ta = run(True, faults=Faults(), stalls=(50, 120), dt=0.0025, drdy=False)
    b, sb, fb, tb = run(False, faults=Faults(), stalls=(50, 120), dt=0.0025, drdy=False)
    np.testing.assert_array_equal(fa["status"], fb["status"])
    for name in FIELDS:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    assert sa["fifo_overflows"] == sb["fifo_overflows"] >= 2 and sa["samples"] == sb["samples"] > 80
    assert ta < tb  # a poll that finds a frame takes it in the same transfer


def test_polled_combined_reads_with_drops_and_bit_errors_keep_every_intact_sample():
    got, st, fates, _ = run(True, faults=Faults(drop=0.03, ber=2e-4, seed=5), stalls=(50, 120), dt=0.0025,
                            drdy=False)
    status = fates["status"]
    np.testing.assert_array_equal(got["seq"], np.flatnonzero(status == SENT))
    assert (status == CORRUPTED).any() and (status == DROPPED).any() and (status == FIFO_FULL).any()
    np.testing.assert_array_equal((got["flags"] & FLAG_GAP_BEFORE) != 0, np.r_[False, np.diff(got["seq"]) > 1])
    assert np.count_nonzero(got["flags"] & FLAG_FIFO_OVERFLOW) == st["fifo_overflows"]


class LateClock(ManualClock):
    """A clock that moves on by ``step`` at every reading: the device samples between the messages of one
    combined transfer (a real device's FIFO fills whenever its sample is due)."""

    def __init__(self, step: float):
        super().__init__()
        self.step = step

    def __call__(self) -> float:
        self.t += self.step
        return self.t


def test_a_frame_that_arrives_during_the_transfer_is_kept():
    """STATUS says 0 frames (the line was high for a frame the host just took), a frame comes in before the
    data phase: the burst carries it, and it must be kept, not thrown away with the padding."""
    clock, log = LateClock(0.0), SentLog()
    dev = FakeI2CDevice(pattern_blocks(seed=4, fs=200, duration=10), 200, clock=clock, log=log, fifo_depth=16)
    drv = I2CDriver(1, 0x42, smbus_factory=lambda bus: FakeSMBus(dev, bus), data_ready=dev.data_ready)
    with drv:
        got = [drv.read(max_samples=4096, timeout=0)]
        dev.data_ready.set(True)  # a stale DRDY: nothing in the FIFO
        with dev._lock:
            t_next = dev._t_enable + (dev._produced + 1) / 200.0
        clock.step = 1e-3
        clock.t = t_next - 1.5 * clock.step  # the next sample is due between the STATUS and the data reads
        status, count, data = drv._status_and_first(1)
        got.append(drv.decoder.feed(data))
    assert count == 0 and len(data) == 29
    seq = np.concatenate(got)["seq"]
    np.testing.assert_array_equal(seq, np.flatnonzero(dev.fates()["status"] == SENT))


def test_the_fake_bus_refuses_what_i2c_dev_refuses():
    dev = FakeI2CDevice(pattern_blocks(seed=4, fs=200, duration=1), 200, clock=ManualClock())
    bus = FakeSMBus(dev)
    with pytest.raises(OSError) as e:
        bus.i2c_rdwr(*[i2c_msg.write(0x42, [REG_FIFO_COUNT])] * 43)  # I2C_RDWR_IOCTL_MAX_MSGS is 42
    assert e.value.errno == errno.EINVAL
    with pytest.raises(OSError) as e:
        bus.i2c_rdwr(i2c_msg.write(0x42, [REG_FIFO_DATA]), i2c_msg.read(0x42, 8193))
    assert e.value.errno == errno.EINVAL
    w, r = i2c_msg.write(0x42, [REG_FIFO_COUNT]), i2c_msg.read(0x42, 1)
    bus.i2c_rdwr(*[w, r] * 21)  # 42 messages: accepted


def test_drdy_line_raises_per_sample_and_a_read_below_the_watermark_lowers_it():
    from gravcal.drivers.rigs.fake_i2c import DataReadyLine

    line = DataReadyLine()
    try:
        assert not line.wait(0)
        line.set(True)
        line.set(True)  # a second sample while high: still one readable line
        assert line.wait(0)
        line.set(False)  # drained whatever was raised
        assert not line.wait(0)
        line.set(False)
        assert not line.wait(0)
    finally:
        line.close()


def test_the_sampling_thread_raises_drdy_with_the_devices_lock_free():
    """The host DRDY wakes reads the FIFO at once: a raise made while the device still held its lock would
    wake it into a wait for that lock (two wake-ups per sample instead of one)."""
    import threading
    import time

    dev = FakeI2CDevice(pattern_blocks(seed=4, fs=200, duration=10), 200, fifo_depth=255)
    raised = []
    real_set = dev.data_ready.set

    def recording_set(high):
        if high and threading.current_thread().name == "fake-i2c-device":
            raised.append(dev._lock.locked())
        real_set(high)

    dev.data_ready.set = recording_set
    drv = I2CDriver(1, 0x42, smbus_factory=lambda bus: FakeSMBus(dev, bus), data_ready=dev.data_ready)
    got = 0
    with drv:
        dev.start_sampling()
        try:
            t_end = time.monotonic() + 0.5
            while time.monotonic() < t_end:
                got += drv.read(max_samples=4096, timeout=0.05).shape[0]
        finally:
            dev.stop_sampling()
    assert got >= 50 and len(raised) >= 50
    assert not any(raised)


def test_a_polled_read_that_may_wait_asks_again_only_a_poll_interval_after_a_drain():
    """Right after a drain the FIFO is empty but for a frame that came in meanwhile: a read that may wait sleeps
    out the poll interval before its next transfer; one that may not (timeout 0) asks at once."""
    clock = ManualClock()
    dev = FakeI2CDevice(pattern_blocks(seed=4, fs=200, duration=10), 200, clock=clock, log=SentLog(), fifo_depth=16)
    at = []

    class TimedBus(FakeSMBus):
        def i2c_rdwr(self, *msgs):
            at.append(time.monotonic())
            super().i2c_rdwr(*msgs)

    drv = I2CDriver(1, 0x42, smbus_factory=lambda bus: TimedBus(dev, bus), poll_s=0.5)
    with drv:
        clock.advance(0.01)
        assert drv.read(timeout=0).shape[0] >= 1
        n = len(at)
        clock.advance(0.005)
        called = time.monotonic()
        assert drv.read(timeout=0).shape[0] == 1 and len(at) == n + 1  # no time to wait: asked at once
        assert at[-1] - called < 0.5
        drained = time.monotonic()
        clock.advance(0.005)
        got = drv.read(timeout=1.0)
    assert got.shape[0] == 1 and len(at) == n + 2 and at[-1] - drained >= 0.5
