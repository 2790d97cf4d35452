"""gravcald frame-in -> line-out latency, CPU and RSS per bus at 200 Hz, with 1 and 32 clients (not a test).

    python bench/bench_latency.py [--buses serial,can,i2c] [--clients 1,32] [--seconds 20] [--json PATH]
                                  [--baseline-src DIR] [--latency-budget S]
    python bench/bench_latency.py --medians RUN1.json RUN2.json ...   (repeats run one after the other, each
                                  gravcald run followed by its relay: the medians of CPU, ratio and p99)

Each run starts ``gravcald --emulate --bus BUS --fs 200 --speed 1 --scenario six_position``: the emulator in its
own process on a pty (serial), an slcan pty (can) or behind /dev/i2c-1 of a umockdev testbed (i2c: gravcald runs
under umockdev's preload library, its I2C driver's ioctls are answered by the emulator's process, and without a
DRDY line it polls the FIFO). One client watches every sample with raw fields; with N clients, N - 1 more
processes watch every sample and discard it.

Latency: the emulator sends sample ``seq`` at t0 + seq / fs (CLOCK_MONOTONIC, shared by the processes),
so recv - seq / fs is the frame-in -> line-out delay plus a constant; reported as the spread above the
run's best case (which holds the wire time, 0.63 ms for a 29-byte frame at 460800 baud): p50, p99, p99.9.
CPU: the gravcald process's run time over the measurement (/proc schedstat, ns; utime + stime where the
kernel keeps no schedstats), % of one core, and per thread
(/proc/PID/task/TID; gravcald's ?STATUS names its threads' ids); the emulator's process is reported apart
(a real device costs the host nothing). RSS: VmRSS of gravcald at the end and its peak (VmHWM).
Wake-ups: per thread, the voluntary context switches (the thread slept and was woken) and the involuntary
ones (preempted) per sample over the measurement (/proc/PID/task/TID/status), and the bare relay's below.

``--baseline-src DIR``: run the same measurement first with another source tree (a directory holding
gravcal/core, gravcal/drivers, gravcal/daemon, e.g. an unpacked `git archive` of an older commit, put
first on PYTHONPATH) and report the ratios, measured in the same session on the same loaded machine.

The floor (after each run unless ``--no-floor``): bench/bare_relay.c, built with the system compiler ``cc`` into a
temporary directory, relays the same emulator's tty (or slcan pty, or /dev/i2c-1 under the same preload library,
polled as gravcald's I2C driver polls it) to the same number of client processes: one poll(), the reads, and one
send() per client of one line per frame, of the length gravcald's lines had in the run just before. On serial and
i2c its lines carry the frame's number, so its latency is timed as gravcald's (the floor for latency too; slcan's
lines are not numbered). Its CPU is what the wake-ups, the bus transfers and the send() calls (each waking a client
process) cost on this machine with no daemon work at all. ``--floor-uring`` runs the relay a second time with each
wake-up's sends submitted as one io_uring batch: what batching the system calls would save.
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
from typing import Any, Callable

import numpy as np

from bench_daemon import _extra_watcher  # a raw watcher taking every sample

FS = 200.0
RELAY_SOURCE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "bare_relay.c")
# per bus: the bytes of one sample on the wire (VMIN) and the command that starts the stream (slcan: open)
RELAY_BUS = {"serial": (29, None), "can": (78, "O"), "i2c": (29, None)}
I2C_FIFO_DEPTH = 255  # gravcald --emulate's


def i2c_poll_s(budget_s: float | None) -> float:
    """The poll interval gravcald's I2C driver chooses without a DRDY line (drivers/i2c.py ``_connect``)."""
    return max(0.001, min(I2C_FIFO_DEPTH / FS / 4, max(budget_s or 0.0, 0.5 / FS)))


def _cpu_s(pid: int) -> float:
    """CPU seconds of the whole process: the sum over its threads (a process's own schedstat is its main
    thread's); stat's utime + stime where there are no schedstats."""
    if not os.path.exists(f"/proc/{pid}/schedstat"):
        return _cpu_s_path(f"/proc/{pid}/stat")
    return sum(_task_cpu_s(pid).values())


