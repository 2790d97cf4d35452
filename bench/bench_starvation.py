"""Can local clients starve gravcald? (not a test; tests/daemon/test_server_starvation.py asserts a short run)

    python bench/bench_starvation.py [--abuse 20] [--flooders 8] [--slow-readers 20] [--json PATH]

A real-time 200 Hz gravcald (emulated serial, a wake-up per frame) serves one good client watching
every sample; then 8 clients repeat ?STATUS as fast as the socket takes it and 20 clients watch
every sample (raw) while reading 1 KiB a second, all from another process. Prints the good
client's rate and lag (p50/p99/max, arrival minus seq/fs above the quiet phase's best case) quiet
and abused, the device's and server's losses, what the abusers were told, and the daemon's RSS
quiet, abused and after they left.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

from support.faults_starvation import run_starvation  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quiet", type=float, default=5.0, help="seconds watched before the abuse")
    p.add_argument("--abuse", type=float, default=20.0, help="seconds of abuse")
    p.add_argument("--flooders", type=int, default=8)
    p.add_argument("--slow-readers", type=int, default=20)
    p.add_argument("--json", metavar="PATH", help="also write the figures here")
    args = p.parse_args()
    fig = run_starvation(quiet_s=args.quiet, abuse_s=args.abuse, flooders=args.flooders,
                         slow_readers=args.slow_readers)
    for k, v in fig.items():
        print(f"{k:28s} {v}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(fig, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
