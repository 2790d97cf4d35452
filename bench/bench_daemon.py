"""gravcald at its real rate: latency, CPU, memory (not a test).

    python bench/bench_daemon.py latency [--seconds 60] [--latency-budget-s 0] [--watch-rate 0] [--clients 1] [--json PATH]
    python bench/bench_daemon.py memory  [--samples 20000000] [--json PATH]

latency: `gravcald --emulate --bus serial --fs 200 --speed 1` as a subprocess (the emulator in
its own child process on a real pty, the daemon opening it like a USB adapter), one client
watching every sample with raw fields. Per sample the client computes recv time - ``t``
(CLOCK_MONOTONIC on both sides). Two figures:
  - wire -> client: every sample; ``t`` is the driver's stamp (reception time of the newest
    sample of a read, earlier ones back-dated by device ticks), so this includes what the serial
    driver holds back under ``--latency-budget-s`` (default 0: every frame as it arrives; 0.08
    is the former 16-frame batching at 200 Hz);
  - read -> client: the newest sample of each driver read only (its ``t`` IS the moment the
    driver returned it): acquisition -> processing -> server -> socket write -> client wake.
CPU: utime+stime of the gravcald process (not the emulator) over the run, % of one core.
``--clients N``: N - 1 more client processes watch at the same rate (raw) and discard what they get,
so the latency and CPU figures hold with N clients connected.

memory: the daemon in this process on a replay driver (bench_server.ReplayDriver, as fast as
processing takes it, 200 Hz sensor time), no clients; RSS sampled every 1e6 samples; prints
the RSS series and the least-squares slope, extrapolated to 1e8 samples.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time

import numpy as np

TICK_HZ = 1_000_000  # drivers.codec.TICK_HZ (device ticks at --speed 1, every scenario)


def _cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime


def _extra_watcher(path: str, rate: float, stop) -> None:
    """A client watching at ``rate`` (0: every sample) with raw fields, reading and discarding."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.connect(path)
    s.sendall(b'?WATCH={"enable":true,"rate":%s,"raw":true};\n' % str(rate).encode())
    s.settimeout(0.2)
    while not stop.is_set():
        try:
            if not s.recv(1 << 20):
                break
        except socket.timeout:
            continue
    s.close()


def latency(args) -> dict:
    import multiprocessing as mp

    tmp = tempfile.mkdtemp(prefix="bench-daemon-")
    sock = os.path.join(tmp, "g.sock")
    opts = ["--driver-options", f"latency_budget_s={args.latency_budget_s}"]
    cmd = [sys.executable, "-m", "gravcal.daemon.gravcald", "--emulate", "--bus", "serial", "--fs", "200",
           "--speed", "1", "--scenario", "six_position", "--duration", str(args.seconds + 120), "--socket", sock,
           "--state-dir", os.path.join(tmp, "state"), "--log-level", "warning", *opts]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        from gravcal.clients.client import Client

        deadline = time.monotonic() + 60
        while not os.path.exists(sock):
            if time.monotonic() > deadline or proc.poll() is not None:
                raise SystemExit("gravcald did not start")
            time.sleep(0.1)
        time.sleep(2.0)  # let the emulator start streaming
        ctx = mp.get_context("fork")
        stop_extra = ctx.Event()
        extra = [ctx.Process(target=_extra_watcher, args=(sock, args.watch_rate, stop_extra), daemon=True)
                 for _ in range(max(0, args.clients - 1))]
        for p in extra:
            p.start()
        c = Client(sock, timeout=10)
        c.set_watch(enable=True, rate=args.watch_rate, raw=True)
        s = c._sock
        s.settimeout(5)
        buf = bytearray()
        rows = []  # (recv time, t, tick)
        cpu0, t0 = _cpu_s(proc.pid), time.monotonic()
        while time.monotonic() - t0 < args.seconds:
            data = s.recv(1 << 16)
            now = time.monotonic()
            if not data:
                break
            buf += data
            *lines, rest = bytes(buf).split(b"\n")
            buf = bytearray(rest)
            for line in lines:
                m = json.loads(line)
                if m.get("class") == "IMU":
                    rows.append((now, m["t"], m["tick"]))
        wall = time.monotonic() - t0
        cpu = _cpu_s(proc.pid) - cpu0
        c.close()
        stop_extra.set()
        for p in extra:
            p.join(5)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(30)
    a = np.array(rows, dtype=float)
    lat_all = (a[:, 0] - a[:, 1]) * 1e3
    # samples of one driver read share t - tick/TICK_HZ; the newest of each has the largest tick
    key = np.round((a[:, 1] - a[:, 2] / TICK_HZ) * 1e7)
    newest = np.r_[key[1:] != key[:-1], True]
    lat_read = lat_all[newest]
    print(f"gravcald --emulate --bus serial --fs 200 --speed 1, latency_budget_s={args.latency_budget_s}, {args.clients} "
          f"client(s): {a.shape[0]} samples in {wall:.1f} s ({a.shape[0] / wall:.1f}/s), {int(newest.sum())} driver reads")
    for name, x in (("wire -> client (all samples)", lat_all), ("read -> client (newest of each read)", lat_read)):
        print(f"  latency {name:38s} p50 {np.percentile(x, 50):7.2f} ms  p99 {np.percentile(x, 99):7.2f} ms  "
              f"max {x.max():7.2f} ms")
    print(f"  gravcald CPU {cpu:.2f} s in {wall:.1f} s = {cpu / wall * 100:.2f} % of one core "
          f"({args.clients} client(s) watching {'every sample' if args.watch_rate == 0 else f'at {args.watch_rate:g} Hz'}, raw fields)")
    pct = lambda x, q: float(np.percentile(x, q))  # noqa: E731
    return {"what": "latency", "fs_hz": 200.0, "bus": "serial (pty emulator, --speed 1)", "clients": args.clients,
            "latency_budget_s": args.latency_budget_s, "watch_rate_hz": args.watch_rate, "seconds": wall,
            "samples": int(a.shape[0]), "samples_per_s": a.shape[0] / wall, "driver_reads": int(newest.sum()),
            "wire_to_client_ms": {"p50": pct(lat_all, 50), "p99": pct(lat_all, 99), "max": float(lat_all.max())},
            "read_to_client_ms": {"p50": pct(lat_read, 50), "p99": pct(lat_read, 99), "max": float(lat_read.max())},
            "cpu_percent_one_core": cpu / wall * 100}


