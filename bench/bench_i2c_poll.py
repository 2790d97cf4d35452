"""The I2C driver's polled read loop alone, against the emulated device behind /dev/i2c-1 (not a test).

    python bench/bench_i2c_poll.py [--seconds 8] [--poll 0.0025,0.005] [--baseline-src DIR]

This process serves a 200 Hz logger at /dev/i2c-1 of a umockdev testbed (drivers/rigs/i2c_dev.py); a child under
the preload runs the I2C driver's Python read loop (``I2CDriver._read_fifo``: the Python path's, without the daemon) for
``--seconds`` per poll interval: CPU per frame (the child's, the preload's round trips included), I2C_RDWR
transfers per frame (counted by the serving side over the child's whole run) and frames read. ``--baseline-src DIR`` (a tree holding gravcal/...)
runs the same child with that tree first on PYTHONPATH, in the same session.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

CHILD = r"""
import json, resource, sys, time
from gravcal.drivers.i2c import I2CDriver
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime
poll, seconds = float(sys.argv[1]), float(sys.argv[2])
drv = I2CDriver(1, 0x42, poll_s=poll).open()
end, warm = time.monotonic() + 1.0, 0  # warm up
while time.monotonic() < end:
    warm += sum(len(b) for b in drv._read_fifo(end)) // 29
p0, c0, t0 = drv.counters["polls"], cpu(), time.monotonic()
frames, end = 0, t0 + seconds
while time.monotonic() < end:
    frames += sum(len(b) for b in drv._read_fifo(end)) // 29
c, polls = cpu() - c0, drv.counters["polls"] - p0
drv.close()
print(json.dumps({"frames": frames, "all_frames": warm + frames, "polls": polls, "cpu_s": c, "seconds": seconds}))
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--poll", default="0.0025", help="poll intervals [s], comma-separated")
    ap.add_argument("--baseline-src", metavar="DIR")
    args = ap.parse_args(argv)
    from gravcal.drivers.rigs import i2c_dev
    from gravcal.drivers.rigs.fake_i2c import FakeI2CDevice
    from gravcal.drivers.rigs.sources import pattern_blocks

    transfers = [0]
    rdwr = i2c_dev._Client.rdwr

    def counted(client, arg):  # this process's side: costs the measured child nothing
        transfers[0] += 1
        return rdwr(client, arg)

    i2c_dev._Client.rdwr = counted

    fs = 200.0
    device = FakeI2CDevice(pattern_blocks(seed=1, fs=fs, duration=3600.0), fs, fifo_depth=255)
    trees = ([("baseline", args.baseline_src)] if args.baseline_src else []) + [("this", None)]
    with i2c_dev.I2CDevServer(device) as server:
        for poll in [p for p in args.poll.split(",") if p]:
            for label, src in trees:
                env = server.env()
                if src:
                    env["PYTHONPATH"] = os.pathsep.join([src, env.get("PYTHONPATH", "")])
                transfers[0] = 0
                out = subprocess.run([sys.executable, "-c", CHILD, poll, str(args.seconds)], env=env,
                                     capture_output=True, text=True, timeout=args.seconds + 60)
                if out.returncode:
                    raise SystemExit(f"the {label} child failed: {out.stderr[-2000:]}")
                r = json.loads(out.stdout.strip().splitlines()[-1])
                n = max(r["frames"], 1)
                print(f"{label:8s} poll {float(poll) * 1e3:.1f} ms  {r['frames']} frames  "
                      f"{transfers[0] / max(r['all_frames'], 1):.2f} transfers per frame ({r['polls']} polls)  "
                      f"CPU {1e6 * r['cpu_s'] / n:.0f} us per frame, {100 * r['cpu_s'] / r['seconds']:.2f} % of a core",
                      flush=True)
    print(f"load average {' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
