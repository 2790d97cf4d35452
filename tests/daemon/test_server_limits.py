"""Per-client limits of the socket server: request budget, cached STATUS, byte-bounded queues,
idle and hung-up clients, decimation under jittering time."""
import collections
import logging
import math
import socket
import time

import numpy as np
import pytest

from gravcal.daemon.client_limits import RequestBudget
from gravcal.daemon.output_queue import OutputQueue
from gravcal.daemon.protocol import decimation_mask
from gravcal.daemon.server import ServerConfig, SocketServer

from test_server import Raw, block, publish, wait_until


@pytest.fixture
def sockpath(tmp_path):
    return str(tmp_path / "gravcal.sock")


def start(sockpath, **kw):
    calls = []

    def provider():
        calls.append(time.monotonic())
        return {"device": {"ok": 1}}

    srv = SocketServer(sockpath, config=ServerConfig(**kw), status_provider=provider).start()
    return srv, calls


def test_request_budget_grants_burst_then_rate():
    b = RequestBudget(rate=10.0, burst=5, now=0.0)
    assert b.take(8, 0.0) == 5  # the burst
    assert b.take(1, 0.05) == 0  # half a token
    assert b.wait_for_one(0.05) == pytest.approx(0.05)
    granted = sum(b.take(1, 0.1 + k * 0.01) for k in range(100))  # one second of asking every 10 ms
    assert granted == pytest.approx(10, abs=1)


def test_output_queue_bounded_in_bytes_drops_oldest_and_counts():
    q = OutputQueue(limit=10**6, max_bytes=1000)
    lines = [b"%04d" % i + b"x" * 95 + b"\n" for i in range(100)]  # 100 bytes each
    lost = 0
    for k in range(0, 100, 7):
        lost += q.put(lines[k:k + 7])
        assert q.nbytes <= 1000
    assert lost + len(q) == 100 and len(q) == 10
    data = b"".join(q.take(1 << 20)[0])
    assert data == b"".join(lines[90:]) and q.nbytes == 0 and len(q) == 0


def test_flooding_client_gets_error_then_is_disconnected_and_logged(sockpath, caplog):
    caplog.set_level(logging.INFO, "gravcal.server")
    srv, calls = start(sockpath, request_rate_hz=20.0, request_burst=10, flood_timeout_s=1.0)
    try:
        good = Raw(sockpath)
        good.line()
        flood = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        flood.connect(sockpath)
        flood.setblocking(False)
        sent, t0 = 0, time.monotonic()
        errors = []
        buf = b""
        next_poll = t0
        while time.monotonic() - t0 < 4.0:
            try:
                sent += flood.send(b"?STATUS;\n" * 200)
            except BlockingIOError:
                time.sleep(0.01)
            except OSError:
                break  # disconnected
            try:
                buf += flood.recv(1 << 20)
            except BlockingIOError:
                pass
            except OSError:
                break
            if time.monotonic() - t0 > 0.5 and len(errors) == 0:
                errors = [line for line in buf.split(b"\n") if b"too many requests" in line]
            if time.monotonic() >= next_poll:  # 10 requests/s, within its budget
                next_poll += 0.1
                good.send(b"?POLL;\n")
                assert good.line()["class"] == "POLL"  # the well-behaved client keeps being answered
        assert errors, "the flooder was never told"
        assert wait_until(lambda: srv.clients_flooding == 1, 5.0)
        assert srv.requests_refused > 0
        # refused requests never reached the status provider: at most one call per cache period
        span = calls[-1] - calls[0] if len(calls) > 1 else 0.0
        assert len(calls) <= span / srv.config.status_cache_s + 2
        assert any("flooding requests" in r.getMessage() for r in caplog.records)
        good.close()
        flood.close()
    finally:
        srv.stop()


def test_idle_non_watchers_time_out_watchers_stay(sockpath, caplog):
    caplog.set_level(logging.INFO, "gravcal.server")
    srv, _ = start(sockpath, idle_timeout_s=0.5)
    try:
        idle = Raw(sockpath)
        idle.line()
        watcher = Raw(sockpath)
        watcher.line()
        watcher.send(b'?WATCH={"enable":true};\n')
        watcher.line()
        assert wait_until(lambda: srv.clients_idle == 1, 5.0)
        with pytest.raises(EOFError):
            idle.line()
        time.sleep(0.6)
        assert srv.n_clients == 1  # the watcher, silent but watching, is kept
        assert any("idle" in r.getMessage() for r in caplog.records)
        watcher.close()
        idle.close()
    finally:
        srv.stop()


def test_watchers_that_leave_while_no_data_flows_free_their_slots(sockpath):
    srv, _ = start(sockpath, max_clients=8)
    try:
        for _ in range(3):  # 24 watchers come and go with the bus silent: no send reveals them
            socks = []
            for _ in range(8):
                r = Raw(sockpath)
                assert r.line()["class"] == "VERSION"
                r.send(b'?WATCH={"enable":true};\n')
                r.line()
                socks.append(r)
            for r in socks:
                r.close()
            assert wait_until(lambda: srv.n_clients == 0, 5.0), srv.stats()
        assert srv.clients_hung_up == 24 and srv.clients_rejected == 0
    finally:
        srv.stop()


