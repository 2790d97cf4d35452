"""The socket server over real Unix sockets in temporary directories."""
import json
import os
import socket
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest

from gravcal.core.samples import empty
from gravcal.clients.client import Client, ServerError
from gravcal.daemon.server import ServerConfig, SocketServer
from gravcal.daemon.socket_activation import SocketPathError, activated_socket, bind_unix_socket, listen_fds


def block(n, seq0=0, fs=200.0):
    s = empty(n)
    s["seq"] = seq0 + np.arange(n)
    s["t"] = s["seq"] / fs
    s["t1"] = 10000
    s["t2"] = 20000
    acc = np.tile([0.0, 0.0, 9.80665], (n, 1))
    return s, acc, np.zeros(n), np.ones(n, dtype=bool)


def publish(server, n, seq0=0, chunk=100, pause=0.0):
    for start in range(seq0, seq0 + n, chunk):
        server.publish(*block(min(chunk, seq0 + n - start), start))
        if pause:
            time.sleep(pause)


def wait_until(cond, timeout=10.0, step=0.02):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(step)
    return cond()


class Raw:
    """A bare line client for abuse tests."""

    def __init__(self, path):
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.settimeout(10)
        self.sock.connect(path)
        self.buf = b""

    def send(self, data: bytes):
        self.sock.sendall(data)

    def line(self):
        while b"\n" not in self.buf:
            d = self.sock.recv(65536)
            if not d:
                raise EOFError
            self.buf += d
        line, self.buf = self.buf.split(b"\n", 1)
        return json.loads(line)

    def close(self):
        self.sock.close()


@pytest.fixture
def sockpath(tmp_path):
    return str(tmp_path / "gravcal.sock")


@pytest.fixture
def server(sockpath):
    srv = SocketServer(sockpath, config=ServerConfig(stall_timeout_s=30.0), status_provider=lambda: {"device": {"crc_errors": 7}})
    srv.start()
    yield srv
    srv.stop()


def test_greeting_and_every_command(server, sockpath):
    with Client(sockpath) as c:
        assert c.version["class"] == "VERSION"
        assert (c.version["proto_major"], c.version["proto_minor"]) == (1, 1)
        assert c.version["release"]
        assert c.poll()["imu"] == []  # nothing published yet
        calib = c.calib()
        assert calib["accepted"] is False and calib["revision"] == 0
        server.set_calibration({"revision": 4, "accepted": True, "offset": [0.5, 0.5, 0.5]})
        publish(server, 10)
        assert wait_until(lambda: server.published_samples == 10)
        poll = c.poll()
        assert [m["seq"] for m in poll["imu"]] == [9]
        assert poll["imu"][0]["acc"] == pytest.approx([0, 0, 9.80665])
        assert c.calib()["revision"] == 4
        st = c.status()
        assert st["device"]["crc_errors"] == 7
        assert st["server"]["clients"] == 1 and st["server"]["published_samples"] == 10
        assert c.request("?VERSION;", "VERSION")["proto_major"] == 1


def test_watch_streams_all_samples_in_order_and_pushes_calib(server, sockpath):
    with Client(sockpath) as c:
        w = c.set_watch(enable=True)
        assert w == {"class": "WATCH", "enable": True, "raw": False, "rate": 0.0}
        publish(server, 300)
        server.set_calibration({"revision": 1, "accepted": True})
        publish(server, 200, seq0=300)
        seqs, calib_at = [], None
        while len(seqs) < 500:
            m = c.read_message()
            if m["class"] == "IMU":
                seqs.append(m["seq"])
            elif m["class"] == "CALIB":
                calib_at = len(seqs)
        assert seqs == list(range(500))
        assert calib_at == 300  # pushed in order with the samples
        # disable: samples stop, replies continue
        assert c.set_watch(enable=False)["enable"] is False
        publish(server, 50, seq0=500)
        assert wait_until(lambda: server.published_samples == 550)
        assert c.poll()["imu"][0]["seq"] == 549
        assert not [m for m in c._pending if m["class"] == "IMU" and m["seq"] >= 500]


def test_watch_rate_and_raw(server, sockpath):
    with Client(sockpath) as c:
        c.set_watch(enable=True, rate=20, raw=True)
        publish(server, 400)  # 2 s of samples at 200 Hz
        got = []
        while not got or got[-1]["seq"] < 390:
            m = c.read_message()
            if m["class"] == "IMU":
                got.append(m)
        assert 38 <= len(got) <= 40  # 20 per second of sample time
        assert np.diff([m["t"] for m in got]).min() >= 0.05 - 1e-9
        assert got[0]["duty"] == pytest.approx([0.5] * 4) and got[0]["t1"] == [10000] * 4


