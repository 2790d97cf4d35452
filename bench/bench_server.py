"""Replay throughput of the daemon, end to end, with watching clients (not a test).

    python bench/bench_server.py [--samples 2000000] [--clients 20] [--rate 0] [--profile] [--json PATH]

The daemon (gravcald's Gravcald: acquisition thread -> ring buffer -> processing thread:
detector, recursive estimator, correction -> socket server thread -> clients) runs in this
process on a replay driver that hands out pre-simulated sample blocks as fast as they are
taken (six_position scenario, 200 Hz, seq continuing across repeats), pausing while the ring
buffer is half full or the server lags by 64 blocks (a replay can wait; a live bus cannot). ``--clients`` client
processes each watch every sample (``rate`` 0) and count the lines they receive.

Prints: samples/s through the daemon (wall), the daemon process's CPU seconds per 1e5 samples
(all its threads: "on one core" means this stays under 1 s), lines each client received and
what the server dropped for slow clients. ``--profile`` runs cProfile on the processing and
server threads and prints the top functions.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import socket
import sys
import tempfile
import time

import numpy as np

from gravcal.core.samples import SAMPLE_DTYPE
from gravcal.daemon.config import Config
from gravcal.daemon.service import Gravcald

READ_BLOCK = 2048  # [device] read_block: samples per driver read (a replay file is read in large chunks)


class ReplayDriver:
    """Pre-simulated blocks, repeated with continuing seq, as fast as read() is called."""

    def __init__(self, total: int, fs: float = 200.0, seed: int = 0):
        from gravcal.core.simulate import simulate_blocks

        base = np.concatenate(list(simulate_blocks("six_position", seed=seed, duration=600.0, fs=fs, block=4096)))
        self.base, self.fs, self.total, self.n = base, fs, total, 0

    ring = None  # set after the daemon started: replay waits while the ring buffer is half full or the
    server = None  # server has more than 64 blocks to take (back-pressure a live bus cannot give)

    def read(self, max_samples: int = 256, timeout: float = 0.1) -> np.ndarray:
        while self.ring is not None and (len(self.ring) > self.ring.capacity // 2
                                         or (self.server is not None and self.server.backlog > 64)):
            time.sleep(0.001)
        if self.n >= self.total:
            time.sleep(timeout)
            return np.zeros(0, SAMPLE_DTYPE)
        m = min(max_samples, self.total - self.n)
        i = self.n % self.base.shape[0]
        m = min(m, self.base.shape[0] - i)
        out = self.base[i:i + m].copy()
        out["seq"] = np.arange(self.n, self.n + m)
        out["t"] = out["seq"] / self.fs
        self.n += m
        return out

    def stats(self) -> dict:
        return {"frames": self.n}

    def close(self) -> None:
        pass


def client_proc(path: str, rate: float, expect: int, ready, stop, result) -> None:
    """Watch, count lines and bytes; done once ``expect`` lines arrived (or at ``stop``)."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.connect(path)
    s.sendall(b'?WATCH={"enable":true,"rate":%s};\n' % str(rate).encode())
    s.settimeout(0.2)
    ready.release()
    lines = nbytes = 0
    while lines < expect:
        try:
            data = s.recv(1 << 20)
        except socket.timeout:
            if stop.is_set():
                break
            continue
        if not data:
            break
        lines += data.count(b"\n")
        nbytes += len(data)
    result.put((lines, nbytes, time.perf_counter()))


