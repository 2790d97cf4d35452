"""The C step on the I2C FIFO (daemon/fastpath.py feeding ``take`` with the bursts smbus2 read) against the
Python path: the same device stream (a 16-bit wrap, gaps, a device restart) through gravcald with and without
it; every client receives the same bytes (``t`` apart), the driver's counters agree.

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
from test_fastpath import assert_same_counts, assert_same_streams

FS = 200.0
HERE = Path(__file__).resolve().parent

# gravcald in the child: started on /dev/i2c-1, two watchers; "settle" on stdin ends it, the result to a file
DAEMON = """
import base64, json, sys
sys.path[:0] = [{tests!r}, {here!r}]
from pathlib import Path
from gravcal.drivers import open_driver
from test_fastpath import Reader, settle, start_daemon, stop_all
tmp, fast = Path(sys.argv[1]), sys.argv[2] == "fast"
drv = open_driver("i2c://1/0x42?tick_hz=1000000")
d = start_daemon(tmp, fast, drv.open())
cfg = d.cfg
readers = {{}}
try:
    readers["plain"] = a = Reader(cfg.socket.path, '?WATCH={{"enable":true}};')
    readers["raw"] = Reader(cfg.socket.path, '?WATCH={{"enable":true,"raw":true}};')
    print("ready", flush=True)
    sys.stdin.readline()
    settle(d, a)
    stats = {{**drv.stats(), "taken_by_c": d._fast.taken if d._fast is not None else 0,
             "published": d.server.published_samples}}
finally:
    out = stop_all(d, readers)
(tmp / f"out-{{fast}}.json").write_text(json.dumps(
    {{"stats": stats, "out": {{k: base64.b64encode(v).decode() for k, v in out.items()}}}}))
"""


def stream() -> np.ndarray:
    seqs = np.r_[np.arange(65300, 65536 + 100), np.arange(65536 + 104, 65536 + 300),  # a wrap, a gap of 3
                 np.arange(0, 200)]  # the device restarted (seq and tick from 0)
    s = next(pattern_blocks(seed=5, fs=FS, duration=seqs.shape[0] / FS, block=seqs.shape[0])).copy()
    ticks = np.r_[seqs[:-200] * 5000, np.arange(200) * 5000]
    s["seq"], s["tick"] = seqs & 0xFFFF, ticks & 0xFFFFFFFF
    return s


def run(tmp_path, fast: bool) -> tuple[dict[str, bytes], dict]:
    samples = stream()
    clock = ManualClock()  # the device samples only as the test advances its clock: the same stream each run
    device = FakeI2CDevice([samples], FS, clock=clock)
    code = DAEMON.format(tests=str(HERE.parent), here=str(HERE))
    with I2CDevServer(device) as server:
        child = subprocess.Popen([sys.executable, "-c", code, str(tmp_path), "fast" if fast else "python"],
                                 env=server.env(), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
        try:
            assert child.stdout.readline().strip() == "ready", child.stderr.read()[-3000:]
            for _ in range(samples.shape[0]):
                clock.advance(1 / FS)
                time.sleep(0.004)
            _, err = child.communicate("settle\n", timeout=120)
        finally:
            if child.poll() is None:
                child.kill()
                child.wait()
    assert child.returncode == 0, err[-3000:]
    got = json.loads((tmp_path / f"out-{fast}.json").read_text())
    return {k: base64.b64decode(v) for k, v in got["out"].items()}, got["stats"]


def test_i2c_clients_receive_the_same_bytes_with_and_without_the_c_step(tmp_path):
    require_umockdev()
    slow, slow_stats = run(tmp_path, fast=False)
    fast, fast_stats = run(tmp_path, fast=True)
    assert_same_counts(slow_stats, fast_stats, ("frames", "crc_errors", "gaps", "missing", "restarts", "samples"),
                       min_share=0.5)
    assert slow_stats["gaps"] >= 1 and slow_stats["restarts"] == 1
    assert_same_streams(slow, fast, min_imu=600)