def test_new_watcher_gets_current_calibration_first(server, sockpath):
    server.set_calibration({"revision": 9, "accepted": True})
    assert wait_until(lambda: server._calib is not None)
    with Client(sockpath) as c:
        c.set_watch()
        assert c.read_message()["revision"] == 9


def test_bad_requests_get_error_and_connection_survives(server, sockpath):
    r = Raw(sockpath)
    assert r.line()["class"] == "VERSION"
    for bad, expect in [(b"?WATCH={\"enable\":true,\"colour\":1};\n", "unknown field 'colour'"),
                        (b"hello\n", "requests start with '?'"),
                        (b"?SKY;\n", "unknown command"),
                        (b"?WATCH={\"rate\":-5};\n", "'rate' must be a number"),
                        (b"?WATCH={bad json};\n", "not valid JSON")]:
        r.send(bad)
        m = r.line()
        assert m["class"] == "ERROR" and expect in m["message"], m
    r.send(b"?POLL;\n")
    assert r.line()["class"] == "POLL"  # still served
    # a bad command after a good one on the same line: good one answered, then the error
    r.send(b"?VERSION;?BOGUS;\n")
    assert r.line()["class"] == "VERSION" and r.line()["class"] == "ERROR"
    with Client(sockpath) as c, pytest.raises(ServerError, match="unknown field 'speed'"):
        c.request('?WATCH={"speed":1};', "WATCH")
    r.close()


def test_oversized_request_error_resync_then_disconnect_after_repeats(sockpath):
    srv = SocketServer(sockpath, config=ServerConfig(max_request_bytes=256, max_oversize=3)).start()
    try:
        r = Raw(sockpath)
        r.line()
        r.send(b"?" + b"A" * 5000)  # no newline yet: error as soon as the bound is passed
        m = r.line()
        assert m["class"] == "ERROR" and "longer than 256 bytes" in m["message"]
        r.send(b"B" * 3000 + b"\n?POLL;\n")  # rest of the long line is skipped, then resync
        assert r.line()["class"] == "POLL"
        r.send(b"?" + b"C" * 400 + b"\n")  # second oversized (complete line)
        assert r.line()["class"] == "ERROR"
        r.send(b"?STATUS;\n")
        assert r.line()["class"] == "STATUS"
        r.send(b"?" + b"D" * 400 + b"\n")  # third: error, then hang up
        assert r.line()["class"] == "ERROR"
        with pytest.raises(EOFError):
            r.line()
        assert wait_until(lambda: srv.n_clients == 0)
    finally:
        srv.stop()


def test_half_closed_client_gets_its_answer(server, sockpath):
    # `echo '?STATUS;' | nc -U sock` style: commands then EOF on the write side.
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(10)
    s.connect(sockpath)
    s.sendall(b"?STATUS;\n")
    s.shutdown(socket.SHUT_WR)
    data = b""
    while True:
        d = s.recv(65536)
        if not d:
            break
        data += d
    s.close()
    classes = [json.loads(x)["class"] for x in data.splitlines()]
    assert classes == ["VERSION", "STATUS"]


def test_forty_clients_at_once_each_get_every_sample(server, sockpath):
    n_clients, n = 40, 600
    clients = [Client(sockpath) for _ in range(n_clients)]
    try:
        for c in clients:
            c.set_watch(enable=True)
        assert server.stats()["clients"] == n_clients
        results = [None] * n_clients

        def reader(i):
            seqs = []
            while len(seqs) < n:
                m = clients[i].read_message()
                if m["class"] == "IMU":
                    seqs.append(m["seq"])
            results[i] = seqs

        threads = [threading.Thread(target=reader, args=(i,)) for i in range(n_clients)]
        for t in threads:
            t.start()
        publish(server, n, chunk=50, pause=0.002)
        for t in threads:
            t.join(30)
        assert all(r == list(range(n)) for r in results)
        st = clients[0].status()["server"]
        assert st["clients"] == n_clients and st["dropped_messages"] == 0
    finally:
        for c in clients:
            c.close()


def test_too_many_clients_are_refused_with_error(sockpath):
    srv = SocketServer(sockpath, config=ServerConfig(max_clients=2)).start()
    try:
        a, b = Client(sockpath), Client(sockpath)
        r = Raw(sockpath)
        m = r.line()
        assert m["class"] == "ERROR" and "too many clients (limit 2)" in m["message"]
        with pytest.raises(EOFError):
            r.line()
        assert srv.stats()["clients_rejected"] == 1
        a.close(), b.close()
    finally:
        srv.stop()