def _profile_threads() -> dict:
    """cProfile the processing and server threads (wraps their run functions before start)."""
    import cProfile

    from gravcal.daemon.server import SocketServer

    profiles: dict = {}

    def wrap(cls, name, label):
        orig = getattr(cls, name)

        def run(self, *a, **k):
            prof = profiles[label] = cProfile.Profile()
            prof.enable()
            try:
                return orig(self, *a, **k)
            finally:
                prof.disable()

        setattr(cls, name, run)

    wrap(Gravcald, "_process", "processing")
    wrap(SocketServer, "_run", "server")
    return profiles


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=2_000_000)
    ap.add_argument("--clients", type=int, default=20)
    ap.add_argument("--rate", type=float, default=0.0, help="clients' ?WATCH rate [Hz] (0: every sample)")
    ap.add_argument("--read-block", type=int, default=READ_BLOCK, help="samples per driver read (default 2048)")
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--json", metavar="PATH", help="write the figures here")
    args = ap.parse_args(argv)

    tmp = tempfile.mkdtemp(prefix="bench-server-")
    cfg = Config()
    cfg.device.fs_hz = 200.0
    cfg.device.read_block = args.read_block
    cfg.socket.path = os.path.join(tmp, "g.sock")
    # Every client gets every sample: queues deep enough for the whole run (the encoded lines
    # are shared by all queues, so this costs the run's size once, not per client).
    cfg.socket.queue_messages = args.samples + 1000 if args.rate == 0 else 1 << 16
    cfg.socket.queue_bytes = 400 * cfg.socket.queue_messages  # bytes too (a raw line is ~260 B)
    cfg.state.directory = os.path.join(tmp, "state")
    cfg.daemon.log_level = "warning"
    driver = ReplayDriver(args.samples)
    driver.total = 0  # hold the stream until the clients are connected
    d = Gravcald(cfg, driver=driver, environ={})
    driver.ring = d.ring
    profiles = _profile_threads() if args.profile else {}
    d.start()
    driver.server = d.server
    ctx = mp.get_context("fork")
    ready, stop, result = ctx.Semaphore(0), ctx.Event(), ctx.Queue()
    expect = args.samples + 2 if args.rate == 0 else 1 << 62  # + VERSION + WATCH (+ CALIB pushes)
    procs = [ctx.Process(target=client_proc, args=(cfg.socket.path, args.rate, expect, ready, stop, result))
             for _ in range(args.clients)]
    for p in procs:
        p.start()
    for _ in procs:
        ready.acquire()
    while d.server.stats()["clients"] < args.clients or sum(
            1 for c in d.server.stats()["per_client"] if c["watching"]) < args.clients:
        time.sleep(0.05)

    cpu0, t0 = time.process_time(), time.perf_counter()
    driver.total = args.samples
    last, last_t = -1, time.perf_counter()
    while d.server.published_samples < args.samples:
        time.sleep(0.01)
        if d.server.published_samples != last:
            last, last_t = d.server.published_samples, time.perf_counter()
        elif time.perf_counter() - last_t > 10:
            print(f"stalled at {last} published samples (processing errors {d.process_errors})", file=sys.stderr)
            break
    wall = time.perf_counter() - t0
    if args.rate > 0:
        time.sleep(0.5)
        stop.set()
    got = [result.get(timeout=300) for _ in procs]
    wall_clients = max(g[2] for g in got) - t0
    cpu_clients = time.process_time() - cpu0
    st = d.server.stats()
    stop.set()
    for p in procs:
        p.join(10)
    d.request_stop()
    d.shutdown()
    for name, prof in profiles.items():
        import pstats

        print(f"--- profile of the {name} thread (cumulative, top 25)")
        pstats.Stats(prof).sort_stats("tottime").print_stats(25)
    n = args.samples
    lines = [g[0] for g in got]
    print(f"replay: {n} samples at 200 Hz sensor rate, {args.read_block} per read, {args.clients} clients watching "
          f"(rate {args.rate:g})")
    print(f"  daemon          {n / wall:,.0f} samples/s processed and handed to the server ({wall:.2f} s wall)")
    print(f"  end to end      {n / wall_clients:,.0f} samples/s until the last client had every sample "
          f"({wall_clients:.2f} s wall)" if args.rate == 0 else "  end to end      (decimated clients)")
    print(f"  daemon CPU      {cpu_clients:.2f} s for {n} samples = {cpu_clients / n * 1e5:.3f} CPU-s per 1e5 samples "
          f"= {n / cpu_clients:,.0f} samples per CPU-second (all daemon threads, until the clients were served)")
    print(f"  clients         lines received min {min(lines):,} max {max(lines):,} "
          f"(+1 VERSION +1 WATCH +CALIB pushes each); server dropped {st['dropped_messages']:,} for slow clients, "
          f"inbox overruns {st['inbox_overruns']:,}; ring overwritten {d.ring.stats()['overwritten']:,}")
    print(f"  client traffic  {sum(g[1] for g in got) / wall_clients / 1e6:,.1f} MB/s in total")
    if args.json:
        res = {"samples": n, "clients": args.clients, "watch_rate_hz": args.rate, "read_block": args.read_block,
               "daemon_samples_per_s": n / wall, "daemon_wall_s": wall,
               "end_to_end_samples_per_s": n / wall_clients if args.rate == 0 else None,
               "end_to_end_wall_s": wall_clients, "cpu_s": cpu_clients, "cpu_s_per_1e5_samples": cpu_clients / n * 1e5,
               "samples_per_cpu_s": n / cpu_clients, "client_lines_min": min(lines), "client_lines_max": max(lines),
               "dropped_messages": st["dropped_messages"], "inbox_overruns": st["inbox_overruns"],
               "ring_overwritten": d.ring.stats()["overwritten"],
               "client_traffic_mb_per_s": sum(g[1] for g in got) / wall_clients / 1e6}
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(res, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
