"""gravcald's resident memory through client churn (not a test; tests/daemon/test_client_churn.py asserts it).

    python bench/bench_client_churn.py [--bus serial] [--rounds 3] [--queue-mb 1] [--flooders 8]
                                       [--slow-readers 20] [--probe] [--env NAME=VALUE]

A live 200 Hz gravcald (emulated ``--bus``: serial, i2c or can) serves a good watcher; each round, from another
process, ``--flooders`` clients repeat ?STATUS and ``--slow-readers`` raw watchers read 1 KiB a second until
every one's queue is at the byte bound (``--queue-mb``), then all of them leave. Prints the daemon's resident MB
by kind of mapping (tests/support/smaps.py: brk heap, thread arenas, other anonymous, files) after warm-up, with
the queues full and after they left, per round. ``--probe`` also prints gravcald's own view
(daemon/memory_probe.py: tracemalloc by line, or pymalloc's arenas with
``--env GRAVCALD_MEMORY_PROBE_TRACE=0``); tracemalloc inflates the figures.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

from support.client_churn import run_churn  # noqa: E402


def mb(kinds: dict) -> str:
    return " ".join(f"{k} {v / 1024:6.1f}" for k, v in kinds.items())


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bus", default="serial", choices=("serial", "i2c", "can"))
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--queue-mb", type=float, default=1.0)
    p.add_argument("--flooders", type=int, default=8)
    p.add_argument("--slow-readers", type=int, default=20)
    p.add_argument("--probe", action="store_true")
    p.add_argument("--env", action="append", default=[], metavar="NAME=VALUE",
                   help="for gravcald, e.g. MALLOC_ARENA_MAX=2, PYTHONPATH=DIR (another source tree)")
    args = p.parse_args()
    env = dict(e.split("=", 1) for e in args.env)
    with tempfile.TemporaryDirectory(prefix="bench-churn-") as tmp:
        fig = run_churn(bus=args.bus, rounds=args.rounds, queue_bytes=int(args.queue_mb * (1 << 20)),
                        flooders=args.flooders, slow_readers=args.slow_readers,
                        probe_dir=Path(tmp) if args.probe else None, env=env)
    print(f"{args.bus}: resident MB by kind; {args.flooders} flooders + {args.slow_readers} slow readers per round, "
          f"queue bound {args.queue_mb:g} MiB")
    print(f"baseline      {mb(fig['baseline'])}")
    if args.probe:
        print(fig["baseline_probe"])
    for k, r in enumerate(fig["rounds"], 1):
        print(f"round {k} full  {mb(r['full'])}   ({r['queued_bytes'] / 1048576:.1f} MiB queued)")
        if args.probe:
            print(r["probe_full"])
        print(f"round {k} after {mb(r['after'])}")
        if args.probe:
            print(r["probe_after"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
