"""Serial driver: in-process (pyserial loop://, a pty) and against the emulator in another process."""
from __future__ import annotations

import errno
import time

import numpy as np
import pytest
import serial

from gravcal.core.samples import FLAG_GAP_BEFORE, FLAG_RECONNECT, SAMPLE_DTYPE
from gravcal.drivers import DriverError, open_driver
from gravcal.drivers.codec import encode_frames, wire_roundtrip
from gravcal.drivers.rigs.emulator import OFFLINE, SENT, CORRUPTED, DROPPED, PtyLink, load_sent_log
from gravcal.drivers.rigs.hil import EmulatorProcess
from gravcal.drivers.rigs.sources import pattern_blocks

from tests.support.hil_reads import read_all

PAYLOAD = ("tick", "t1", "t2", "gyro", "temp", "vsupply")


def check_against_log(got: np.ndarray, log: dict) -> tuple[np.ndarray, np.ndarray]:
    """Every sample received was sent intact, with identical values; returns (seq, status)."""
    sent, status = log["samples"], log["status"]
    seq = got["seq"]
    assert np.all(np.diff(seq) > 0), "samples out of order or duplicated"
    np.testing.assert_array_equal(sent["seq"][seq], seq)  # the source numbers samples 0, 1, ...
    assert np.all(status[seq] == SENT)
    for name in PAYLOAD:
        np.testing.assert_array_equal(got[name], sent[name][seq], err_msg=name)
    return seq, status


def test_loop_url_roundtrip_with_garbage():
    blocks = list(pattern_blocks(seed=2, fs=200, duration=1.0, block=50))
    samples = np.concatenate(blocks)
    got = []
    with open_driver("serial:loop://?baudrate=115200") as drv:
        for b in blocks:  # pyserial's loopback holds 4 kB: write a block, read it back
            drv._ser.write(b"\x00garbage\xa5" + encode_frames(b))
            for _ in range(20):
                got.append(drv.read(max_samples=64, timeout=0.5))
                if sum(g.shape[0] for g in got) >= b["seq"][-1] + 1:
                    break
        got = np.concatenate(got)
        st = drv.stats()
    want = wire_roundtrip(samples)
    np.testing.assert_array_equal(got["seq"], want["seq"])
    for name in PAYLOAD:
        np.testing.assert_array_equal(got[name], want[name])
    assert st["frames"] == 200 and st["samples"] == 200 and st["gaps"] == 0
    assert st["bytes_skipped"] == 4 * 9  # the garbage, nothing else
    # host time: newest at reception, earlier ones spaced by device ticks (5 ms at 200 Hz)
    np.testing.assert_allclose(np.diff(got["t"][:50]), 0.005, atol=1e-6)


@pytest.mark.xdist_group("realtime")  # a wall-clock timeout: one real-time test at a time under xdist
def test_silent_port_returns_empty_within_timeout():
    link = PtyLink()
    link.connect()
    try:
        with open_driver(link.spec) as drv:
            t0 = time.monotonic()
            out = drv.read(timeout=0.3)
            elapsed = time.monotonic() - t0
        assert out.shape == (0,) and out.dtype == SAMPLE_DTYPE
        assert 0.25 <= elapsed < 2.0
    finally:
        link.close()


def test_nonexistent_device_is_named():
    with pytest.raises(DriverError, match=r"/dev/ttyGRAVCAL_NOPE does not exist"):
        open_driver("serial:///dev/ttyGRAVCAL_NOPE")


def test_permission_denied_names_dialout(monkeypatch, tmp_path):
    dev = tmp_path / "ttyUSB0"
    dev.touch()

    def denied(port, **kw):
        raise serial.SerialException(errno.EACCES, f"could not open port {port}: [Errno 13] Permission denied")

    monkeypatch.setattr(serial, "serial_for_url", denied)
    with pytest.raises(DriverError, match=r"permission denied opening .*ttyUSB0: add your user to group 'dialout'"):
        open_driver(f"serial://{dev}")


def test_bad_specs():
    with pytest.raises(DriverError, match="unknown option 'baud'.*baudrate"):
        open_driver("serial:///dev/ttyUSB0?baud=9600")
    with pytest.raises(DriverError, match="baudrate='fast'"):
        open_driver("serial:///dev/ttyUSB0?baudrate=fast")
    with pytest.raises(DriverError, match="unknown bus 'usb'"):
        open_driver("usb://x")
    with pytest.raises(DriverError, match="not open"):
        open_driver("serial:loop://", open=False).read()


