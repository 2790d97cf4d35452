"""The C step on the I2C FIFO (daemon/fastpath.py feeding ``take`` with the bursts smbus2 read) against the
Python path: the same device stream (a 16-bit wrap, gaps, a device restart) through gravcald with and without
it; every client receives the same bytes (``t`` apart), the driver's counters agree."""
from __future__ import annotations

import time

import numpy as np

from gravcal.drivers.rigs.fake_i2c import FakeI2CDevice, FakeI2CDriver, ManualClock
from gravcal.drivers.rigs.sources import pattern_blocks
from test_fastpath import Reader, assert_same_counts, assert_same_streams, settle, start_daemon, stop_all

FS = 200.0


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
    drv = FakeI2CDriver(device, realtime=False).open()
    d = start_daemon(tmp_path, fast, drv)
    cfg = d.cfg
    readers = {}
    try:
        readers["plain"] = a = Reader(cfg.socket.path, '?WATCH={"enable":true};')
        readers["raw"] = Reader(cfg.socket.path, '?WATCH={"enable":true,"raw":true};')
        for _ in range(samples.shape[0]):
            clock.advance(1 / FS)
            time.sleep(0.004)
        settle(d, a)
        stats = {**drv.stats(), "taken_by_c": d._fast.taken if d._fast is not None else 0,
                 "published": d.server.published_samples}
    finally:
        out = stop_all(d, readers)
    return out, stats


def test_i2c_clients_receive_the_same_bytes_with_and_without_the_c_step(tmp_path):
    slow, slow_stats = run(tmp_path, fast=False)
    fast, fast_stats = run(tmp_path, fast=True)
    assert_same_counts(slow_stats, fast_stats, ("frames", "crc_errors", "gaps", "missing", "restarts", "samples"),
                       min_share=0.5)
    assert slow_stats["gaps"] >= 1 and slow_stats["restarts"] == 1
    assert_same_streams(slow, fast, min_imu=600)
