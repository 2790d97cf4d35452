"""Codec and driver speed.

    python bench/bench_codec.py [--seconds 10] [--skip-drivers] [--json PATH]

1. Serial frame decoding [frames/s] on one core: one large buffer, and 8-frame reads as the
   serial driver does them at 200 Hz. Target >= 200k frames/s.
2. Driver CPU at 200 Hz [% of one core]: time.process_time of this process while a driver
   reads a real-time emulator (another process) for --seconds. Target <= 1 %.
   I2C: the fake device runs in this process, so its cost is included (an upper bound).
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from gravcal.drivers import open_driver
from gravcal.drivers.codec import FRAME_LEN, FrameDecoder, encode_frames
from gravcal.drivers.rigs.hil import EmulatorProcess
from gravcal.drivers.rigs.sources import pattern_blocks


def bench_decode(n: int = 400_000) -> dict:
    samples = np.concatenate(list(pattern_blocks(seed=0, fs=200, duration=n / 200, block=65536)))
    stream = encode_frames(samples)
    out: dict = {}
    for label, chunk in (("64 kB reads", 65536), ("8-frame reads", 8 * FRAME_LEN), ("1-frame reads", FRAME_LEN)):
        m = n if chunk >= 65536 else n // 10
        data = stream[: m * FRAME_LEN]
        dec = FrameDecoder()
        t0 = time.process_time()
        for i in range(0, len(data), chunk):
            dec.feed(data[i : i + chunk])
        dt = time.process_time() - t0
        assert dec.stats()["frames"] == m
        print(f"decode {label:14s}: {m / dt:12,.0f} frames/s  ({m} frames, {dt:.3f} s CPU)")
        out[f"decode_{label.replace(' ', '_')}_frames_per_s"] = m / dt
    t0 = time.process_time()
    encode_frames(samples)
    out["encode_frames_per_s"] = n / (time.process_time() - t0)
    print(f"encode               : {out['encode_frames_per_s']:12,.0f} frames/s")
    return out


def bench_driver(bus: str, seconds: float) -> dict:
    fs = 200.0
    if bus == "i2c":
        drv = open_driver(f"fake-i2c://0x42?scenario=pattern&fs={fs:g}&speed=1&duration={seconds + 60}")
        emu = None
    else:
        emu = EmulatorProcess(["--bus", bus, "--scenario", "pattern", "--fs", str(fs), "--duration",
                               str(seconds + 60), "--speed", "1"])
        emu.__enter__()
        drv = open_driver(emu.spec)
    try:
        # settle (python-can/slcan open, first reads), then measure
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            drv.read(timeout=0.1)
        n, w0, c0 = 0, time.monotonic(), time.process_time()
        while time.monotonic() - w0 < seconds:
            n += drv.read(max_samples=256, timeout=0.1).shape[0]
        wall, cpu = time.monotonic() - w0, time.process_time() - c0
        st = drv.stats()
    finally:
        drv.close()
        if emu is not None:
            emu.__exit__(None, None, None)
    print(f"driver {bus:6s} at {fs:.0f} Hz: {100 * cpu / wall:6.2f} % of a core "
          f"({n} samples in {wall:.1f} s = {n / wall:.0f}/s, gaps {st['gaps']}, crc/bad {st.get('crc_errors', st.get('bad_frames'))})")
    return {"fs_hz": fs, "cpu_percent_one_core": 100 * cpu / wall, "samples": n, "wall_s": wall,
            "samples_per_s": n / wall, "gaps": st["gaps"], "crc_or_bad": st.get("crc_errors", st.get("bad_frames"))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--skip-drivers", action="store_true")
    ap.add_argument("--json", metavar="PATH", help="write the figures here")
    args = ap.parse_args(argv)
    res = {"decode": bench_decode(), "drivers": {}}
    if not args.skip_drivers:
        for bus in ("serial", "can", "i2c"):
            try:
                res["drivers"][bus] = bench_driver(bus, args.seconds)
            except Exception as exc:  # one bus failing (no python-can slcan, no pty) must not hide the others
                print(f"driver {bus}: failed: {type(exc).__name__}: {exc}", file=sys.stderr)
                res["drivers"][bus] = {"error": f"{type(exc).__name__}: {exc}"}
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(res, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