def _per_task(pid: int, read: Callable[[str], Any], leaf: str) -> dict[int, Any]:
    """``read(/proc/PID/task/TID/leaf)`` for each thread of ``pid`` still running."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            out[int(tid)] = read(f"/proc/{pid}/task/{tid}/{leaf}")
        except OSError:  # the thread ended
            pass
    return out


def _task_cpu_s(pid: int) -> dict[int, float]:
    """CPU seconds of each thread of ``pid`` (utime + stime of /proc/PID/task/TID/stat)."""
    return _per_task(pid, _cpu_s_path, "stat")


def _switches(path: str) -> tuple[int, int]:
    """(voluntary, involuntary) context switches of a process or thread (/proc/.../status)."""
    got = {}
    with open(path) as fh:
        for line in fh:
            key, _, value = line.partition(":")
            if key in ("voluntary_ctxt_switches", "nonvoluntary_ctxt_switches"):
                got[key] = int(value)
    return got["voluntary_ctxt_switches"], got["nonvoluntary_ctxt_switches"]


def _task_switches(pid: int) -> dict[int, tuple[int, int]]:
    """(voluntary, involuntary) context switches of each thread of ``pid``."""
    return _per_task(pid, _switches, "status")


def _wakeups(names: dict[int, str], sw0: dict[int, tuple[int, int]], sw1: dict[int, tuple[int, int]], wall: float,
             rate: float) -> dict[str, dict[str, float]]:
    """Per thread name: voluntary context switches (the thread slept and was woken: a wake-up) and involuntary
    ones (preempted) per second, and both per sample at ``rate`` samples/s."""
    per: dict[str, list[int]] = {}
    for tid, (v1, i1) in sw1.items():
        v0, i0 = sw0.get(tid, (0, 0))
        acc = per.setdefault(names.get(tid, "other"), [0, 0])
        acc[0] += v1 - v0
        acc[1] += i1 - i0
    return {name: {"voluntary_per_s": v / wall, "involuntary_per_s": i / wall,
                   "voluntary_per_sample": v / wall / rate, "involuntary_per_sample": i / wall / rate}
            for name, (v, i) in per.items()}


def _cpu_s_path(path: str) -> float:
    """CPU seconds of a process or thread: its schedstat run time (ns; the scheduler's own sum, exact), or
    utime + stime of its stat (clock ticks, 10 ms: ±0.1 % of one core over 10 s) without schedstats."""
    try:
        with open(path[: -len("stat")] + "schedstat") as fh:
            return int(fh.read().split()[0]) * 1e-9
    except (OSError, ValueError, IndexError):
        pass
    with open(path) as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _status(path: str) -> dict:
    """gravcald's STATUS (its thread ids by name, the emulated device's own CPU)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.connect(path)
        s.settimeout(5.0)
        s.sendall(b"?STATUS;\n")
        buf = b""
        while True:
            data = s.recv(1 << 16)
            if not data:
                raise SystemExit("gravcald closed the connection before answering ?STATUS")
            buf += data
            for line in buf.split(b"\n")[:-1]:
                if b'"STATUS"' in line:
                    return json.loads(line)


# threads of the emulated I2C device inside the daemon's process (a real device costs the host nothing)
DEVICE_THREADS = ("fake-i2c-device",)


def _thread_cpu(pid: int, status0: dict, status1: dict, task0: dict[int, float], task1: dict[int, float],
                wall: float) -> tuple[dict[str, float], float | None]:
    """(% of one core per daemon thread by name, % spent by the emulated device: its threads and its
    bus accesses made from the driver's thread, which are taken out of that thread's figure; None when
    the daemon does not name its threads: a tree from before this report)."""
    if "threads" not in status1:
        return {"(threads not named)": sum(task1[t] - task0.get(t, 0.0) for t in task1) / wall * 100}, None
    names = {tid: name for name, tid in status1["threads"].items()}
    per: dict[str, float] = {}
    for tid, c1 in task1.items():
        name = names.get(tid, "other")
        per[name] = per.get(name, 0.0) + (c1 - task0.get(tid, 0.0)) / wall * 100
    bus0 = status0.get("emulator", {}).get("bus_access_cpu_s")
    bus1 = status1.get("emulator", {}).get("bus_access_cpu_s")
    device = sum(per.pop(n, 0.0) for n in DEVICE_THREADS)
    if bus0 is not None and bus1 is not None:
        bus = (bus1 - bus0) / wall * 100
        device += bus
        if "gravcal-acquisition" in per:
            per["gravcal-acquisition"] -= bus
    return per, device


