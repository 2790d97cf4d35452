"""Socket abuse: bad commands, huge lines, crowds and never-reading clients beside a watching client."""
from __future__ import annotations

import json
import socket
import threading
import time

import numpy as np

from .gravcald_process import GravcaldProcess, rss_kb


def _watch_phase(c, seconds: float, seq: list, lat: list) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        m = c.read_message(timeout=30)
        if m["class"] == "IMU":
            lat.append(time.monotonic() - m["t"])
            seq.append(m["seq"])


def _abusers(path: str, *, bad_commands: int, mb_lines: int, connections: int, never_read: int,
             garbage_bytes: int, stop: threading.Event, tried: dict) -> list[threading.Thread]:
    def conn():
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(10)
        s.connect(path)
        return s

    def never_reading():  # watch everything, read nothing: the server must drop, then hang up
        socks = []
        for _ in range(never_read):
            s = conn()
            s.sendall(b'?WATCH={"enable":true,"raw":true};\n')
            socks.append(s)
        tried["never_read_clients"] += len(socks)
        stop.wait()
        for s in socks:
            s.close()

    def bad_commands_sender():
        s = conn()
        reader = threading.Thread(target=lambda: _drain(s), daemon=True)
        reader.start()
        lines = [b"hello\n", b"?FOO;\n", b'?WATCH={"speed":3};\n', b"?WATCH={nope;\n", b"?POLL=1;\n",
                 b'?WATCH={"rate":-1};\n', b"\xff\xfe\x00garbage\n", b";;;;\n"]
        for i in range(bad_commands):
            s.sendall(lines[i % len(lines)])
            tried["bad_commands"] += 1
        s.close()

    def megabyte_lines():
        for _ in range(mb_lines):
            s = conn()
            try:
                s.sendall(b"?" + b"X" * (1 << 20) + b"\n")
                tried["megabyte_lines"] += 1
            except OSError:
                tried["megabyte_lines_cut_off"] += 1  # hung up on us mid-line: allowed
            s.close()

    def garbage():
        s = conn()
        rng = np.random.default_rng(1)
        data = rng.integers(0, 256, garbage_bytes, dtype=np.uint8).tobytes()
        for k in range(0, len(data), 4096):
            try:
                s.sendall(data[k:k + 4096])
            except OSError:
                break  # hung up on (3 oversized requests): allowed
            tried["garbage_bytes"] += len(data[k:k + 4096])
        s.close()

    def crowd():
        socks = []
        for _ in range(connections):
            try:
                socks.append(conn())
            except OSError:
                tried["connections_refused"] += 1  # connect() failed: the server never saw it
        tried["connections"] += len(socks)
        for s in socks:  # the first line says which: VERSION (accepted) or ERROR (over the limit)
            first = _first_line(s)
            if first.get("class") == "VERSION":
                tried["crowd_accepted"] += 1
            elif first.get("class") == "ERROR" and "too many clients" in first.get("message", ""):
                tried["crowd_told_too_many"] += 1
            else:
                tried["crowd_no_answer"] += 1
        stop.wait()
        for s in socks:
            s.close()

    threads = [threading.Thread(target=t, daemon=True) for t in (never_reading, bad_commands_sender, megabyte_lines, garbage, crowd)]
    for t in threads:
        t.start()
    return threads


def _first_line(s: socket.socket, timeout: float = 10.0) -> dict:
    """The first protocol message on ``s`` as a dict ({} on timeout, EOF or garbage)."""
    buf = b""
    s.settimeout(timeout)
    try:
        while b"\n" not in buf:
            chunk = s.recv(4096)
            if not chunk:
                break
            buf += chunk
        return json.loads(buf.split(b"\n", 1)[0])
    except (OSError, ValueError):
        return {}


def _drain(s: socket.socket) -> None:
    try:
        while s.recv(65536):
            pass
    except OSError:
        pass


def run_socket_abuse(*, seconds: float = 6.0, bad_commands: int = 2000, mb_lines: int = 3, connections: int = 100,
                     never_read: int = 4, garbage_bytes: int = 1 << 20, speed: float = 2.0, fs: float = 200.0) -> dict:
    """A well-behaved watcher before and during abuse of a running gravcald (emulated serial)."""
    d = GravcaldProcess(None, "--bus", "serial", "--scenario", "static", "--speed", str(speed), "--duration", "100000",
                 fs=fs)
    tried = dict.fromkeys(["never_read_clients", "bad_commands", "megabyte_lines", "megabyte_lines_cut_off",
                           "garbage_bytes", "connections", "connections_refused", "crowd_accepted",
                           "crowd_told_too_many", "crowd_no_answer"], 0)
    stop = threading.Event()
    try:
        d.wait_serving()
        probe = d.client()
        with d.client() as c:
            c.set_watch(enable=True, rate=0)
            seq0, lat0, seq1, lat1 = [], [], [], []
            _watch_phase(c, seconds, seq0, lat0)
            rss0 = rss_kb(d.proc.pid)
            threads = _abusers(d.sock, bad_commands=bad_commands, mb_lines=mb_lines, connections=connections,
                               never_read=never_read, garbage_bytes=garbage_bytes, stop=stop, tried=tried)
            poll_ms = []

            def poller():
                while not stop.is_set():
                    t = time.monotonic()
                    probe.poll()
                    poll_ms.append((time.monotonic() - t) * 1e3)
                    stop.wait(0.05)

            pt = threading.Thread(target=poller, daemon=True)
            pt.start()
            _watch_phase(c, seconds, seq1, lat1)
            rss1 = rss_kb(d.proc.pid)
            stop.set()
            for t in threads + [pt]:
                t.join(30)
            st = c.status()
        probe.close()
    finally:
        stop.set()
        code = d.stop()
    seq = np.asarray(seq0 + seq1)
    steps = np.diff(seq)
    p = lambda x, q: round(float(np.percentile(np.asarray(x) * 1e3, q)), 2) if x else None
    return {
        **tried,
        "samples_received": int(seq.size),
        "samples_during_abuse": len(seq1),
        "expected_during_abuse": round(seconds * fs * speed),
        "seq_gaps": int((steps > 1).sum()),
        "seq_backwards": int((steps <= 0).sum()),
        "latency_ms_p50_before": p(lat0, 50), "latency_ms_p99_before": p(lat0, 99),
        "latency_ms_p50_abused": p(lat1, 50), "latency_ms_p99_abused": p(lat1, 99),
        "poll_rtt_ms_p99": round(float(np.percentile(poll_ms, 99)), 2) if poll_ms else None,
        "polls": len(poll_ms),
        "rss_kb_before": rss0, "rss_kb_abused": rss1,
        "clients_rejected": st["server"]["clients_rejected"],
        "clients_stalled": st["server"]["clients_stalled"],
        "inbox_overruns": st["server"]["inbox_overruns"],
        "ring_overwritten": st["ring"]["overwritten"],
        "device_gaps": st["device"].get("gaps"),
        "daemon_exit_code": code,
    }
