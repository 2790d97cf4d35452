"""The C step on the I2C FIFO (daemon/_i2cpoll.c: the FIFO polled through the I2C_RDWR ioctl and its frames
through the engine, without the GIL) against the Python path: the same device stream (a 16-bit wrap, gaps, a
device restart) through gravcald with and without it; every client receives the same bytes (``t`` apart), the
driver's counters agree, and every sample is the reference model's (tests/support/correction_reference.py) under
an extended calibration (temperature and supply terms).

The device is served at /dev/i2c-1 from this process (drivers/rigs/i2c_dev.py) and gravcald runs in a child
process under umockdev's preload library, reading it with the production I2C driver through the device node;
this process advances the device's clock, so both runs see the same stream."""
from __future__ import annotations

import base64
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from gravcal.drivers.rigs.fake_i2c import FakeI2CDevice, ManualClock
from gravcal.drivers.rigs.i2c_dev import I2CDevServer
from gravcal.drivers.rigs.sources import pattern_blocks
from support.umockdev import require_umockdev
from test_fastpath import EXTENDED, assert_same_counts, assert_same_streams

from gravcal.core.samples import FLAG_FIFO_OVERFLOW
from gravcal.daemon.protocol import STANDARD_GRAVITY
from gravcal.drivers.codec import wire_roundtrip
from support.correction_reference import extended_model

FS = 200.0
DEPTH = 128  # the emulated FIFO's frames
HERE = Path(__file__).resolve().parent

# gravcald in the child: started on /dev/i2c-1, two watchers; "settle" on stdin ends it, the result to a file
DAEMON = """
import base64, json, sys
sys.path[:0] = [{tests!r}, {here!r}]
from pathlib import Path
from gravcal.drivers import open_driver
from test_fastpath import EXTENDED, Reader, settle, start_daemon, stop_all
tmp, fast = Path(sys.argv[1]), sys.argv[2] != "python"
drv = open_driver("i2c://1/0x42?tick_hz=1000000" + sys.argv[3])
d = start_daemon(tmp, fast, drv.open(), EXTENDED)
cfg = d.cfg
readers = {{}}
try:
    readers["plain"] = a = Reader(cfg.socket.path, '?WATCH={{"enable":true}};')
    readers["raw"] = Reader(cfg.socket.path, '?WATCH={{"enable":true,"raw":true}};')
    print("ready", flush=True)
    sys.stdin.readline()
    settle(d, a)
    stats = {{**drv.stats(), "taken_by_c": d._fast.taken if d._fast is not None else 0,
             "nogil": d._fast.nogil if d._fast is not None else 0, "published": d.server.published_samples,
             "fs": cfg.device.fs_hz}}
finally:
    out = stop_all(d, readers)
(tmp / "out.json").write_text(json.dumps(
    {{"stats": stats, "out": {{k: base64.b64encode(v).decode() for k, v in out.items()}}}}))
"""


def stream() -> np.ndarray:
    seqs = np.r_[np.arange(65300, 65536 + 100), np.arange(65536 + 104, 65536 + 300),  # a wrap, a gap of 3
                 np.arange(0, 200)]  # the device restarted (seq and tick from 0)
    s = next(pattern_blocks(seed=5, fs=FS, duration=seqs.shape[0] / FS, block=seqs.shape[0])).copy()
    ticks = np.r_[seqs[:-200] * 5000, np.arange(200) * 5000]
    s["seq"], s["tick"] = seqs & 0xFFFF, ticks & 0xFFFFFFFF
    return s


def drained(device: FakeI2CDevice, timeout: float = 30.0) -> None:
    """Wait until the reader has polled twice since the clock last moved and found the FIFO empty."""
    end, seen = time.monotonic() + timeout, device.accesses
    while time.monotonic() < end and (device.accesses < seen + 2 or device._fifo_seq):
        time.sleep(0.02)
    assert not device._fifo_seq, "the reader did not drain the FIFO"