def test_cross_process_drops_and_bit_errors(tmp_path):
    rec = tmp_path / "sent.npz"
    args = ["--bus", "serial", "--scenario", "pattern", "--fs", "200", "--duration", "3", "--speed", "2",
            "--drop", "0.03", "--ber", "2e-4", "--seed", "7", "--record", str(rec)]
    with EmulatorProcess(args) as emu:
        with open_driver(emu.spec) as drv:
            got = read_all(drv, emu)
            st = drv.stats()
    log = load_sent_log(rec)
    seq, status = check_against_log(got, log)
    first, last = seq[0], seq[-1]
    window = status[first : last + 1]
    # every frame sent intact in the window arrived; gaps exactly at dropped / corrupted frames
    np.testing.assert_array_equal(np.flatnonzero(window == SENT) + first, seq)
    assert (window == DROPPED).sum() >= 3 and (window == CORRUPTED).sum() >= 3  # faults did happen
    gap = np.r_[False, np.diff(seq) > 1]
    np.testing.assert_array_equal((got["flags"] & FLAG_GAP_BEFORE) != 0, gap)
    assert st["gaps"] == gap.sum() and st["missing"] == (last - first + 1) - seq.shape[0]
    assert st["crc_errors"] >= 1 and st["reconnects"] == 0
    assert last >= 590  # read to the end of the 600-sample stream


def test_cross_process_disconnect_and_reconnect(tmp_path):
    rec = tmp_path / "sent.npz"
    link = tmp_path / "ttyGRAVCAL0"
    args = ["--bus", "serial", "--scenario", "pattern", "--fs", "200", "--duration", "3", "--speed", "2",
            "--disconnect-at", "1.0:0.5", "--seed", "3", "--record", str(rec), "--link", str(link)]
    with EmulatorProcess(args) as emu:
        assert emu.spec == f"serial://{link}"
        with open_driver(emu.spec) as drv:
            got = read_all(drv, emu)
            st = drv.stats()
    log = load_sent_log(rec)
    seq, status = check_against_log(got, log)
    offline = np.flatnonzero(status == OFFLINE)
    assert offline[0] == 200 and offline[-1] == 299  # 1.0 s .. 1.5 s at 200 Hz
    rec_idx = np.flatnonzero(got["flags"] & FLAG_RECONNECT)
    assert rec_idx.shape == (1,), "exactly one sample flagged as first after the reconnect"
    k = rec_idx[0]
    assert got["flags"][k] & FLAG_GAP_BEFORE
    assert seq[k - 1] < offline[0] and seq[k] > offline[-1]  # the flagged gap spans the outage
    # Apart from the outage (plus what arrived before the driver reopened, flushed by the
    # port's open), the stream is complete on both sides.
    before, after = seq[:k], seq[k:]
    np.testing.assert_array_equal(before, np.arange(before[0], before[-1] + 1))
    np.testing.assert_array_equal(after, np.arange(after[0], after[-1] + 1))
    assert st["disconnects"] == 1 and st["reconnects"] == 1
    assert any("disconnected" in e for e in emu.events) and any("reconnected" in e for e in emu.events)


def test_one_wake_up_per_frame_however_its_bytes_trickle_in(monkeypatch):
    """A frame's bytes arrive over 0.6 ms at 460800 baud: the driver reads once per frame (the
    terminal's VMIN), not once per byte that wakes select()."""
    import threading

    from gravcal.drivers import serial as serial_mod

    n = 6
    sent = wire_roundtrip(next(pattern_blocks(seed=4, fs=200, duration=n / 200, block=n)))
    reads = []
    read_now = serial_mod._read_now
    monkeypatch.setattr(serial_mod, "_read_now", lambda fd: reads.append(read_now(fd)) or reads[-1])
    link = PtyLink()
    link.connect()
    try:
        with open_driver(link.spec) as drv:
            def trickle() -> None:
                for k in range(n):
                    for b in encode_frames(sent[k : k + 1]):
                        link.write(bytes([b]), True)
                        time.sleep(0.0003)
                    time.sleep(0.005)

            writer = threading.Thread(target=trickle)
            writer.start()
            got, end = [], time.monotonic() + 20
            while sum(g.shape[0] for g in got) < n and time.monotonic() < end:
                got.append(drv.read(timeout=0.5))
            writer.join()
        got = np.concatenate(got)
    finally:
        link.close()
    np.testing.assert_array_equal(got["seq"], sent["seq"])
    for name in PAYLOAD:
        np.testing.assert_array_equal(got[name], sent[name])
    assert 1 <= len(reads) <= n, [len(r) for r in reads]  # each read completes at least one frame