def _rss_mb(pid: int) -> tuple[float, float]:
    out = {}
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                out[key] = int(value.split()[0]) / 1024
    return out.get("VmRSS", float("nan")), out.get("VmHWM", float("nan"))


def _lines(sock: socket.socket, seconds: float, sizes: list | None = None):
    """(receive time, seq) of every IMU line for ``seconds``; each line's length appended to ``sizes``."""
    buf, rows, t0 = b"", [], time.monotonic()
    sock.settimeout(2.0)
    while time.monotonic() - t0 < seconds:
        try:
            data = sock.recv(1 << 16)
        except socket.timeout:
            continue
        now = time.monotonic()
        if not data:
            break
        *lines, buf = (buf + data).split(b"\n")
        for line in lines:
            if b'"IMU"' in line:
                rows.append((now, json.loads(line)["seq"]))
                if sizes is not None:
                    sizes.append(len(line) + 1)
    return rows


def run(bus: str, clients: int, seconds: float, src: str | None, budget_s: float | None = None,
        extra_args: tuple[str, ...] = ()) -> dict:
    """One measurement; ``extra_args``: more gravcald options (bench/bench_engine_terms.py: its calibration)."""
    import multiprocessing as mp

    tmp = tempfile.mkdtemp(prefix="bench-latency-")
    path = os.path.join(tmp, "g.sock")
    config = []
    if budget_s is not None:
        with open(os.path.join(tmp, "gravcald.toml"), "w", encoding="utf-8") as fh:
            fh.write(f"[device]\nlatency_budget_s = {budget_s!r}\n")
        config = ["--config", os.path.join(tmp, "gravcald.toml")]
    env = dict(os.environ)
    if src:
        env["PYTHONPATH"] = src + os.pathsep + env.get("PYTHONPATH", "")
    cmd = [sys.executable, "-m", "gravcal.daemon.gravcald", "--emulate", "--bus", bus, "--fs", str(FS), "--speed", "1",
           "--scenario", "six_position", "--duration", str(seconds + 300), "--socket", path,
           "--state-dir", os.path.join(tmp, "state"), "--log-level", "warning", *config, *extra_args]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    ctx = mp.get_context("fork")
    stop = ctx.Event()
    extra = []
    try:
        deadline = time.monotonic() + 90
        while not os.path.exists(path):
            if time.monotonic() > deadline or proc.poll() is not None:
                raise SystemExit(f"gravcald --bus {bus} did not start")
            time.sleep(0.1)
        extra = [ctx.Process(target=_extra_watcher, args=(path, 0, stop), daemon=True) for _ in range(clients - 1)]
        for p in extra:
            p.start()
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.connect(path)
        s.sendall(b'?WATCH={"enable":true,"raw":true};\n')
        _lines(s, 8.0)  # warm-up: imports, the emulator's start-up backlog, first windows
        status0 = _status(path)
        emulators = [int(c) for c in open(f"/proc/{proc.pid}/task/{proc.pid}/children").read().split()]
        emu0 = sum(_cpu_s(c) for c in emulators)
        cpu0, task0, t0 = _cpu_s(proc.pid), _task_cpu_s(proc.pid), time.monotonic()
        sw0 = _task_switches(proc.pid)
        sizes: list[int] = []
        rows = _lines(s, seconds, sizes)
        wall = time.monotonic() - t0
        cpu, task1, sw1 = _cpu_s(proc.pid) - cpu0, _task_cpu_s(proc.pid), _task_switches(proc.pid)
        emu_cpu = sum(_cpu_s(c) for c in emulators) - emu0
        status1 = _status(path)
        names = {tid: name for name, tid in status1.get("threads", {}).items()}
        wakeups = _wakeups(names, sw0, sw1, wall, max(len(rows), 1) / wall)
        threads, device = _thread_cpu(proc.pid, status0, status1, task0, task1, wall)
        rss, hwm = _rss_mb(proc.pid)
        s.close()
    finally:
        stop.set()
        for p in extra:
            p.join(5)
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
    a = np.array(rows, dtype=float)
    delay = a[:, 0] - a[:, 1] / FS
    spread = (delay - delay.min()) * 1e3
    pct = {f"p{q:g}": float(np.percentile(spread, q)) for q in (50, 99, 99.9)}
    # the share of the samples the latency path's C step delivered (None: a tree without it)
    dev0, dev1 = status0.get("device", {}), status1.get("device", {})
    in_c = None if "samples_in_c" not in dev1 else (
        (dev1["samples_in_c"] - dev0["samples_in_c"]) / max(1, dev1["samples"] - dev0["samples"]))
    # the C step's batches (reads) delivered without taking the GIL, per sample (None: a tree without the count)
    nogil = None if "batches_without_gil" not in dev1 else (
        (dev1["batches_without_gil"] - dev0["batches_without_gil"]) / max(1, dev1["samples"] - dev0["samples"]))
    # I2C: the driver's STATUS reads (polls) and FIFO_DATA reads (bursts; a combined poll counts in both) per sample
    per_sample = {k: (dev1[k] - dev0[k]) / max(1, dev1["samples"] - dev0["samples"])
                  for k in ("polls", "bursts") if k in dev1 and k in dev0}
    return {"bus": bus, "clients": clients, "samples": int(a.shape[0]), "seconds": wall, "share_in_c": in_c,
            "nogil_batches_per_sample": nogil, "i2c_reads_per_sample": per_sample or None,
            "samples_per_s": a.shape[0] / wall, "latency_ms": pct, "cpu_percent": cpu / wall * 100,
            "cpu_percent_daemon": None if device is None else cpu / wall * 100 - device,
            "cpu_percent_emulated_device": device, "cpu_percent_emulator_process": emu_cpu / wall * 100,
            "cpu_percent_by_thread": threads, "wakeups_by_thread": wakeups,
            "rss_mb": rss, "rss_peak_mb": hwm, "src": src or "this tree", "latency_budget_s": budget_s,
            "line_bytes": float(np.mean(sizes)) if sizes else None,
            "model": status1.get("calibration", {}).get("model")}