def test_half_closed_watcher_is_kept_and_served(sockpath):
    srv, _ = start(sockpath)
    try:
        r = Raw(sockpath)
        r.line()
        r.send(b'?WATCH={"enable":true};\n')
        r.sock.shutdown(socket.SHUT_WR)
        r.line()
        time.sleep(0.6)
        publish(srv, 10)
        assert r.line()["class"] == "IMU" and srv.n_clients == 1
        r.close()
    finally:
        srv.stop()


def test_full_table_makes_room_from_the_longest_idle_non_watcher(sockpath, monkeypatch):
    monkeypatch.setattr("gravcal.daemon.server.ROOM_IDLE_S", 0.2)
    srv, _ = start(sockpath, max_clients=3)
    try:
        first = [Raw(sockpath) for _ in range(3)]
        for r in first:
            r.line()
        time.sleep(0.3)
        first[1].send(b"?VERSION;\n")
        first[1].line()
        late = Raw(sockpath)
        assert late.line()["class"] == "VERSION"
        with pytest.raises(EOFError):
            first[0].line()  # the longest idle went
        assert srv.clients_idle == 1 and srv.clients_rejected == 0
        for r in first + [late]:
            r.close()
    finally:
        srv.stop()


def test_slow_reader_queue_stays_within_its_byte_bound(sockpath):
    srv, _ = start(sockpath, queue_bytes=20_000, queue_messages=10**6, stall_timeout_s=60.0)
    try:
        slow = Raw(sockpath)
        slow.line()
        slow.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        slow.send(b'?WATCH={"enable":true,"raw":true};\n')
        assert slow.line()["class"] == "WATCH"  # watching before the burst starts
        publish(srv, 20_000, chunk=200)
        assert wait_until(lambda: srv.backlog == 0)
        per = srv.stats()["per_client"][0]
        assert 0 < per["queued_bytes"] <= 20_000 and per["dropped"] > 0
        slow.close()
    finally:
        srv.stop()


@pytest.mark.parametrize("seed", range(5))
def test_decimation_holds_its_rate_when_time_jitters_backwards(seed):
    rng = np.random.default_rng(seed)
    fs, rate, seconds = 200.0, 1.0, 20.0
    t = np.arange(int(fs * seconds)) / fs
    t = t + np.where(rng.random(t.size) < 0.05, -rng.uniform(0, 0.25, t.size), 0.0)  # steps back up to 250 ms
    last, sent = -np.inf, 0
    for k in range(0, t.size, 16):
        mask, last = decimation_mask(t[k:k + 16], rate, last)
        sent += int(mask.sum())
    assert sent <= math.ceil(seconds * rate) + 1
    assert sent >= seconds * rate - 1
    # a restart (time back to 0) is followed, not silenced
    mask, _ = decimation_mask(np.arange(0, 3, 1 / fs), rate, last)
    assert mask.sum() == 3


def test_output_queue_bound_holds_for_runs_and_by_messages():
    # runs queued with their joined bytes: whole messages, oldest first, within both bounds (messages bind here)
    q = OutputQueue(limit=15, max_bytes=2000)
    lines = [b"%04d" % i + b"x" * (i % 13) + b"\n" for i in range(100)]
    lost = 0
    for k in range(0, 100, 7):
        run = lines[k:k + 7]
        lost += q.put(run, b"".join(run))
        assert q.nbytes == len(q.buf) <= 2000 and len(q) <= 15 and q.buf.count(b"\n") == len(q)
    data = b"".join(q.take(1 << 20)[0])
    assert data == b"".join(lines[lost:]) and lost == 85 and q.nbytes == 0 and len(q) == 0


@pytest.mark.parametrize("seed", range(5))
def test_output_queue_keeps_the_newest_lines_within_both_bounds(seed):
    # against a reference: a deque of lines, the oldest dropped while either bound is exceeded
    rng = np.random.default_rng(seed)
    limit, max_bytes = int(rng.integers(5, 60)), int(rng.integers(200, 3000))
    q, ref, lost = OutputQueue(limit=limit, max_bytes=max_bytes), collections.deque(), 0
    for k in range(300):
        run = [b"%d" % k + b"z" * int(rng.integers(0, 120)) + b"\n" for _ in range(int(rng.integers(1, 9)))]
        lost += q.put(run, b"".join(run) if k % 2 else None)
        ref.extend(run)
        while len(ref) > limit or sum(map(len, ref)) > max_bytes:
            ref.popleft()
        assert bytes(q.buf) == b"".join(ref) and len(q) == len(ref) and q.nbytes == sum(map(len, ref))
        if k % 50 == 49:  # a reader takes some
            taken, n = q.take(int(rng.integers(50, 500)))
            for line in b"".join(taken).splitlines(keepends=True):
                assert ref.popleft() == line
            assert n == len(b"".join(taken).splitlines())
    assert lost > 0


def test_output_queue_take_cuts_at_whole_lines():
    q = OutputQueue(limit=10**6, max_bytes=10**6)
    lines = [b"%04d" % i + b"y" * (i % 17) + b"\n" for i in range(200)]
    q.put(lines)
    got, n = [], 0
    while len(q):
        chunk, k = q.take(100)
        assert len(chunk) == 1 and chunk[0].endswith(b"\n") and chunk[0].count(b"\n") == k
        assert len(chunk[0]) <= 100 or k == 1
        got.append(chunk[0])
        n += k
    assert b"".join(got) == b"".join(lines) and n == 200 and q.nbytes == 0
