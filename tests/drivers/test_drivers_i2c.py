"""I2C driver against the fake logger at the smbus2 boundary (deterministic manual clock)."""
from __future__ import annotations

import errno

import numpy as np
import pytest
from smbus2 import i2c_msg

from gravcal.core.samples import FLAG_FIFO_OVERFLOW, FLAG_GAP_BEFORE, FLAG_RECONNECT
from gravcal.drivers import DriverError, open_driver
from gravcal.drivers.rigs.emulator import CORRUPTED, DROPPED, FIFO_FULL, OFFLINE, SENT, Faults, SentLog
from gravcal.drivers.rigs.fake_i2c import FakeI2CDevice, FakeSMBus, ManualClock
from gravcal.drivers.i2c import (
    REG_FIFO_COUNT, REG_FIFO_DEPTH, REG_ODR, REG_STATUS, REG_WHO_AM_I, WHO_AM_I_VALUE,
    I2CDriver,
)
from gravcal.drivers.rigs.sources import pattern_blocks
from tests.support.child import run_child

PAYLOAD = ("tick", "t1", "t2", "gyro", "temp", "vsupply")


def rig(duration=5.0, fs=200.0, faults=None, depth=32):
    clock, log = ManualClock(), SentLog()
    dev = FakeI2CDevice(pattern_blocks(seed=9, fs=fs, duration=duration), fs, clock=clock, log=log,
                        faults=faults or Faults(), fifo_depth=depth)
    drv = I2CDriver(1, 0x42, smbus_factory=lambda bus: FakeSMBus(dev, bus))
    return clock, dev, drv


def pump(clock, drv, steps, dt):
    got = []
    for _ in range(steps):
        clock.advance(dt)
        got.append(drv.read(max_samples=4096, timeout=0))
    if drv._order.held is not None:  # a sample after a gap waits for the next read to confirm it: arrived
        got.append(drv._order.held)
    return np.concatenate(got)


def check(got, fates):
    sent, status = fates["samples"], fates["status"]
    seq = got["seq"]
    assert np.all(status[seq] == SENT)
    for name in PAYLOAD:
        np.testing.assert_array_equal(got[name], sent[name][seq], err_msg=name)
    np.testing.assert_array_equal(np.flatnonzero(status == SENT), seq)  # every sample in the FIFO arrived
    np.testing.assert_array_equal((got["flags"] & FLAG_GAP_BEFORE) != 0, np.r_[False, np.diff(seq) > 1])
    return seq, status


def test_register_map_through_real_i2c_msgs():
    clock, dev, _ = rig()
    bus = FakeSMBus(dev)
    assert bus.read_byte_data(0x42, REG_WHO_AM_I) == WHO_AM_I_VALUE
    assert bus.read_byte_data(0x42, REG_FIFO_DEPTH) == 32
    assert bus.read_byte_data(0x42, REG_ODR) == 3  # 25 Hz * 2**3 = 200 Hz
    bus.write_byte_data(0x42, 0x06, 0b11)  # FIFO reset + enable
    clock.advance(0.1)  # 20 samples at 200 Hz
    w, r = i2c_msg.write(0x42, [REG_STATUS]), i2c_msg.read(0x42, 2)
    bus.i2c_rdwr(w, r)
    status, count = bytes(r)
    assert count == 20 and status & 1
    assert bus.read_i2c_block_data(0x42, REG_FIFO_COUNT, 1) == [20]
    with pytest.raises(OSError) as e:
        bus.read_byte_data(0x43, REG_WHO_AM_I)  # nobody at 0x43: NACK
    assert e.value.errno == errno.ENXIO


def test_samples_equal_sent_with_drops():
    clock, dev, drv = rig(faults=Faults(drop=0.05, seed=3))
    with drv:
        got = pump(clock, drv, 60, 0.05)  # 3 s, polled every 50 ms (FIFO holds 160 ms)
        st = drv.stats()
    fates = dev.fates()
    seq, status = check(got, fates)
    assert (status == DROPPED).sum() >= 10 and seq.shape[0] == (status == SENT).sum() == st["samples"]
    assert st["fifo_overflows"] == 0 and st["gaps"] == int((np.diff(seq) > 1).sum())