def build_relay(tmp: str) -> str | None:
    """bench/bare_relay.c compiled with ``cc`` into ``tmp``: the executable, or None (no compiler, or it failed:
    said on stdout)."""
    exe = os.path.join(tmp, "bare_relay")
    try:
        subprocess.run(["cc", "-O2", "-Wall", "-o", exe, RELAY_SOURCE], check=True, capture_output=True, text=True)
    except FileNotFoundError:
        print("floor: no C compiler (cc) on this machine; the bare relay is skipped", flush=True)
        return None
    except subprocess.CalledProcessError as exc:
        print(f"floor: building bench/bare_relay.c failed, the bare relay is skipped: {exc.stderr.strip()[:300]}",
              flush=True)
        return None
    return exe


def floor(relay: str, bus: str, clients: int, seconds: float, line_bytes: int, uring: bool = False,
          budget_s: float | None = None, i2c_first: int = 1) -> dict:
    """CPU of the bare C relay for the same traffic as gravcald's run: the emulator's stream, ``clients``
    processes each taking one line of ``line_bytes`` per sample; ``uring``: the sends of a wake-up as one
    io_uring batch; ``i2c_first``: frames read with STATUS in each poll's one I2C_RDWR (the driver's combined
    poll: 1; 0: the driver's pattern before it, STATUS alone first and again right after a drain)."""
    import multiprocessing as mp

    frame_bytes, open_cmd = RELAY_BUS[bus]
    tmp = tempfile.mkdtemp(prefix="bench-floor-")
    path = os.path.join(tmp, "relay.sock")
    testbed = os.path.join(tmp, "testbed")  # i2c: the umockdev testbed the emulator serves /dev/i2c-1 in
    i2c = ["--testbed", testbed, "--fifo-depth", str(I2C_FIFO_DEPTH)] if bus == "i2c" else []
    emu = subprocess.Popen([sys.executable, "-m", "gravcal.drivers.rigs.emulate", "--bus", bus, "--fs", str(FS),
                            "--speed", "1", "--scenario", "six_position", "--duration", str(seconds + 120), *i2c],
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    ctx = mp.get_context("fork")
    stop = ctx.Event()
    readers, relay_proc = [], None
    try:
        spec = emu.stdout.readline().strip()  # serial:///.../ttyGRAVCAL0 or can://slcan/.../ttyGRAVCAN0?bitrate=...
        if not spec:
            raise SystemExit(f"the {bus} emulator did not start")
        env = None
        if bus == "i2c":  # i2c://1/0x42: the device node, polled as gravcald's driver polls it, under the preload
            from gravcal.drivers.rigs.i2c_dev import preload_env

            tty, env = f"i2c:/dev/i2c-1:{round(i2c_poll_s(budget_s) * 1e6)}:{i2c_first}", preload_env(testbed)
        else:
            tty = spec.split("://", 1)[1].split("?", 1)[0].removeprefix("slcan")
        relay_proc = subprocess.Popen([relay, *(["--uring"] if uring else []), tty, path, str(clients),
                                       str(line_bytes), str(frame_bytes),
                                       *([open_cmd] if open_cmd else [])], stdout=subprocess.PIPE, text=True, env=env)
        if relay_proc.stdout.readline().strip() != "listening":
            raise SystemExit("the bare relay did not start")
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)  # its first client: the lines timed here
        probe.connect(path)
        readers = [ctx.Process(target=_extra_watcher, args=(path, 0, stop), daemon=True) for _ in range(clients - 1)]
        for p in readers:
            p.start()
        if relay_proc.stdout.readline().strip() != "ready":
            raise SystemExit("the bare relay did not get its clients")
        ready = time.monotonic()
        _lines(probe, 3.0)  # the emulator's start, the clients' first reads
        cpu0, t0 = _cpu_s(relay_proc.pid), time.monotonic()
        sw0 = _switches(f"/proc/{relay_proc.pid}/status")
        rows = [r for r in _lines(probe, seconds) if r[1] >= 0]  # serial: each line's frame number
        cpu, wall = _cpu_s(relay_proc.pid) - cpu0, time.monotonic() - t0
        sw1 = _switches(f"/proc/{relay_proc.pid}/status")
        stop.set()  # the clients leave first, then the relay says what it sent
        probe.close()
        for p in readers:
            p.join(5)
        relay_proc.send_signal(signal.SIGTERM)
        counts = relay_proc.communicate(timeout=10)[0].split()
        lifetime = time.monotonic() - ready
    finally:
        stop.set()
        for p in readers:
            p.join(5)
        for proc in (relay_proc, emu):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
    stats = dict(zip(counts[::2], map(int, counts[1::2])))
    pct = None
    if len(rows) > 100:  # the 16-bit numbers unwrapped; the spread above the best case, as for gravcald
        a = np.array(rows, dtype=float)
        seq = a[:, 1] + 65536 * np.concatenate([[0], np.cumsum(np.diff(a[:, 1]) < -32768)])
        delay = a[:, 0] - seq / FS
        spread = (delay - delay.min()) * 1e3
        pct = {f"p{q:g}": float(np.percentile(spread, q)) for q in (50, 99, 99.9)}
    return {"bus": bus, "clients": clients, "sends": "io_uring batch" if uring else "send() per client",
            "cpu_percent": cpu / wall * 100, "line_bytes": line_bytes,
            "latency_ms": pct,
            "lines_per_s_per_client": stats.get("lines", 0) / clients / lifetime if stats else None,
            "wakeups_per_s": stats.get("wakeups", 0) / lifetime if stats else None,
            "voluntary_switches_per_s": (sw1[0] - sw0[0]) / wall,
            "involuntary_switches_per_s": (sw1[1] - sw0[1]) / wall,
            "bytes_per_s_per_client": stats.get("bytes", 0) / clients / lifetime if stats else None,
            "i2c_reads_per_sample": {k: stats[k] / max(1, stats.get("lines", 0) / clients) for k in ("polls", "bursts")}
            if bus == "i2c" and "polls" in stats else None}