def memory(args) -> dict:
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from bench_server import ReplayDriver

    from gravcal.daemon.config import Config
    from gravcal.daemon.service import Gravcald

    tmp = tempfile.mkdtemp(prefix="bench-daemon-mem-")
    cfg = Config()
    cfg.device.fs_hz = 200.0
    cfg.socket.path = os.path.join(tmp, "g.sock")
    cfg.state.directory = os.path.join(tmp, "state")
    cfg.state.save_interval_s = 5.0
    cfg.daemon.log_level = "warning"
    driver = ReplayDriver(args.samples)
    d = Gravcald(cfg, driver=driver, environ={})
    driver.ring = d.ring
    page = os.sysconf("SC_PAGE_SIZE")

    def rss_mb() -> float:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * page / 1e6

    d.start()
    driver.server = d.server
    # a decimated watcher, as `gravcal watch` would be
    w = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    w.connect(cfg.socket.path)
    w.sendall(b'?WATCH={"enable":true,"rate":10};\n')
    w.setblocking(False)
    series = []
    step = 1_000_000
    t0 = time.perf_counter()
    nxt = 0
    while d.server.published_samples < args.samples:
        time.sleep(0.05)
        try:
            while w.recv(1 << 20):
                pass
        except BlockingIOError:
            pass
        if d.server.published_samples >= nxt:
            series.append((d.server.published_samples, rss_mb()))
            nxt += step
    wall = time.perf_counter() - t0
    series.append((d.server.published_samples, rss_mb()))
    d.request_stop()
    d.shutdown()
    n, r = np.array(series).T
    late = n >= n.max() * 0.25  # after warm-up (imports, first allocations)
    slope = np.polyfit(n[late], r[late], 1)[0]
    print(f"memory: {int(n.max()):,} samples (200 Hz sensor time: {n.max() / 200 / 3600:.1f} h) in {wall:.0f} s, "
          f"one watcher at 10 Hz")
    print("  RSS [MB] at " + ", ".join(f"{int(a / 1e6)}M: {b:.1f}" for a, b in series[:: max(1, len(series) // 12)]))
    print(f"  slope after warm-up {slope * 1e6 * 1e3:+.3f} kB per 1e6 samples -> {slope * 1e8:+.2f} MB "
          f"extrapolated over 1e8 samples (RSS now {r[-1]:.1f} MB)")
    half = n >= n.max() * 0.5
    slope_half = float(np.polyfit(n[half], r[half], 1)[0]) if half.sum() >= 3 else float("nan")
    jumps = [[int(n[i + 1]), float(r[i + 1] - r[i])] for i in range(len(n) - 1) if r[i + 1] - r[i] > 2.0]
    print(f"  second half: slope {slope_half * 1e6 * 1e3:+.3f} kB per 1e6 samples; steps > 2 MB at "
          + (", ".join(f"{a / 1e6:.0f}M (+{b:.1f} MB)" for a, b in jumps) or "none"))
    return {"what": "memory", "samples": int(n.max()), "sensor_hours_at_200hz": float(n.max() / 200 / 3600),
            "rss_mb_max": float(r.max()), "slope_second_half_mb_per_1e6": slope_half * 1e6, "rss_steps_mb": jumps,
            "wall_s": wall, "samples_per_s": float(n.max() / wall), "watchers": 1,
            "rss_mb_series": [[int(a), float(b)] for a, b in series], "rss_mb_end": float(r[-1]),
            "slope_mb_per_1e6": float(slope * 1e6), "extrapolated_growth_mb_per_1e8": float(slope * 1e8),
            "extrapolated": bool(n.max() < 1e8)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    lat = sub.add_parser("latency")
    lat.add_argument("--seconds", type=float, default=60.0)
    lat.add_argument("--latency-budget-s", type=float, default=0.0, help="the serial driver's latency budget [s]")
    lat.add_argument("--watch-rate", type=float, default=0.0,
                     help="the client's ?WATCH rate [Hz] (0: every sample; 10: like `gravcal watch`, for the CPU figure)")
    lat.add_argument("--clients", type=int, default=1, help="clients connected, all watching every sample (default 1)")
    lat.add_argument("--json", metavar="PATH", help="write the figures here")
    mem = sub.add_parser("memory")
    mem.add_argument("--samples", type=int, default=20_000_000)
    mem.add_argument("--json", metavar="PATH", help="write the figures here")
    args = ap.parse_args(argv)
    res = latency(args) if args.what == "latency" else memory(args)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(res, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