def test_fifo_overflow_detected_and_flagged():
    clock, dev, drv = rig(depth=16)
    with drv:
        a = pump(clock, drv, 10, 0.04)  # keeping up: 8 samples per poll
        clock.advance(0.5)  # host stalls 0.5 s: 100 samples, FIFO holds 16
        b = pump(clock, drv, 10, 0.04)
        st = drv.stats()
    got = np.concatenate([a, b])
    seq, status = check(got, dev.fates())
    lost = np.flatnonzero(status == FIFO_FULL)
    assert lost.shape[0] == 100 + 8 - 16  # produced during the stall (+ the first poll after) minus FIFO depth
    k = np.flatnonzero(got["flags"] & FLAG_FIFO_OVERFLOW)
    assert k.shape == (1,) and seq[k[0]] == lost[-1] + 1 and seq[k[0] - 1] == lost[0] - 1
    assert got["flags"][k[0]] & FLAG_GAP_BEFORE and st["fifo_overflows"] == 1


def test_bit_errors_in_bursts_are_rejected():
    clock, dev, drv = rig(faults=Faults(ber=3e-4, seed=1))
    with drv:
        got = pump(clock, drv, 60, 0.05)
        st = drv.stats()
    fates = dev.fates()
    seq, status = check(got, fates)
    assert (status == CORRUPTED).sum() >= 5 and st["crc_errors"] >= 1


def test_device_vanishes_and_comes_back():
    clock, dev, drv = rig(faults=Faults(disconnects=[(1.0, 0.5)]))
    drv.backoff.initial_s = 0.0  # the manual clock does not move during backoff waits
    with drv:
        got = pump(clock, drv, 60, 0.05)
        st = drv.stats()
    seq, status = check(got, dev.fates())
    assert (status == OFFLINE).sum() == 100
    k = np.flatnonzero(got["flags"] & FLAG_RECONNECT)
    # The FIFO kept what it held when the device stopped answering (190..199, produced by the
    # access that got the NACK): they come first after the reconnect, unflagged; the first sample
    # produced after the outage carries both the reconnect and the gap.
    assert k.shape == (1,) and seq[k[0]] == 300
    assert seq[k[0] - 1] == 199 and got["flags"][k[0]] & FLAG_GAP_BEFORE
    assert st["disconnects"] == 1 and st["reconnects"] == 1


def test_an_overflow_while_the_host_reconnects_is_flagged_after_the_fifo_content():
    # the device comes back and fills its FIFO (16) before the host reopens it: the FIFO's frames follow the
    # outage's gap (reconnect), the overflow's gap comes after them, and each flag lands on its own gap
    clock, dev, drv = rig(faults=Faults(disconnects=[(1.0, 0.5)]), depth=16)
    drv.backoff.initial_s = 0.0
    with drv:
        a = pump(clock, drv, 20, 0.05)  # to 1.0 s
        clock.advance(0.5)  # the outage
        held = drv.read(max_samples=4096, timeout=0)  # what the FIFO held, then the NACK
        clock.advance(0.3)  # back for 0.3 s before the reopen: 60 samples, the FIFO keeps 16
        b = pump(clock, drv, 10, 0.05)
        st = drv.stats()
    got = np.concatenate([a, held, b])
    seq, status = check(got, dev.fates())
    full = np.flatnonzero(status == FIFO_FULL)
    assert (status == OFFLINE).sum() == 100 and full.shape[0] >= 40
    rec = np.flatnonzero(got["flags"] & FLAG_RECONNECT)
    ovf = np.flatnonzero(got["flags"] & FLAG_FIFO_OVERFLOW)
    assert rec.shape == (1,) and seq[rec[0]] == 300 and got["flags"][rec[0]] & FLAG_GAP_BEFORE
    assert ovf.shape == (1,) and seq[ovf[0]] == full[-1] + 1 and seq[ovf[0] - 1] == full[0] - 1 == 315
    assert st["fifo_overflows"] == 1 and st["gaps"] == 2 and st["missing"] == 100 + full.shape[0]


