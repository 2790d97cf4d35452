"""The C step on a CAN bus over slcan (drivers/can.py fast_entry: the port's slcan lines read in C) against
python-can's path: the same byte stream, on a pty, through gravcald with and without it; every client receives
the same bytes (``t`` apart, never running backwards), the driver's counters agree. The stream holds what the
C step hands back to python-can: a 16-bit wrap, several samples per read, a gap, a garbled line, a BELL, a
sample split across reads, a sample missing a frame, a frame of another id, an extended frame, a device
restart and a reconnect; gravcald corrects all of it with an extended calibration (temperature and supply
terms), which the C step takes as any other."""
from __future__ import annotations

import json
import time

import numpy as np

from gravcal.drivers import open_driver
from gravcal.drivers.can import DEFAULT_BASE_ID, pack_frames
from gravcal.drivers.rigs.can_links import SlcanPtyLink
from gravcal.drivers.rigs.sources import pattern_blocks
from test_fastpath import (EXTENDED, TICKS_PER_SAMPLE, Reader, assert_same_counts, assert_same_streams, settle,
                           start_daemon, stop_all)


def sample_lines(seqs, ticks=None, seed=0, drop_frame: int | None = None) -> list[bytes]:
    """Each sample's four slcan lines as the adapter sends them (``drop_frame``: that frame of the first
    sample lost on the bus)."""
    seqs = np.asarray(seqs, dtype=np.int64)
    s = next(pattern_blocks(seed=seed, fs=200, duration=seqs.shape[0] / 200, block=seqs.shape[0])).copy()
    s["seq"] = seqs & 0xFFFF
    s["tick"] = (seqs * TICKS_PER_SAMPLE if ticks is None else np.asarray(ticks)) & 0xFFFFFFFF
    out = []
    for i, parts in enumerate(pack_frames(s)):
        out.append(b"".join(f"t{DEFAULT_BASE_ID + k:03X}{len(d)}{d.hex().upper()}\r".encode()
                            for k, d in enumerate(parts) if not (i == 0 and k == drop_frame)))
    return out


def run_stream(tmp_path, fast: bool) -> tuple[dict[str, bytes], dict]:
    link = SlcanPtyLink(tmp_path / f"tty-{fast}" / "ttyGRAVCAN0")
    link.connect()
    d = start_daemon(tmp_path, fast, open_driver(link.spec + "&tick_hz=1000000"), calibration=EXTENDED)
    cfg = d.cfg
    readers: dict[str, Reader] = {}

    def write(samples: list[bytes], per_write: int = 1, pause: float = 0.002) -> None:
        for i in range(0, len(samples), per_write):
            link.write(b"".join(samples[i:i + per_write]), True)
            time.sleep(pause)

    try:
        readers["plain"] = a = Reader(cfg.socket.path, '?WATCH={"enable":true};')
        readers["raw"] = Reader(cfg.socket.path, '?WATCH={"enable":true,"raw":true};')
        time.sleep(0.1)  # the adapter's replies to python-can's open commands are read first
        seq = 65400
        write(sample_lines(range(seq, seq + 200)))  # through the 16-bit wrap, one sample per read
        seq += 200
        write(sample_lines(range(seq, seq + 60), seed=1), per_write=3)  # several samples per read
        seq += 60
        settle(d, a)
        write(sample_lines(range(seq + 5, seq + 8), seed=2))  # 5 samples lost
        seq += 8
        link.write(b"tZZ18\r", True)  # a garbled line (bytes lost on the USB link)
        time.sleep(0.02)
        link.write(b"\a", True)  # an error reply
        time.sleep(0.02)
        link.write(f"t{DEFAULT_BASE_ID + 9:03X}20102\r".encode(), True)  # a frame of another id
        time.sleep(0.02)
        link.write(b"T000001008" + b"00" * 8 + b"\r", True)  # an extended frame
        time.sleep(0.02)
        write(sample_lines(range(seq, seq + 20), seed=3))
        seq += 20
        split = b"".join(sample_lines(range(seq, seq + 2), seed=4))
        link.write(split[:50], True)  # a sample split across two reads
        time.sleep(0.05)
        link.write(split[50:], True)
        seq += 2
        write(sample_lines(range(seq, seq + 3), seed=5, drop_frame=3))  # a sample missing its HOUSEKEEPING
        seq += 3
        write(sample_lines(range(seq, seq + 30), seed=6))
        seq += 30
        settle(d, a)
        write(sample_lines(range(0, 20), ticks=np.arange(20) * TICKS_PER_SAMPLE, seed=7))  # a restart, no outage
        write(sample_lines(range(20, 60), ticks=np.arange(20, 60) * TICKS_PER_SAMPLE, seed=8))
        settle(d, a)
        link.disconnect()  # an unplugged adapter; the device restarts meanwhile (seq and tick from 0)
        time.sleep(0.6)
        link.connect()
        time.sleep(1.5)  # the driver reopens the port (backoff)
        write(sample_lines(range(0, 60), ticks=np.arange(60) * TICKS_PER_SAMPLE, seed=9))
        settle(d, a)
        write(sample_lines(range(60, 120), ticks=np.arange(60, 120) * TICKS_PER_SAMPLE, seed=10), per_write=2)
        settle(d, a)
        n = d.server.published_samples
        write(sample_lines([120], ticks=[120 * TICKS_PER_SAMPLE], seed=11, drop_frame=3))  # cut short, the last
        end = time.monotonic() + 5
        while d.server.published_samples == n and time.monotonic() < end:
            time.sleep(0.01)
        stats = {**d.driver.stats(), "taken_by_c": d._fast.taken if d._fast is not None else 0,
                 "nogil": d._fast.nogil if d._fast is not None else 0,
                 "published": d.server.published_samples, "model": d.processor.applied.model}
    finally:
        out = stop_all(d, readers, link)
    return out, stats


COUNTERS = ("can_frames", "orphan_frames", "bad_frames", "partial", "error_frames", "foreign_frames",
            "garbled_lines", "frames", "gaps", "missing", "restarts", "reconnects", "samples")


def test_can_clients_receive_the_same_bytes_with_and_without_the_c_step(tmp_path):
    slow, slow_stats = run_stream(tmp_path, fast=False)
    fast, fast_stats = run_stream(tmp_path, fast=True)
    # an extended calibration (temperature and supply terms) throughout: the C step takes it as any other
    assert slow_stats["model"] == fast_stats["model"] == EXTENDED.model
    assert_same_counts(slow_stats, fast_stats, COUNTERS, min_share=0.6)  # the cases C does not take: python-can
    assert slow_stats["gaps"] >= 1 and slow_stats["garbled_lines"] >= 1 and slow_stats["partial"] == 2
    assert slow_stats["restarts"] >= 1 and slow_stats["reconnects"] == 1
    assert_same_streams(slow, fast, min_imu=400)
    imu = [json.loads(x) for x in fast["raw"].splitlines() if b'"IMU"' in x]
    assert any(m["flags"] & 1 for m in imu)  # a gap flagged (FLAG_GAP_BEFORE)