def _count_lines(sock, stop, counter):
    buf = b""
    while not stop.is_set():
        try:
            d = sock.recv(1 << 20)
        except socket.timeout:
            continue
        if not d:
            break
        buf += d
        *lines, buf = buf.split(b"\n")
        for line in lines:
            counter.append(line)


def test_slow_client_loses_oldest_messages_counted_and_fast_client_loses_none(sockpath):
    # Queue of 500 messages; the slow client reads nothing while 12000 samples go out, the
    # fast one reads continuously. Exact accounting: slow received + reported drops = 12000.
    n = 12000
    srv = SocketServer(sockpath, config=ServerConfig(queue_messages=500, stall_timeout_s=60.0,
                                                     send_chunk_bytes=16384)).start()
    try:
        fast = Raw(sockpath)
        slow = Raw(sockpath)
        for r in (fast, slow):
            r.line()
            r.send(b'?WATCH={"enable":true};\n')
            assert r.line()["class"] == "WATCH"
        fast.sock.settimeout(0.2)
        stop, fast_lines = threading.Event(), []
        t = threading.Thread(target=_count_lines, args=(fast.sock, stop, fast_lines))
        t.start()
        publish(srv, n, chunk=100, pause=0.01)  # ~10k samples/s for 1.2 s
        assert wait_until(lambda: len(fast_lines) >= n, timeout=30)
        stop.set()
        t.join()
        fast_msgs = [json.loads(x) for x in fast_lines]
        assert [m["seq"] for m in fast_msgs if m["class"] == "IMU"] == list(range(n))
        assert not [m for m in fast_msgs if m["class"] == "DROPPED"]

        # now the slow one reads everything that is left for it
        slow.sock.settimeout(2.0)
        seqs, drops = [], []
        while not seqs or seqs[-1] != n - 1:
            m = slow.line()
            if m["class"] == "IMU":
                seqs.append(m["seq"])
            elif m["class"] == "DROPPED":
                drops.append(m)
        assert drops, "the slow client was told about its losses"
        assert len(seqs) + sum(d["count"] for d in drops) == n
        assert drops[-1]["total"] == sum(d["count"] for d in drops)
        assert seqs == sorted(seqs) and seqs[-1] == n - 1  # the newest kept, the oldest lost
        assert len(seqs) < n / 2
        per_client = {c["id"]: c for c in srv.stats()["per_client"]}
        assert per_client[2]["dropped"] == sum(d["count"] for d in drops)
        assert per_client[1]["dropped"] == 0
        fast.close(), slow.close()
    finally:
        srv.stop()


def test_stalled_client_is_disconnected_and_others_keep_flowing(sockpath):
    srv = SocketServer(sockpath, config=ServerConfig(queue_messages=200, stall_timeout_s=0.8)).start()
    try:
        stalled = Raw(sockpath)
        stalled.line()
        stalled.send(b'?WATCH={"enable":true};\n')
        assert stalled.line()["class"] == "WATCH"
        live = Raw(sockpath)
        live.line()
        live.send(b'?WATCH={"enable":true};\n')
        assert live.line()["class"] == "WATCH"
        live.sock.settimeout(0.2)
        stop, lines = threading.Event(), []
        reader = threading.Thread(target=_count_lines, args=(live.sock, stop, lines))
        reader.start()
        seq, deadline = 0, time.monotonic() + 30
        # ~10k samples/s until the never-reading client has filled its socket buffer and
        # made no progress for 0.8 s
        while srv.stats()["clients_stalled"] == 0 and time.monotonic() < deadline:
            publish(srv, 100, seq0=seq)
            seq += 100
            time.sleep(0.01)
        assert srv.stats()["clients_stalled"] == 1
        assert wait_until(lambda: len(lines) >= seq)
        stop.set()
        reader.join()
        msgs = [json.loads(x) for x in lines]
        assert [m["seq"] for m in msgs if m["class"] == "IMU"] == list(range(seq))  # the live one lost nothing
        assert srv.n_clients == 1
        stalled.sock.settimeout(5)
        with pytest.raises((EOFError, ConnectionResetError)):
            while True:
                stalled.line()
        live.close()
    finally:
        srv.stop()


# -- socket path handling -----------------------------------------------------------------


