"""The HIL emulator: slcan dialect, pty link, sources, fault plan, the `emulate` command."""
from __future__ import annotations

import argparse
import json
import os
import select
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np
import pytest

from gravcal.drivers.rigs import emulate
from gravcal.drivers.codec import decode_frames
from gravcal.drivers.rigs.can_links import SlcanPtyLink
from gravcal.drivers.rigs.emulator import (
    DROPPED, SENT, Emulator, Faults, PtyLink, SentLog, load_sent_log,
)
from gravcal.drivers.rigs.hil import EmulatorProcess
from gravcal.drivers.rigs.i2c_dev import preload_env
from gravcal.drivers.rigs.sources import pattern_blocks, replay_source
from support.umockdev import require_umockdev


def read_until(fd: int, terminator_count: int, timeout: float = 5.0) -> bytes:
    out, end = b"", time.monotonic() + timeout
    while out.count(b"\r") + out.count(b"\a") < terminator_count and time.monotonic() < end:
        r, _, _ = select.select([fd], [], [], 0.1)
        if r:
            out += os.read(fd, 4096)
    return out


def test_slcan_link_speaks_the_lawicel_dialect(tmp_path):
    link = SlcanPtyLink(tmp_path / "ttyCAN")
    link.connect()
    fd = os.open(link.link, os.O_RDWR | os.O_NOCTTY)
    try:
        samples = np.concatenate(list(pattern_blocks(seed=1, fs=200, duration=0.01)))  # 2 samples
        status, frames = link.send(samples, Faults(), blocking=True)
        assert np.all(status == 5)  # CLOSED: nothing goes out before the host opens the channel
        os.write(fd, b"C\rS8\r\rV\rO\rQ\rt1231AB\r")
        deadline = time.monotonic() + 5
        while len(link.commands) < 7 and time.monotonic() < deadline:
            link.service(0.05)
        assert link.commands == ["C", "S8", "", "V", "O", "Q", "t1231AB"]
        assert read_until(fd, 7) == b"\r\r\rV1013\r\r\az\r"
        assert link.channel_open
        status, frames = link.send(samples, Faults(), blocking=True)
        assert np.all(status == SENT) and frames.all()
        lines = read_until(fd, 8).split(b"\r")[:8]
        assert [ln[:5] for ln in lines[:4]] == [b"t1008", b"t1017", b"t1027", b"t1035"]
        assert lines[0] == b"t1008" + bytes(samples["seq"][0:1].astype("<u2").tobytes().hex().upper(), "ascii") + \
            samples["tick"][0:1].astype("<u4").tobytes().hex().upper().encode() + \
            samples["gyro"][0:1].astype("<u2").tobytes().hex().upper().encode()
    finally:
        os.close(fd)
        link.close()
    assert not (tmp_path / "ttyCAN").exists()


def test_pty_link_replaces_device_behind_the_same_path(tmp_path):
    link = PtyLink(tmp_path / "ttyX")
    link.connect()
    first = os.readlink(link.link)
    link.disconnect()
    assert not link.link.exists()  # unplugged: the path is gone
    link.connect()
    try:
        fd = os.open(link.link, os.O_RDWR | os.O_NOCTTY)
        s = np.concatenate(list(pattern_blocks(seed=2, fs=100, duration=0.1)))
        status, _ = link.send(s, Faults(), blocking=True)
        data = b""
        while len(data) < 29 * 10:
            data += os.read(fd, 4096)
        os.close(fd)
        np.testing.assert_array_equal(decode_frames(data)["t1"], s["t1"])  # raw mode: bytes intact
        assert os.readlink(link.link).startswith("/dev/pts/") and first.startswith("/dev/pts/")
    finally:
        link.close()


def test_fault_plan_validation_and_bit_flips():
    with pytest.raises(ValueError, match="bit-error rate"):
        Faults(ber=1.5)
    with pytest.raises(ValueError, match="drop probability"):
        Faults(drop=-0.1)
    with pytest.raises(ValueError, match="disconnect 3.0:0.0"):
        Faults(disconnects=[(3.0, 0.0)])
    f = Faults(ber=1e-3, seed=4)
    data = bytearray(100_000)
    hit = f.flip_bits(data)
    n_bits = sum(bin(b).count("1") for b in data)
    # binomial(800000, 1e-3): mean 800, sd 28; 6 sd bounds
    assert 800 - 6 * 28 < n_bits < 800 + 6 * 28 and np.all(np.asarray(data)[hit] != 0)
    np.testing.assert_array_equal(f.offline(np.array([0.0, 1.0, 1.49, 1.5])), [False] * 4)
    g = Faults(disconnects=[(1.0, 0.5)])
    np.testing.assert_array_equal(g.offline(np.array([0.99, 1.0, 1.49, 1.5])), [False, True, True, False])