def _floor_latency(f: dict) -> str:
    lat = f.get("latency_ms")
    return "" if not lat else f"  latency p50 {lat['p50']:.2f} p99 {lat['p99']:.2f} p99.9 {lat['p99.9']:.2f} ms"


def _show(r: dict) -> str:
    lat = r["latency_ms"]
    budget = "" if r.get("latency_budget_s") is None else f"budget {r['latency_budget_s'] * 1e3:g} ms  "
    return (f"{budget}{r['bus']:6s} {r['clients']:3d} client(s)  {r['samples_per_s']:6.1f}/s  latency p50 {lat['p50']:7.2f} "
            f"p99 {lat['p99']:7.2f} p99.9 {lat['p99.9']:7.2f} ms  CPU {r['cpu_percent']:5.2f} %  "
            f"RSS {r['rss_mb']:6.1f} MB (peak {r['rss_peak_mb']:.1f})"
            + ("" if r.get("share_in_c") is None else f"  C step {r['share_in_c'] * 100:.1f} % of samples")
            + ("" if r.get("nogil_batches_per_sample") is None
               else f", {r['nogil_batches_per_sample']:.3f} batches per sample without the GIL")
            + ("" if not r.get("i2c_reads_per_sample") else f", I2C reads per sample: " + ", ".join(
                f"{k} {v:.3f}" for k, v in r["i2c_reads_per_sample"].items())) + "\n"
            f"{'':9s}CPU by thread:" + "".join(f" {k} {v:.2f} %" for k, v in sorted(
                r["cpu_percent_by_thread"].items(), key=lambda kv: -kv[1]) if v >= 0.005)
            + ("" if not r.get("wakeups_by_thread") else f"\n{'':9s}wake-ups per sample by thread (voluntary + "
               f"involuntary context switches):" + "".join(
                   f" {k} {w['voluntary_per_sample']:.3f} + {w['involuntary_per_sample']:.3f}"
                   for k, w in sorted(r["wakeups_by_thread"].items(), key=lambda kv: -kv[1]["voluntary_per_s"])
                   if w["voluntary_per_s"] + w["involuntary_per_s"] > 0))
            + (f"\n{'':9s}CPU of the process {r['cpu_percent']:.2f} % = gravcald's own {r['cpu_percent_daemon']:.2f} % "
               f"+ the emulated I2C device in its process {r['cpu_percent_emulated_device']:.2f} % (its sampling "
               f"thread and its bus accesses from the driver's thread)"
               if r["bus"] == "i2c" and r["cpu_percent_emulated_device"] else "")
            + f"\n{'':9s}the emulator's own process (not gravcald's): CPU {r['cpu_percent_emulator_process']:.2f} %")