def test_live_socket_path_is_refused(server, sockpath):
    with pytest.raises(SocketPathError, match=f"another gravcald is running on {sockpath}"):
        bind_unix_socket(sockpath)


def test_stale_socket_is_replaced(sockpath):
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(sockpath)
    s.close()  # path stays, nobody listens: what a crash leaves behind
    assert os.path.exists(sockpath)
    srv = SocketServer(sockpath).start()
    try:
        with Client(sockpath) as c:
            assert c.version["class"] == "VERSION"
    finally:
        srv.stop()
    assert not os.path.exists(sockpath)  # we bound it, we remove it


def test_non_socket_path_is_never_removed(tmp_path):
    p = tmp_path / "important.txt"
    p.write_text("data")
    with pytest.raises(SocketPathError, match="exists and is not a socket"):
        bind_unix_socket(str(p))
    assert p.read_text() == "data"
    with pytest.raises(SocketPathError, match="does not exist"):
        bind_unix_socket(str(tmp_path / "nodir" / "s.sock"))


def test_socket_mode_applied(sockpath):
    srv = SocketServer(sockpath, socket_mode=0o600)
    try:
        assert os.stat(sockpath).st_mode & 0o777 == 0o600
    finally:
        srv.stop()


def test_listen_fds_ignores_other_pids_and_malformed(tmp_path):
    env = {"LISTEN_PID": str(os.getpid() + 1), "LISTEN_FDS": "1", "LISTEN_FDNAMES": "gravcal"}
    assert listen_fds(environ=env) == {}
    assert "LISTEN_FDS" not in env  # unset either way
    assert listen_fds(environ={"LISTEN_PID": "x", "LISTEN_FDS": "1"}) == {}
    assert activated_socket(environ={}) is None


ACTIVATED_CHILD = textwrap.dedent(
    """
    import os, sys, time, numpy as np
    from gravcal.daemon.server import SocketServer
    from gravcal.daemon.socket_activation import activated_socket
    from gravcal.core.samples import empty
    sock = activated_socket("gravcal")
    print("env", os.environ.get("LISTEN_FDS"), os.environ.get("LISTEN_PID"), flush=True)
    srv = SocketServer(sock=sock).start()
    s = empty(3); s["seq"] = [7, 8, 9]
    srv.publish(s, np.zeros((3, 3)), np.zeros(3), np.zeros(3, bool))
    print("ready", flush=True)
    sys.stdin.read()
    srv.stop()
    """
)


def test_socket_activation_with_named_fd_in_subprocess(sockpath):
    # What systemd does: bind+listen, put the fd at 3, set LISTEN_FDS/LISTEN_FDNAMES and
    # LISTEN_PID = the child's own pid (sh's $$ survives exec).
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(sockpath)
    listener.listen(8)
    fd = listener.fileno()
    env = dict(os.environ, LISTEN_FDS="1", LISTEN_FDNAMES="gravcal")
    proc = subprocess.Popen(
        ["sh", "-c", 'LISTEN_PID=$$ exec "$0" -c "$1"', sys.executable, ACTIVATED_CHILD],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env,
        close_fds=False, preexec_fn=lambda: os.dup2(fd, 3),
    )
    try:
        assert proc.stdout.readline().split() == ["env", "None", "None"]  # consumed and unset
        assert proc.stdout.readline().strip() == "ready"
        listener.close()  # only the child holds it now
        with Client(sockpath) as c:
            assert c.version["class"] == "VERSION"
            assert wait_until(lambda: c.poll()["imu"] != [])
            assert c.poll()["imu"][0]["seq"] == 9
    finally:
        proc.stdin.close()
        proc.wait(20)
    assert proc.returncode == 0
    assert os.path.exists(sockpath)  # systemd's socket: the daemon must not unlink it


def test_activation_with_wrong_name_is_a_clear_error(sockpath):
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(sockpath)
    listener.listen(1)
    fd = listener.fileno()
    code = "from gravcal.daemon.socket_activation import activated_socket\ntry:\n activated_socket('gravcal')\nexcept OSError as e:\n print(e)"
    env = dict(os.environ, LISTEN_FDS="1", LISTEN_FDNAMES="other")
    out = subprocess.run(["sh", "-c", 'LISTEN_PID=$$ exec "$0" -c "$1"', sys.executable, code], env=env,
                         close_fds=False, preexec_fn=lambda: os.dup2(fd, 3),
                         capture_output=True, text=True, timeout=30)
    listener.close()
    assert "none named 'gravcal'" in out.stdout and "FileDescriptorName=gravcal" in out.stdout
