"""Can local clients starve gravcald? Request floods and slow readers beside one good watcher.

A running gravcald (emulated serial, one frame per wake-up, real time) serves a good client that
watches every sample. Then, from a separate process (its own GIL, like other local users),
``flooders`` clients repeat ``?STATUS`` as fast as the socket takes it and ``slow_readers`` clients
watch every sample with raw fields and read 1 KiB a second. Figures: the good client's sample rate
and its lag (arrival minus seq/fs, above the best case of the quiet phase) before and during
the abuse, what the abusers were told, the device's losses, and the daemon's resident memory
before, during and after the abusers leave.
"""
from __future__ import annotations

import multiprocessing as mp
import socket
import threading
import time

import numpy as np

from .gravcald_process import GravcaldProcess, rss_kb


def _flooder(path: str, stop: threading.Event, out: dict) -> None:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.connect(path)
    s.settimeout(0.2)
    burst = b"?STATUS;\n" * 64
    buf = b""
    while not stop.is_set():
        try:
            s.sendall(burst)
            out["sent"] += 64
        except socket.timeout:
            pass  # reading paused by the server: the kernel buffer is full
        except OSError:
            out["disconnected"] += 1
            return
        try:
            data = s.recv(1 << 16)
            if not data:
                out["disconnected"] += 1
                return
            buf = (buf + data)[-(1 << 16):]
            out["errors"] += data.count(b"too many requests")
            out["answers"] += data.count(b'"class":"STATUS"')
        except socket.timeout:
            pass
        except OSError:
            out["disconnected"] += 1
            return
    s.close()


def _slow_reader(path: str, stop: threading.Event, out: dict) -> None:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.connect(path)
    s.sendall(b'?WATCH={"enable":true,"raw":true};\n')
    s.settimeout(1.0)
    while not stop.wait(1.0):
        try:
            if not s.recv(1024):
                out["disconnected"] += 1
                return
        except socket.timeout:
            pass
        except OSError:
            out["disconnected"] += 1
            return
    s.close()


def abusers_main(path: str, flooders: int, slow_readers: int, seconds: float, result) -> None:
    """Child process: the abusers for ``seconds``, then close everything; counts into ``result``."""
    stop = threading.Event()
    flood = {"sent": 0, "errors": 0, "answers": 0, "disconnected": 0}
    slow = {"disconnected": 0}
    threads = [threading.Thread(target=_flooder, args=(path, stop, flood), daemon=True) for _ in range(flooders)]
    threads += [threading.Thread(target=_slow_reader, args=(path, stop, slow), daemon=True)
                for _ in range(slow_readers)]
    for t in threads:
        t.start()
    result.put("started")
    time.sleep(seconds)
    stop.set()
    for t in threads:
        t.join(5.0)
    result.put({"flood": flood, "slow": slow})


def _watch(c, seconds: float, arrivals: list, times: list, seqs: list, dropped: list) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        m = c.read_message(timeout=10)
        if m["class"] == "IMU":
            arrivals.append(time.monotonic())
            times.append(m["t"])
            seqs.append(m["seq"])
        elif m["class"] == "DROPPED":
            dropped.append(m["count"])


def run_starvation(*, quiet_s: float = 3.0, abuse_s: float = 6.0, flooders: int = 8, slow_readers: int = 20,
                   fs: float = 200.0, after_s: float = 3.0, warmup_s: float = 3.0) -> dict:
    d = GravcaldProcess(None, "--bus", "serial", "--scenario", "static", "--speed", "1", "--duration", "100000", fs=fs)
    ctx = mp.get_context("spawn")
    result = ctx.Queue()
    try:
        d.wait_serving()
        with d.client() as c:
            c.set_watch(enable=True, rate=0)
            _watch(c, warmup_s, [], [], [], [])  # the emulator's start-up catch-up is not the daemon's lag
            quiet = ([], [], [], [])
            _watch(c, quiet_s, *quiet)
            rss_quiet = rss_kb(d.proc.pid)
            child = ctx.Process(target=abusers_main, args=(d.sock, flooders, slow_readers, abuse_s, result))
            child.start()
            abused = ([], [], [], [])
            while result.empty():  # the abusers' start-up counts too, the good client reads throughout
                _watch(c, 0.05, *abused)
            assert result.get() == "started"
            _watch(c, abuse_s - 1.0, *abused)
            rss_abused = rss_kb(d.proc.pid)
            child.join(abuse_s + 30)
            told = result.get(timeout=10)
            after = ([], [], [], [])
            _watch(c, after_s, *after)
            rss_after = rss_kb(d.proc.pid)
            st = c.status()
    finally:
        code = d.stop()
    # lag against the device's clock, seq/fs (the emulated sample time `t` is the driver's tick count, not
    # a clock to measure against), above the quiet phase's best case
    t_quiet = np.asarray(quiet[0]) - np.asarray(quiet[2]) / fs
    best = float(t_quiet.min())
    lag_quiet = (t_quiet - best) * 1e3
    lag_abused = (np.asarray(abused[0]) - np.asarray(abused[2]) / fs - best) * 1e3
    seq = np.asarray(quiet[2] + abused[2] + after[2])
    steps = np.diff(seq)
    span = abused[0][-1] - abused[0][0] if len(abused[0]) > 1 else 0.0
    pct = lambda x, q: round(float(np.percentile(x, q)), 2)
    events = st.get("emulator", {}).get("events", [])
    return {
        "samples_abused": len(abused[2]),
        "rate_abused_hz": round((len(abused[2]) - 1) / span, 2) if span else 0.0,
        "expected_hz": fs,
        "lag_ms_p50_quiet": pct(lag_quiet, 50), "lag_ms_p99_quiet": pct(lag_quiet, 99),
        "lag_ms_p50_abused": pct(lag_abused, 50), "lag_ms_p99_abused": pct(lag_abused, 99),
        "lag_ms_max_abused": round(float(lag_abused.max()), 2),
        "good_client_dropped": int(sum(quiet[3] + abused[3] + after[3])),
        "seq_gaps": int((steps > 1).sum()), "seq_backwards": int((steps <= 0).sum()),
        "flood_requests_sent": told["flood"]["sent"], "flood_errors_seen": told["flood"]["errors"],
        "flood_status_answers": told["flood"]["answers"], "flooders_disconnected": told["flood"]["disconnected"],
        "slow_disconnected": told["slow"]["disconnected"],
        "requests_refused": st["server"]["requests_refused"],
        "server_dropped_messages": st["server"]["dropped_messages"],
        "inbox_overruns": st["server"]["inbox_overruns"],
        "ring_overwritten": st["ring"]["overwritten"],
        "device_gaps": st["device"].get("gaps"),
        "emulator_overruns": sum(1 for e in events if str(e).startswith("overrun")),
        "clients_after": st["server"]["clients"],
        "rss_kb_quiet": rss_quiet, "rss_kb_abused": rss_abused, "rss_kb_after": rss_after,
        "daemon_exit_code": code,
    }