def run(tmp_path, fast: bool, drdy: str | None = None) -> tuple[dict[str, bytes], dict]:
    """The stream through gravcald (``fast``: with the C step); ``drdy``: the DRDY line's value file (a file
    that reads "1": the line always high, so the step reads STATUS and the frames without a poll interval)."""
    samples = stream()
    clock = ManualClock()  # the device samples only as the test advances its clock: the same stream each run
    device = FakeI2CDevice([samples], FS, clock=clock, fifo_depth=DEPTH)
    code = DAEMON.format(tests=str(HERE.parent), here=str(HERE))
    mode = "python" if not fast else "fast" if drdy is None else "drdy"
    work = tmp_path / mode
    work.mkdir()
    with I2CDevServer(device) as server:
        child = subprocess.Popen([sys.executable, "-c", code, str(work), mode, "" if drdy is None else f"&drdy={drdy}"],
                                 env=server.env(), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
        try:
            assert child.stdout.readline().strip() == "ready", child.stderr.read()[-3000:]
            # one sample per poll interval, every 40th step 6 at once (the combined poll's frame, then a burst),
            # and once, with the FIFO drained, DEPTH + 8 at once: an overflow, 8 samples lost (the deep FIFO keeps
            # a reader stalled by the host's load from losing more)
            for i in range(samples.shape[0]):
                if i == 500:
                    drained(device)
                clock.advance((DEPTH + 8 if i == 500 else 6 if i % 40 == 39 else 1) / FS)
                time.sleep(0.004)
            _, err = child.communicate("settle\n", timeout=120)
        finally:
            if child.poll() is None:
                child.kill()
                child.wait()
    assert child.returncode == 0, err[-3000:]
    got = json.loads((work / "out.json").read_text())
    return {k: base64.b64decode(v) for k, v in got["out"].items()}, got["stats"]


def test_i2c_clients_receive_the_same_bytes_with_and_without_the_c_step(tmp_path):
    """Polled, and with a DRDY line (a value file that reads "1": the line always high, so the step asks STATUS
    and the frames without a poll interval)."""
    require_umockdev()
    high = tmp_path / "drdy-value"
    high.write_text("1\n")
    slow, slow_stats = run(tmp_path, fast=False)
    fast, fast_stats = run(tmp_path, fast=True)
    check_against_python_path(slow, slow_stats, fast, fast_stats)
    drdy, drdy_stats = run(tmp_path, fast=True, drdy=str(high))
    check_against_python_path(slow, slow_stats, drdy, drdy_stats)
    assert drdy_stats["polls"] > 2 * fast_stats["polls"], (drdy_stats, fast_stats)


def check_against_python_path(slow: dict[str, bytes], slow_stats: dict, fast: dict[str, bytes],
                              fast_stats: dict) -> None:
    assert_same_counts(slow_stats, fast_stats, ("frames", "crc_errors", "gaps", "missing", "restarts", "samples",
                                                "bytes_skipped", "fifo_overflows"), min_share=0.5)
    assert slow_stats["gaps"] >= 2 and slow_stats["restarts"] == 1 and slow_stats["fifo_overflows"] == 1
    assert fast_stats["bursts"] - fast_stats["polls"] >= 10, fast_stats  # bursts after a combined poll, read in C
    assert_same_streams(slow, fast, min_imu=600)
    # the oracle: each sample published is the device's (found by its tick), corrected by the extended model
    imu = [json.loads(x) for x in fast["raw"].splitlines() if b'"IMU"' in x]
    device = wire_roundtrip(stream())
    index = {int(t): i for i, t in enumerate(device["tick"])}
    rows = device[[index[m["tick"]] for m in imu]]
    assert len(imu) == fast_stats["published"] >= 600
    assert sum(bool(m["flags"] & FLAG_FIFO_OVERFLOW) for m in imu) == 1  # flagged by the driver, after C handed it back
    rows["seq"] = [m["seq"] for m in imu]
    want = extended_model(EXTENDED, rows, fast_stats["fs"], STANDARD_GRAVITY)
    np.testing.assert_allclose(np.array([m["acc"] for m in imu]), want, rtol=0, atol=6e-6)  # the line's 5 decimals