@pytest.mark.xdist_group("realtime")  # wall-clock pacing: one real-time test at a time under xdist
def test_emulator_paces_in_time_lapse():
    class Capture(PtyLink):
        def __init__(self):
            self.times, self.n = [], 0

        def connect(self):
            pass

        def disconnect(self):
            pass

        def service(self, timeout):
            time.sleep(max(0.0, timeout))

        def send(self, samples, faults, blocking):
            self.times.append((time.monotonic(), samples.shape[0]))
            return np.zeros(samples.shape[0], np.uint8), None

    link = Capture()
    log = SentLog()
    t0 = time.monotonic()
    n = Emulator(pattern_blocks(fs=200, duration=2.0), 200.0, link, speed=8.0, log=log).run()
    wall = time.monotonic() - t0
    assert n == 400 and log.arrays()["samples"].shape == (400,)
    assert 0.24 <= wall < 1.5  # 2 s of stream at 8x = 0.25 s (upper bound generous for loaded CI)


def test_an_overrun_is_logged_and_reported_as_an_event(tmp_path):
    """Nobody reads the pty at 50x: its buffer fills, frames are lost as OVERRUN (a real UART's
    overflow) and the emulator says so, so a test can tell a loaded host from a lossy daemon."""
    events: list[str] = []
    link = PtyLink(tmp_path / "ttyLOG")
    log = SentLog()
    try:
        Emulator(pattern_blocks(fs=200, duration=60.0), 200.0, link, speed=200.0, log=log,
                 on_event=events.append).run()
    finally:
        link.close()
    lost = log.counts().get("overrun", 0)
    assert lost > 0, log.counts()  # 60 s x 200 Hz x 29 bytes = 348 kB: more than a pty holds
    reported = [e for e in events if e.startswith("overrun")]
    assert reported and sum(int(e.split(": ")[1].split()[0]) for e in reported) == lost, (reported[:3], lost)

def test_replay_of_a_recording_written_by_gravcal_simulate(tmp_path):
    from gravcal.io import recordings
    s = np.concatenate(list(pattern_blocks(seed=6, fs=100, duration=1.0)))
    path = tmp_path / "rec.csv"
    recordings.write_recording(path, s)
    src = replay_source(path, block=32)
    assert abs(src.fs - 100.0) < 1e-6
    got = np.concatenate(list(src.blocks))
    for name in ("t1", "t2", "gyro"):
        np.testing.assert_array_equal(got[name], s[name])
    np.testing.assert_allclose(got["temp"], s["temp"], atol=1e-3)
    bad = tmp_path / "bad.csv"
    bad.write_text("t,ax,ay,az\n0,0.5,0.5,0.5\n0.01,0.5,0.5,0.5\n")
    with pytest.raises(ValueError, match="missing column\\(s\\) t1_ax"):
        replay_source(bad)


def parse(argv):
    p = emulate.configure_parser(argparse.ArgumentParser())
    return p.parse_args(argv)


def test_cli_options(capsys):
    a = parse(["--bus", "can", "--speed", "max", "--disconnect-at", "3:1.5", "--disconnect-at", "10:2"])
    assert a.speed == float("inf") and a.disconnect_at == [(3.0, 1.5), (10.0, 2.0)]
    for bad, msg in ((["--disconnect-at", "3"], "T:DUR"), (["--ber", "2"], "probability"),
                     (["--speed", "0"], "speed must be > 0"), (["--bus", "usb"], "invalid choice")):
        with pytest.raises(SystemExit) as e:
            parse(bad)
        assert e.value.code == 2 and msg in capsys.readouterr().err
    assert emulate.main(["--replay", "/nonexistent/rec.csv"]) == 2
    assert "no such recording" in capsys.readouterr().err


I2C_HOST = """
import json, sys, time
from gravcal.drivers.base import open_driver
drv = open_driver(sys.argv[1]).open()
got, quiet_since = 0, time.monotonic()
while time.monotonic() - quiet_since < 1.0 or not got:
    n = drv.read(max_samples=4096, timeout=0.2).shape[0]
    got += n
    quiet_since = time.monotonic() if n else quiet_since
st = drv.stats()
drv.close()
print(json.dumps({"received": got, "missing": st["missing"]}))
"""


def test_cli_i2c_serves_the_device_node_to_another_process(tmp_path):
    require_umockdev()
    rec = tmp_path / "i2c.npz"
    testbed = tempfile.mkdtemp(prefix="gravcal-i2c-")  # a short path: the socket's must fit sun_path
    try:
        with EmulatorProcess(["--bus", "i2c", "--scenario", "pattern", "--fs", "200", "--duration", "2", "--speed", "4",
                              "--drop", "0.05", "--seed", "2", "--record", str(rec), "--testbed", testbed],
                             linger=30) as emu:
            assert emu.spec.startswith("i2c://1/0x42")
            host = subprocess.run([sys.executable, "-c", I2C_HOST, emu.spec], env=preload_env(testbed),
                                  capture_output=True, text=True, timeout=60)
            assert host.returncode == 0, host.stderr[-2000:]
            assert emu.wait_done(30)
    finally:
        shutil.rmtree(testbed, ignore_errors=True)
    got = json.loads(host.stdout.splitlines()[-1])
    log = load_sent_log(rec)
    assert got["received"] == (log["status"] == SENT).sum() > 300
    assert got["missing"] >= (log["status"] == DROPPED).sum() - 2  # drops at the very end are invisible