def test_an_overflow_during_a_slow_read_is_flagged_on_its_gap():
    # the host is held up 0.2 s inside a read (a slow bus): the FIFO (16) fills behind the frames it is reading
    # and drops the newest; the next read finds the frames from before the drop, then the gap, then newer ones
    clock, dev, _ = rig(depth=16)
    slow = {"at": None, "n": 0}

    class SlowBus(FakeSMBus):
        def i2c_rdwr(self, *msgs):
            if len(msgs) == 2 and msgs[1].len > 2:  # a FIFO burst
                slow["n"] += 1
                if slow["n"] == slow["at"]:
                    clock.advance(0.2)
            super().i2c_rdwr(*msgs)

    drv = I2CDriver(1, 0x42, smbus_factory=lambda bus: SlowBus(dev, bus), combined=False)  # STATUS, then one burst
    with drv:
        a = pump(clock, drv, 10, 0.05)
        slow["at"] = slow["n"] + 1
        b = pump(clock, drv, 10, 0.05)
        st = drv.stats()
    got = np.concatenate([a, b])
    seq, status = check(got, dev.fates())
    lost = np.flatnonzero(status == FIFO_FULL)
    k = np.flatnonzero(got["flags"] & FLAG_FIFO_OVERFLOW)
    assert lost.shape[0] > 0 and st["fifo_overflows"] == 1 and st["gaps"] == 1
    assert k.shape == (1,) and seq[k[0]] == lost[-1] + 1 and seq[k[0] - 1] == lost[0] - 1


@pytest.mark.parametrize("combined", [False, True], ids=["status-then-bursts", "combined-poll"])
@pytest.mark.parametrize("lost_on_the_wire", [False, True], ids=["burst-refused", "burst-lost"])
def test_frames_read_before_the_bus_fails_mid_read_are_kept(lost_on_the_wire, combined):
    # a read of 41 frames (99..139) takes three bursts (16, 16, 9) after STATUS, or the combined poll's first frame
    # and then bursts (16, 16, 8); the bus fails on the last: the frames taken out of the FIFO before it are decoded
    # after the reconnect, before anything newer. A refused burst leaves its frames in the FIFO (nothing lost); a
    # burst lost on the wire loses its frames, the reconnect's gap
    clock, dev, _ = rig(depth=64)
    bursts = {"n": 0, "fail_at": None}

    class FlakyBus(FakeSMBus):
        def i2c_rdwr(self, *msgs):
            failing = len(msgs) == 2 and msgs[1].len > 2 and bursts["n"] + 1 == bursts["fail_at"]
            bursts["n"] += len(msgs) == 2 and msgs[1].len > 2  # a FIFO burst (STATUS reads 2 bytes)
            if failing and not lost_on_the_wire:
                raise OSError(errno.EREMOTEIO, "Remote I/O error (no ACK)")
            super().i2c_rdwr(*msgs)
            if failing:
                raise OSError(errno.EREMOTEIO, "Remote I/O error (no ACK)")

    drv = I2CDriver(1, 0x42, smbus_factory=lambda bus: FlakyBus(dev, bus), combined=combined)
    drv.backoff.initial_s = 0.0
    with drv:
        a = pump(clock, drv, 10, 0.05)
        bursts["fail_at"] = bursts["n"] + 3
        b = pump(clock, drv, 10, 0.2)
        st = drv.stats()
    got = np.concatenate([a, b])
    seq = got["seq"]
    sent = np.flatnonzero(dev.fates()["status"] == SENT)
    lost = np.setdiff1d(sent, seq)
    np.testing.assert_array_equal(lost, np.arange(131 + combined, 140) if lost_on_the_wire else [])
    np.testing.assert_array_equal((got["flags"] & FLAG_GAP_BEFORE) != 0, np.r_[False, np.diff(seq) > 1])
    assert st["disconnects"] == 1 and st["reconnects"] == 1 and st["restarts"] == 0
    assert st["missing"] == lost.shape[0] and st["gaps"] == int(lost.shape[0] > 0)
    k = np.flatnonzero(got["flags"] & FLAG_RECONNECT)
    assert k.shape == (1,) and seq[k[0]] == 140  # the first sample produced after the outage


def test_open_errors_are_named():
    with pytest.raises(DriverError, match=r"I2C bus /dev/i2c-99 does not exist"):
        open_driver("i2c://99/0x42")

    def denied(bus):
        raise PermissionError(errno.EACCES, "Permission denied", f"/dev/i2c-{bus}")

    with pytest.raises(DriverError, match=r"permission denied opening /dev/i2c-1: add your user to group 'i2c'"):
        I2CDriver(1, 0x42, smbus_factory=denied).open()
    _, dev, _ = rig()
    with pytest.raises(DriverError, match="no device answers at address 0x43"):
        I2CDriver(1, 0x43, smbus_factory=lambda b: FakeSMBus(dev, b)).open()

    class Impostor(FakeSMBus):
        def read_byte_data(self, addr, reg, force=None):
            return 0x68 if reg == REG_WHO_AM_I else super().read_byte_data(addr, reg)

    with pytest.raises(DriverError, match="not a gravcal logger: WHO_AM_I = 0x68, expected 0x47"):
        I2CDriver(1, 0x42, smbus_factory=lambda b: Impostor(dev, b)).open()
    with pytest.raises(DriverError, match="outside the 7-bit range"):
        open_driver("i2c://1/0x90")
    with pytest.raises(DriverError, match="output rate 123.0 Hz not supported"):
        open_driver("i2c://1/0x42?rate=123")


