"""What waking N client processes per sample costs on this machine, whoever does it (not a test).

    python bench/bench_fanout_floor.py [--clients 1,8,32] [--seconds 5] [--repeat 3] [--json PATH]

Builds bench/wakeup_fanout.c with the system compiler ``cc`` and runs it, interleaved, ``--repeat`` times per
client count and mode, at 200 Hz: ``send`` (a 271-byte line to each client's Unix socket, as gravcald does) and
``futex`` (one FUTEX_WAKE of every client sleeping on a shared word: no socket, no copy, one system call).
Prints the waker's CPU (% of one core; median and range over the repeats) and each extra client's cost per
sample (the slope over the client counts). gravcald's target with 32 clients (CPU <= 2 % of one core) is
below what the futex's wake-ups alone cost here when that figure is above 2 %.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

SOURCE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "wakeup_fanout.c")
MODES = ("send", "futex")


def build(tmp: str) -> str:
    exe = os.path.join(tmp, "wakeup_fanout")
    try:
        subprocess.run(["cc", "-O2", "-Wall", "-o", exe, SOURCE], check=True, capture_output=True, text=True)
    except FileNotFoundError:
        raise SystemExit("bench_fanout_floor: no C compiler (cc) on this machine") from None
    except subprocess.CalledProcessError as exc:
        raise SystemExit(f"bench_fanout_floor: building {SOURCE} failed: {exc.stderr.strip()[:300]}") from None
    return exe


def run_once(exe: str, mode: str, clients: int, seconds: float) -> dict:
    out = subprocess.run([exe, mode, str(clients), str(seconds)], check=True, capture_output=True, text=True,
                         timeout=seconds + 60).stdout.split()
    return {k: float(v) for k, v in zip(out[::2], out[1::2])}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clients", default="1,8,32")
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", metavar="PATH")
    args = ap.parse_args(argv)
    counts = [int(c) for c in args.clients.split(",") if c]
    exe = build(tempfile.mkdtemp(prefix="bench-fanout-"))
    runs: dict[tuple[str, int], list[dict]] = {(m, n): [] for m in MODES for n in counts}
    for _ in range(args.repeat):  # interleaved, so a change in the machine's load touches every cell alike
        for n in counts:
            for mode in MODES:
                runs[mode, n].append(run_once(exe, mode, n, args.seconds))
    print(f"load average at the end: {os.getloadavg()[0]:.2f}")
    table = []
    for mode in MODES:
        medians = []
        for n in counts:
            cpu = np.array([r["cpu_percent"] for r in runs[mode, n]])
            us = float(np.median([r["us_per_sample"] for r in runs[mode, n]]))
            woke = float(np.median([r["client_wakeups_per_sample"] for r in runs[mode, n]]))
            medians.append(us)
            table.append({"mode": mode, "clients": n, "cpu_percent_median": float(np.median(cpu)),
                          "cpu_percent_min": float(cpu.min()), "cpu_percent_max": float(cpu.max()),
                          "us_per_sample_median": us, "client_wakeups_per_sample_median": woke})
            print(f"{mode:6s} {n:3d} client(s)  CPU {np.median(cpu):5.2f} % of one core "
                  f"({cpu.min():.2f}-{cpu.max():.2f})  {us:7.1f} us per sample, each client woken "
                  f"{woke:.3f} times per sample", flush=True)
        if len(counts) > 1:
            slope = float(np.polyfit(counts, medians, 1)[0])
            table.append({"mode": mode, "us_per_extra_client_per_sample": slope})
            print(f"{mode:6s} each extra client: {slope:.2f} us per sample", flush=True)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({"fs_hz": 200.0, "seconds": args.seconds, "repeat": args.repeat, "rows": table}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
