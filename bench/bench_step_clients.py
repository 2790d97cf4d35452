"""CPU of the latency path's C step per sample, with N full-rate clients (not a test).

    python bench/bench_step_clients.py [--clients 1,32] [--samples 1000]
    PYTHONPATH=DIR python bench/bench_step_clients.py   # another tree (DIR as for bench_latency --baseline-src)

A pipe stands for the bus (one 29-byte frame every 5 ms, as at 200 Hz), a real SocketServer for the clients
(N Unix-socket watchers, raw, drained by a thread every 2 ms so no send() wakes a reader); the step runs in
this thread as gravcald's acquisition thread runs it. Reported: that thread's CPU time per sample [µs], and
per client added beyond the first. No daemon, no emulator, no detector: only the step and its sends.
"""
from __future__ import annotations

import argparse
import os
import socket
import sys
import tempfile
import threading
import time

import numpy as np

from gravcal.core.calibration import Calibration
from gravcal.core.samples import SAMPLE_DTYPE
from gravcal.daemon import fastpath as fp
from gravcal.daemon._fastpath import Engine, step
from gravcal.daemon.processing import engine_params
from gravcal.daemon.server import SocketServer
from gravcal.drivers.codec import encode_frames
from gravcal.drivers.rigs.sources import pattern_blocks

MAX_FRAMES = 16


def per_sample_us(clients: int, samples: int) -> float:
    s = next(pattern_blocks(seed=3, fs=200, duration=samples / 200, block=samples)).copy()
    s["seq"], s["tick"] = np.arange(samples) & 0xFFFF, np.arange(samples) * 5000
    data = encode_frames(s)
    r, w = os.pipe()
    os.set_blocking(r, False)
    srv = SocketServer(os.path.join(tempfile.mkdtemp(prefix="bench-step-"), "g.sock")).start()
    peers, done = [], threading.Event()
    try:
        for _ in range(clients):
            c = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            c.connect(srv.address)
            c.sendall(b'?WATCH={"enable":true,"raw":true};\n')
            peers.append(c)
        while not srv.fast_watchers or len(srv.fast_watchers) < clients:
            time.sleep(0.01)
        time.sleep(0.3)  # the greetings flushed: nothing pending

        def drain() -> None:
            for c in peers:
                c.setblocking(False)
            while not done.is_set():
                for c in peers:
                    try:
                        while c.recv(1 << 16):
                            pass
                    except BlockingIOError:
                        pass
                time.sleep(0.002)

        def write() -> None:
            for k in range(samples):
                os.write(w, data[29 * k:29 * k + 29])
                time.sleep(0.005)

        threads = [threading.Thread(target=drain, daemon=True), threading.Thread(target=write, daemon=True)]
        for t in threads:
            t.start()
        engine = Engine()
        engine.set_params(engine_params(Calibration("6", np.array([0.5, 0.51, 0.49]), np.diag([0.04, 0.041, 0.039])),
                                        200.0, (2048.0, 357.36), (0, True)))
        ist, fst = np.zeros(fp.IST_N, np.int64), np.zeros(fp.FST_N)
        ist[fp.IST_STAGE_LIMIT] = 1 << 30
        fst[fp.FST_TICK_HZ] = 1e6
        rows, acc = np.zeros(MAX_FRAMES, SAMPLE_DTYPE), np.zeros((MAX_FRAMES, 3))
        gyro, codes, staged = np.zeros(MAX_FRAMES), np.zeros(MAX_FRAMES, np.int8), bytearray()
        t0, n = time.thread_time(), 0
        while n < samples:
            ist[fp.IST_FRAMES] = 0
            _, stopped = step(r, 0.25, MAX_FRAMES, ist, fst, staged, srv.fast_box, engine, rows, acc, gyro, codes)
            if stopped is not None:
                raise SystemExit("a client's socket was full: the step stopped (drain faster)")
            n += int(ist[fp.IST_FRAMES])
            staged.clear()
        return (time.thread_time() - t0) / samples * 1e6
    finally:
        done.set()
        srv.stop()
        for c in peers:
            c.close()
        os.close(r)
        os.close(w)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clients", default="1,32")
    ap.add_argument("--samples", type=int, default=1000)
    args = ap.parse_args(argv)
    got = {n: per_sample_us(n, args.samples) for n in (int(c) for c in args.clients.split(",") if c)}
    for n, us in got.items():
        print(f"{n:3d} client(s): {us:6.1f} µs per sample in the step's thread", flush=True)
    if len(got) >= 2:
        (n0, u0), (n1, u1) = min(got.items()), max(got.items())
        print(f"per client beyond the first: {(u1 - u0) / (n1 - n0):.2f} µs per sample")
    return 0


if __name__ == "__main__":
    sys.exit(main())
