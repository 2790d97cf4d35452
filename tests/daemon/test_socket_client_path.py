"""The socket as a program author meets it from docs/socket-protocol.md: requests a gpsd client sends."""
import json

import pytest

from gravcal.daemon.server import ServerConfig, SocketServer
from test_server import Raw

DEVICE = {"spec": "serial:///dev/ttyUSB0?baudrate=460800", "bus": "serial", "device": "/dev/ttyUSB0",
          "connected": True, "rate_hz": 199.5, "samples": 1234, "reconnects": 2, "crc_errors": 7}


@pytest.fixture
def served(tmp_path):
    path = str(tmp_path / "g.sock")
    srv = SocketServer(path, config=ServerConfig(), status_provider=lambda: {"device": dict(DEVICE)})
    srv.start()
    try:
        yield path
    finally:
        srv.stop()


def test_devices_names_the_device_from_status(served):
    c = Raw(served)
    assert c.line()["class"] == "VERSION"
    c.send(b"?devices;?STATUS;\n")
    devices, status = c.line(), c.line()
    assert devices["class"] == "DEVICES" and status["class"] == "STATUS"
    [entry] = devices["devices"]
    assert entry["class"] == "DEVICE" and entry["path"] == status["device"]["spec"] == DEVICE["spec"]
    for key in ("bus", "device", "connected", "rate_hz", "samples", "reconnects"):
        assert entry[key] == status["device"][key], key
    assert "crc_errors" not in entry


def _one_shot_server(path, greeting: bytes):
    """A listener that greets one client with ``greeting`` and holds the connection until closed."""
    import socket
    import threading

    lsock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    lsock.bind(path)
    lsock.listen(1)

    def serve():
        conn, _ = lsock.accept()
        conn.sendall(greeting)
        conn.recv(1)  # until the client closes
        conn.close()

    threading.Thread(target=serve, daemon=True).start()
    return lsock


def test_client_refuses_another_protocol_major_with_a_clear_message(tmp_path):
    from gravcal.clients.client import Client, ClientError

    path = str(tmp_path / "g.sock")
    lsock = _one_shot_server(path, b'{"class":"VERSION","release":"9.0","proto_major":2,"proto_minor":1}\n')
    try:
        with pytest.raises(ClientError, match=r"speaks protocol 2\.1; this client speaks 1\.1"):
            Client(path, timeout=5)
    finally:
        lsock.close()


def test_client_accepts_a_newer_minor(tmp_path):
    from gravcal.clients.client import Client

    path = str(tmp_path / "g.sock")
    lsock = _one_shot_server(path, b'{"class":"VERSION","release":"0.2","proto_major":1,"proto_minor":7}\n')
    try:
        with Client(path, timeout=5) as c:
            assert c.version["proto_minor"] == 7
    finally:
        lsock.close()


def test_permission_denied_names_the_group_rule(tmp_path, monkeypatch):
    import socket

    from gravcal.clients.client import Client, ClientError

    def refuse(self, address):  # what a non-member gets from a 0660 socket (root, running the tests, never does)
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    with pytest.raises(ClientError, match="permission denied .*group"):
        Client(str(tmp_path / "g.sock"))


def test_gravcal_watch_reconnect_follows_a_daemon_restart(tmp_path):
    import subprocess
    import sys
    import time

    from test_server import publish, wait_until

    path = str(tmp_path / "g.sock")
    first = SocketServer(path, config=ServerConfig())
    first.start()
    p = subprocess.Popen([sys.executable, "-m", "gravcal.cli.main", "watch", "--socket", path, "--json",
                          "--rate", "0", "--reconnect", "--timeout", "5", "--count", "200"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    second = None
    try:
        assert wait_until(lambda: first._watchers, timeout=30)
        publish(first, 100, seq0=0)
        time.sleep(0.5)
        first.stop()  # the daemon stops: the socket goes away
        time.sleep(1.5)  # the watch finds nothing there for a while
        second = SocketServer(path, config=ServerConfig())
        second.start()
        assert wait_until(lambda: second._watchers, timeout=30)
        publish(second, 100, seq0=0)  # a restarted daemon's stream starts again
        out, err = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
        if second is not None:
            second.stop()
    seqs = [m["seq"] for m in map(json.loads, out.splitlines()) if m["class"] == "IMU"]
    assert p.returncode == 0, err
    assert seqs == list(range(100)) * 2, seqs[:5]
    assert "connecting again" in err and "connected again" in err and "Traceback" not in err, err


def test_gravcal_watch_without_reconnect_ends_with_one_line(tmp_path):
    import subprocess
    import sys

    p = subprocess.run([sys.executable, "-m", "gravcal.cli.main", "watch", "--socket", str(tmp_path / "none.sock")],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 1 and p.stderr.count("\n") == 1 and "no such socket" in p.stderr, p.stderr


def _documented_fields(after: str, tables: int) -> list[str]:
    """Field names of the first ``tables`` tables after the heading ``after`` in docs/socket-protocol.md."""
    import re
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[2] / "docs" / "socket-protocol.md").read_text()
    rest, names, seen = doc[doc.index(after):].splitlines(), [], 0
    in_table = False
    for line in rest[1:]:
        row = re.match(r"\| `(\w+)` \|", line)
        if row:
            names.append(row.group(1))
        if line.startswith("|") != in_table:
            in_table = not in_table
            seen += not in_table
            if seen == tables:
                break
    return names


def test_imu_lines_carry_exactly_the_documented_fields_and_types():
    import numpy as np

    from gravcal.core.samples import empty
    from gravcal.daemon.protocol import encode_imu

    s = empty(2)
    s["seq"], s["t1"], s["t2"], s["temp"], s["vsupply"] = [5, 6], 10000, 20000, 24.5, 3.3
    acc, gyro, static = np.full((2, 3), 1.5), np.array([0.1, np.nan]), np.array([True, False])
    plain = [json.loads(x) for x in encode_imu(s, acc, gyro, static)]
    raw = [json.loads(x) for x in encode_imu(s, acc, gyro, static, raw=True)]
    documented = _documented_fields("### IMU", 2)
    assert len(documented) == 13, documented
    assert set(raw[0]) - {"class"} == set(documented)
    assert set(plain[0]) - {"class"} == set(documented[:7])
    m = raw[0]
    assert isinstance(m["seq"], int) and isinstance(m["t"], float) and isinstance(m["static"], bool)
    assert len(m["acc"]) == 3 and len(m["duty"]) == 4 and len(m["t1"]) == 4 and len(m["t2"]) == 2
    assert all(isinstance(m[k], int) for k in ("gyro_counts", "tick", "flags"))
    assert m["gyro"] == 0.1 and raw[1]["gyro"] is None  # rad/s, null while uncalibrated


def test_gravcal_watch_prints_device_notices():
    from gravcal.cli.cmd_watch import _print_stream

    class Stream:
        def watch(self, rate, raw):
            yield {"class": "DEVICE", "path": "serial:///dev/ttyUSB0", "connected": False}
            yield {"class": "DEVICE", "path": "serial:///dev/ttyUSB0", "connected": True}

    import argparse
    import io

    out = io.StringIO()
    args = argparse.Namespace(rate=0, raw=False, json=False, count=0)
    assert _print_stream(Stream(), args, out, [0]) == 0
    assert out.getvalue().splitlines() == ["DEVICE serial:///dev/ttyUSB0 gone (no samples until back)",
                                           "DEVICE serial:///dev/ttyUSB0 connected"]