def medians(paths: list[str]) -> None:
    """The medians over several runs' --json files (interleaved repeats): per bus and client count, gravcald's CPU,
    the bare relay's and their ratio (the median of each run's ratio, so a run's load cancels), and p99 of both."""
    rows: dict[tuple[str, int], list[dict]] = {}
    for path in paths:
        with open(path, encoding="utf-8") as fh:
            for pair in json.load(fh)["runs"]:
                rows.setdefault((pair["this"]["bus"], pair["this"]["clients"]), []).append(pair)
    for (bus, n), pairs in rows.items():
        with_floor = [p for p in pairs if "floor" in p]
        med = lambda xs: float(np.median(xs)) if xs else float("nan")  # noqa: E731
        ratios = [p["this"]["cpu_percent"] / p["floor"]["cpu_percent"] for p in with_floor]
        p99_floor = [p["floor"]["latency_ms"]["p99"] for p in with_floor if p["floor"].get("latency_ms")]
        print(f"median of {len(pairs)}  {bus:6s} {n:3d} client(s)  CPU gravcald "
              f"{med([p['this']['cpu_percent'] for p in pairs]):.2f} %  relay "
              f"{med([p['floor']['cpu_percent'] for p in with_floor]):.2f} %  ratio x{med(ratios):.2f} "
              f"(runs: {', '.join(f'{r:.2f}' for r in ratios)})  p99 gravcald "
              f"{med([p['this']['latency_ms']['p99'] for p in pairs]):.2f} ms  relay {med(p99_floor):.2f} ms",
              flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--buses", default="serial,can,i2c")
    ap.add_argument("--clients", default="1,32")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--baseline-src", metavar="DIR", help="also measure this source tree and report ratios")
    ap.add_argument("--json", metavar="PATH")
    ap.add_argument("--latency-budget", type=float, metavar="S",
                    help="[device] latency_budget_s for both trees (default: the configured default)")
    ap.add_argument("--no-floor", action="store_true", help="skip the bare C relay (the floor) after each run")
    ap.add_argument("--floor-uring", action="store_true",
                    help="also run the bare relay with each wake-up's sends as one io_uring batch")
    ap.add_argument("--floor-i2c-status-first", action="store_true",
                    help="i2c: also run the bare relay as the driver polled before its combined poll (floor0: "
                         "STATUS alone, then bursts, asking again right after a drain): a baseline tree's floor")
    ap.add_argument("--medians", nargs="+", metavar="JSON",
                    help="print the medians over these runs' --json files (interleaved repeats) and exit")
    args = ap.parse_args(argv)
    if args.medians:
        medians(args.medians)
        return 0
    relay = None if args.no_floor else build_relay(tempfile.mkdtemp(prefix="bench-relay-"))
    buses = [b for b in args.buses.split(",") if b]
    counts = [int(c) for c in args.clients.split(",") if c]
    results = []
    for bus in buses:
        for n in counts:
            pair = {}
            for label, src in (("baseline", args.baseline_src), ("this", None)):
                if label == "baseline" and not src:
                    continue
                pair[label] = r = run(bus, n, args.seconds, src, args.latency_budget)
                print(f"{label:8s} {_show(r)}", flush=True)
            if "baseline" in pair:
                b, t = pair["baseline"], pair["this"]
                ratio = {"p99": t["latency_ms"]["p99"] / b["latency_ms"]["p99"],
                         "p50": t["latency_ms"]["p50"] / max(b["latency_ms"]["p50"], 1e-9),
                         "cpu": t["cpu_percent"] / b["cpu_percent"], "rss": t["rss_mb"] / b["rss_mb"]}
                pair["ratio_this_to_baseline"] = ratio
                print(f"{'ratio':8s} {bus:6s} {n:3d} client(s)  p50 x{ratio['p50']:.3f}  p99 x{ratio['p99']:.3f}  "
                      f"CPU x{ratio['cpu']:.2f}  RSS x{ratio['rss']:.2f}", flush=True)
            t = pair["this"]
            floors = [("floor", False, 1)] + ([("floor_uring", True, 1)] if args.floor_uring else [])
            if bus == "i2c" and args.floor_i2c_status_first:
                floors.append(("floor_status_first", False, 0))
            for key, uring, first in floors if relay is not None and bus in RELAY_BUS and t["line_bytes"] else []:
                pair[key] = f = floor(relay, bus, n, args.seconds, round(t["line_bytes"]), uring,
                                      args.latency_budget, first)
                label = "floor" if first else "floor0"
                print(f"{label:8s} {bus:6s} {n:3d} client(s)  a bare C relay of the same traffic, {f['sends']} "
                      f"({f['line_bytes']} bytes per line, "
                      f"{f['bytes_per_s_per_client'] / f['line_bytes']:.1f} lines/s sent per client, "
                      f"{f['wakeups_per_s']:.1f} wake-ups/s, context switches "
                      f"{f['voluntary_switches_per_s']:.1f} + "
                      f"{f['involuntary_switches_per_s']:.1f}/s, {f['voluntary_switches_per_s'] / FS:.3f} + "
                      f"{f['involuntary_switches_per_s'] / FS:.3f} per sample): "
                      f"CPU {f['cpu_percent']:.2f} %  (gravcald {t['cpu_percent']:.2f} %)" + _floor_latency(f)
                      + ("" if not f.get("i2c_reads_per_sample") else ", I2C reads per sample: " + ", ".join(
                          f"{k} {v:.3f}" for k, v in f["i2c_reads_per_sample"].items())),
                      flush=True)
            results.append(pair)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({"fs_hz": FS, "seconds": args.seconds, "runs": results}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
