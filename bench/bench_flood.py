"""Multi-command request floods against gravcald at its real rate (not a test).

    python bench/bench_flood.py [--flooders 8] [--seconds 20] [--json PATH]

`gravcald --emulate --bus serial --fs 200 --speed 1` as a subprocess (the emulator in its own child process), one
watcher taking every sample, and ``--flooders`` clients each sending ``?STATUS;?POLL;`` x 72 per line (144 commands
a line) as fast as the socket takes them. Figures: when each flooder was cut off (the server charges the budget per
command: ``request_rate_hz`` 50/s, ``flood_timeout_s`` 10 s), gravcald's CPU [% of one core, utime + stime of the
daemon process, not the emulator] over the flood and over as long a quiet period before it in the same run, and
the watcher's sample rate during the flood.
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time

LINE = b"?STATUS;?POLL;" * 72 + b"\n"


def cpu_s(pid: int) -> float:
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def watcher(sock: str, stop: threading.Event, stamps: list) -> None:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.connect(sock)
    s.sendall(b'?WATCH={"enable":true};\n')
    s.settimeout(1.0)
    buf = b""
    while not stop.is_set():
        try:
            d = s.recv(1 << 16)
        except socket.timeout:
            continue
        if not d:
            break
        buf += d
        *lines, buf = buf.split(b"\n")
        now = time.monotonic()
        stamps.extend(now for x in lines if x.startswith(b'{"class":"IMU"'))
    s.close()


def flooder(sock: str, seconds: float, out: dict, i: int) -> None:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.connect(sock)
    s.setblocking(False)
    t0, answers, closed = time.monotonic(), 0, None
    while time.monotonic() - t0 < seconds:
        try:
            s.send(LINE)
        except BlockingIOError:
            pass
        except OSError:
            closed = time.monotonic() - t0
            break
        try:
            d = s.recv(1 << 20)
            if not d:
                closed = time.monotonic() - t0
                break
            answers += d.count(b"\n")
        except BlockingIOError:
            time.sleep(0.001)
        except OSError:
            closed = time.monotonic() - t0
            break
    s.close()
    out[i] = {"cut_off_s": None if closed is None else round(closed, 2), "lines_received": answers}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--flooders", type=int, default=8)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    tmp = tempfile.mkdtemp(prefix="bench-flood-")
    sock = os.path.join(tmp, "g.sock")
    cmd = [sys.executable, "-m", "gravcal.daemon.gravcald", "--emulate", "--bus", "serial", "--fs", "200", "--speed",
           "1", "--scenario", "six_position", "--duration", str(2 * args.seconds + 120), "--socket", sock,
           "--state-dir", os.path.join(tmp, "state"), "--log-level", "warning"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while not os.path.exists(sock):
            if time.monotonic() > deadline or proc.poll() is not None:
                raise SystemExit("gravcald did not start")
            time.sleep(0.1)
        time.sleep(2.0)
        stop, stamps = threading.Event(), []
        w = threading.Thread(target=watcher, args=(sock, stop, stamps))
        w.start()
        time.sleep(1.0)
        c0, t0 = cpu_s(proc.pid), time.monotonic()
        time.sleep(args.seconds)
        quiet_cpu = 100 * (cpu_s(proc.pid) - c0) / (time.monotonic() - t0)
        results: dict = {}
        c1, t1 = cpu_s(proc.pid), time.monotonic()
        fl = [threading.Thread(target=flooder, args=(sock, args.seconds, results, i)) for i in range(args.flooders)]
        for f in fl:
            f.start()
        for f in fl:
            f.join()
        t2 = time.monotonic()
        flood_cpu = 100 * (cpu_s(proc.pid) - c1) / (t2 - t1)
        stop.set()
        w.join()
        during = [s for s in stamps if t1 <= s <= t2]
        out = {"what": "flood", "flooders": args.flooders, "line_commands": 144, "seconds": args.seconds,
               "gravcald_cpu_quiet_pct": round(quiet_cpu, 2), "gravcald_cpu_flood_pct": round(flood_cpu, 2),
               "watcher_rate_hz_during_flood": round(len(during) / (t2 - t1), 1),
               "flooders_cut_off_s": sorted(r["cut_off_s"] or float("inf") for r in results.values()),
               "lines_received_per_flooder": [results[i]["lines_received"] for i in sorted(results)]}
        print(json.dumps(out, indent=1))
        if args.json:
            with open(args.json, "w") as fh:
                json.dump(out, fh, indent=1)
    finally:
        proc.terminate()
        proc.wait(30)
    return 0


if __name__ == "__main__":
    sys.exit(main())
