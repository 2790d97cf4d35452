"""The CPU floor of waking a Python thread per sample (not a test): what gravcald's per-sample
latency path costs before any decoding, correction or encoding.

    python bench/bench_wakeup.py [--fs 200] [--seconds 15]

A child process writes a 29-byte frame to a pipe every 1/fs s; this process poll()s and reads it
(``plain``), and in a second run also wakes a second thread through another pipe per frame
(``handoff``, as acquisition wakes the server thread). Prints each run's CPU in % of one core.
"""
from __future__ import annotations

import argparse
import os
import select
import threading
import time

FRAME = b"x" * 29


def _writer(w: int, fs: float, n: int) -> None:
    t0 = time.monotonic()
    for i in range(n):
        delay = t0 + i / fs - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        os.write(w, FRAME)


def measure(handoff: bool, fs: float, seconds: float) -> float:
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(r)
        _writer(w, fs, int(fs * seconds))
        os._exit(0)
    os.close(w)
    wake_r, wake_w = os.pipe()

    def server() -> None:
        while os.read(wake_r, 64):
            pass

    if handoff:
        threading.Thread(target=server, daemon=True).start()
    poller = select.poll()  # as the serial driver: the descriptor registered once
    poller.register(r, select.POLLIN)
    t0, c0 = time.monotonic(), time.process_time()
    while True:
        poller.poll()
        if not os.read(r, 4096):
            break
        if handoff:
            os.write(wake_w, b"\0")
    cpu = (time.process_time() - c0) / (time.monotonic() - t0) * 100
    os.waitpid(pid, 0)
    for fd in (r, wake_r, wake_w):
        os.close(fd)
    return cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fs", type=float, default=200.0)
    ap.add_argument("--seconds", type=float, default=15.0)
    args = ap.parse_args()
    for handoff in (False, True):
        print(f"{'handoff' if handoff else 'plain':8s} {measure(handoff, args.fs, args.seconds):5.2f} % of one core "
              f"at {args.fs:g} wake-ups/s", flush=True)


if __name__ == "__main__":
    main()