def test_fake_spec_in_process_and_empty_reads_do_not_hang():
    drv = open_driver("fake-i2c://0x42?scenario=pattern&seed=1&fs=200&speed=1")
    with drv:
        import time

        t0 = time.monotonic()
        got = []
        while time.monotonic() - t0 < 0.6:
            got.append(drv.read(timeout=0.1))
        got = np.concatenate(got)
    assert 60 <= got.shape[0] <= 200  # ~0.6 s at 200 Hz, generous for a loaded machine
    np.testing.assert_array_equal(got["seq"], np.arange(got["seq"][0], got["seq"][0] + got.shape[0]))
    # a device that never produces (stopped clock): read returns empty within its timeout
    clock, dev, drv = rig()
    with drv:
        t0 = time.monotonic()
        out = drv.read(timeout=0.2)
        assert out.shape == (0,) and time.monotonic() - t0 < 1.5


def test_realtime_device_wakes_the_driver_by_drdy_and_loses_only_the_outage():
    """The device samples in real time (its own thread) and raises DRDY at the watermark; the driver
    sleeps on the line. Across an unplug: no FIFO overflow, exactly the offline samples missing, and
    the reconnect flagged on the first sample produced after it."""
    from gravcal.drivers.rigs.fake_i2c import FakeI2CDriver

    fs, log = 200.0, SentLog()
    dev = FakeI2CDevice(pattern_blocks(seed=3, fs=fs, duration=60.0), fs, fifo_depth=64, log=log,
                        faults=Faults(disconnects=[(0.5, 0.4)]))
    drv = FakeI2CDriver(dev)
    got = []
    with drv:
        while dev.stream_time < 1.6:
            got.append(drv.read(max_samples=4096, timeout=0.5))
        st = drv.stats()
    got = np.concatenate(got)
    status = log.arrays()["status"]
    offline = np.flatnonzero(status == OFFLINE)
    assert offline.shape[0] == round(0.4 * fs)
    assert st["fifo_overflows"] == 0 and not (status == FIFO_FULL).any()
    assert st["missing"] == offline.shape[0] and st["gaps"] == 1
    k = np.flatnonzero(got["flags"] & FLAG_RECONNECT)
    assert k.shape == (1,) and got["seq"][k[0]] == offline[-1] + 1 and got["flags"][k[0]] & FLAG_GAP_BEFORE
    # woken by the line: about one STATUS read per sample (a 1 ms poll would take ~1600)
    assert st["polls"] < 1.5 * got.shape[0] + 50, (st["polls"], got.shape[0])


def test_reading_the_fake_device_imports_nothing_new():
    # a daemon that dropped privileges may not be able to load a module from then on (an installation its user
    # cannot read): the emulated device's reads import nothing (np.unique of no bit errors loaded numpy.ma)
    code = ("import sys\n"
            "from gravcal.drivers.rigs.fake_i2c import FakeI2CDevice, FakeSMBus, ManualClock\n"
            "from gravcal.drivers.rigs.sources import pattern_blocks\n"
            "from gravcal.drivers.i2c import I2CDriver\n"
            "clock = ManualClock()\n"
            "dev = FakeI2CDevice(pattern_blocks(seed=1, fs=200.0, duration=2.0), 200.0, clock=clock)\n"
            "drv = I2CDriver(1, 0x42, smbus_factory=lambda bus: FakeSMBus(dev, bus)).open()\n"
            "drv.read(max_samples=64, timeout=0)\n"
            "before = set(sys.modules)\n"
            "for _ in range(20):\n"
            "    clock.advance(0.05)\n"
            "    drv.read(max_samples=64, timeout=0)\n"
            "print(sorted(set(sys.modules) - before))\n")
    assert run_child(code, timeout=120, what="the I2C driver reading from the fake device").strip() == "[]"
