"""A device that restarts (sequence counter and tick from 0) is a restart, not a 16-bit wrap: the
missing count is the samples really lost, the output seq stays continuous, the first sample after it
carries the gap."""
from __future__ import annotations

import time

import numpy as np
import pytest

from gravcal.core.samples import FLAG_GAP_BEFORE, FLAG_RECONNECT
from gravcal.drivers import open_driver
from gravcal.drivers.codec import TICK_HZ, SeqUnwrapper, encode_frames
from gravcal.drivers.rigs.emulator import PtyLink
from gravcal.drivers.rigs.sources import pattern_blocks
from support.sequence_reference import OneFrameUnwrapper

PERIOD = TICK_HZ // 200  # ticks per sample at 200 Hz


def _ticks(seq):
    return (np.asarray(seq, np.int64) * PERIOD) & 0xFFFFFFFF


def _session(u, raw):
    raw = np.asarray(raw, np.int64)
    return u.unwrap((raw & 0xFFFF).astype(np.uint16), _ticks(raw))


@pytest.mark.parametrize("hint", [None, 2000.0], ids=["no-host-clock", "host-clock"])
def test_restart_behind_an_outage_counts_the_samples_lost(hint):
    u = SeqUnwrapper()
    _session(u, np.arange(30000, 30400))  # a device that has run ~150 s
    u.expect_advance(hint)
    keep, seq, gap = _session(u, np.arange(40, 50))  # restarted: 40 samples since its boot were missed
    assert keep.all()
    np.testing.assert_array_equal(seq, 30400 + 40 + np.arange(10))
    assert gap[0] and not gap[1:].any()
    assert u.restarts == 1 and u.gaps == 1 and u.missing == 40


def test_a_long_outage_without_restart_stays_a_loss():
    u = SeqUnwrapper()
    _session(u, np.arange(30000, 30400))
    u.expect_advance(70000.0)  # ~350 s went by: more than one 16-bit wrap
    keep, seq, gap = _session(u, 30400 + 70000 + np.arange(5))
    np.testing.assert_array_equal(seq, 30400 + 70000 + np.arange(5))
    assert u.restarts == 0 and u.missing == 70000 and gap[0]


def test_restart_without_an_outage_is_not_a_wrap():
    u = SeqUnwrapper()
    _session(u, np.arange(30000, 30400))
    keep, seq, gap = _session(u, np.arange(0, 6))  # believed once three continue each other
    # frames 0 and 1 were held back until the restart was certain: they are the samples lost
    np.testing.assert_array_equal(seq, 30400 + 2 + np.arange(4))
    assert gap[0] and u.restarts == 1 and u.missing == 2


def _frames(seq):
    b = np.concatenate(list(pattern_blocks(seed=2, fs=200.0, duration=len(seq) / 200.0)))[: len(seq)]
    b["seq"] = np.asarray(seq) & 0xFFFF
    b["tick"] = _ticks(seq)
    return b


def test_serial_device_restarted_during_an_unplug(tmp_path):
    link = PtyLink(tmp_path / "ttyR")
    link.connect()
    try:
        drv = open_driver(link.spec)
        drv.backoff.initial_s = 0.01
        got = []
        link.write(encode_frames(_frames(np.arange(30000, 30200))), blocking=True)
        while sum(g.shape[0] for g in got) < 200:
            got.append(drv.read(512, 1.0))
        link.disconnect()  # unplugged ...
        deadline = time.monotonic() + 5
        while drv.stats()["disconnects"] == 0 and time.monotonic() < deadline:
            got.append(drv.read(512, 0.1))
        link.connect()  # ... and back, the logger restarted: 25 samples since its boot not read
        while drv.stats()["reconnects"] == 0 and time.monotonic() < deadline + 5:
            got.append(drv.read(512, 0.1))  # (opening the port flushes what came before)
        link.write(encode_frames(_frames(25 + np.arange(50))), blocking=True)
        while sum(g.shape[0] for g in got) < 250 and time.monotonic() < deadline + 5:
            got.append(drv.read(512, 0.2))
        st = drv.stats()
        drv.close()
    finally:
        link.close()
    got = np.concatenate(got)
    assert got.shape[0] == 250
    assert np.all(np.diff(got["seq"]) > 0)
    k = np.flatnonzero(got["flags"] & FLAG_RECONNECT)
    assert k.shape == (1,) and k[0] == 200 and got["flags"][200] & FLAG_GAP_BEFORE
    assert got["seq"][200] - got["seq"][199] == 26
    assert st["restarts"] == 1 and st["missing"] == 25 and st["gaps"] == 1


@pytest.mark.parametrize("hint", [None, 100.0, 400.0], ids=["no-host-clock", "noticed-late", "noticed-early"])
def test_a_young_session_continuing_after_an_outage_is_not_a_restart(hint):
    # seq and tick both still count from the device's boot (under 65536 samples): every frame looks like a
    # fresh boot by itself; the tick continuing the stream decides, whatever the host's estimate
    u = SeqUnwrapper()
    _session(u, np.arange(0, 3000))
    u.expect_advance(hint)
    keep, seq, gap = _session(u, 3000 + 350 + np.arange(5))
    np.testing.assert_array_equal(seq, 3350 + np.arange(5))
    assert u.restarts == 0 and u.missing == 350 and gap[0]


@pytest.mark.parametrize("path", ["one-frame", "block", "c-step"])
def test_a_stream_read_one_frame_at_a_time_still_tells_a_restart_from_a_wrap(path):
    # an event-driven reader gets one frame per read (the CAN and serial latency paths): the tick period is
    # never seen inside one read, yet a device that restarts behind an outage must not count as a 16-bit wrap
    u = OneFrameUnwrapper() if path == "one-frame" else SeqUnwrapper()
    _session(u, [29999])
    _session(u, [30000])
    if path == "c-step":  # then daemon/_fastpath.c takes the frames that continue the stream; 50 per return
        for k in range(1, 8):
            u.continued(50, int(_ticks(30000 + 50 * k)), None)
    else:
        for raw in range(30001, 30351):
            _session(u, [raw])
    u.expect_advance(2000.0)
    keep, seq, gap = _session(u, np.arange(40, 50))  # restarted: 40 samples since its boot were missed
    np.testing.assert_array_equal(seq, 30351 + 40 + np.arange(10))
    assert gap[0] and u.restarts == 1 and u.missing == 40


@pytest.mark.parametrize("outage", [400, 70000], ids=["2s", "6min"])
@pytest.mark.parametrize("together", [False, True], ids=["held-read-alone", "held-read-with-the-rest"])
def test_frames_a_fifo_held_through_an_outage_continue_the_stream(outage, together):
    # a young session (seq and tick still count from boot), an outage the host saw for ~outage samples, and an
    # I2C FIFO that still held the last 3 frames produced before the device stopped answering: they come first
    # and continue the stream; the first frame produced after the outage carries the gap, no restart
    u = SeqUnwrapper()
    _session(u, np.arange(0, 597))
    u.expect_advance(outage * 1.13 + 50, held=3)
    after = 600 + outage + np.arange(5)
    if together:
        keep, seq, gap = _session(u, np.r_[597:600, after])
    else:
        parts = [_session(u, np.arange(597, 599)), _session(u, [599]), _session(u, after)]
        keep, seq, gap = (np.concatenate(x) for x in zip(*parts))
    assert keep.all()
    np.testing.assert_array_equal(seq, np.r_[597:600, after])
    np.testing.assert_array_equal(gap, np.r_[False, False, False, True, False, False, False, False])
    assert u.restarts == 0 and u.gaps == 1 and u.missing == outage
