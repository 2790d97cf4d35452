"""The C step's wake-ups without the GIL (daemon/_fastpath.c): the same lines, records and counters as with it,
the watcher table kept equal to the server's watchers, each client's lock respected, and every record staged
once and in order under load."""
from __future__ import annotations

import json
import os
import socket
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from gravcal.core.samples import SAMPLE_DTYPE
from gravcal.daemon import fastpath as fp
from gravcal.daemon._fastpath import ClientRecord, step
from gravcal.daemon.fanout import fast_snapshot, finish_delivery
from gravcal.daemon.processing import engine_params
from gravcal.daemon.protocol import STANDARD_GRAVITY, ImuBlock
from gravcal.daemon.server import ServerConfig, SocketServer

from support.correction_reference import extended_model, plain_block
from support.line_reference import imu_lines
from test_fastpath_step import FS, PLAIN, Rig, frames
from test_fastpath import EXTENDED
from test_server import block, wait_until


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def _feed(rig: Rig, seqs, pause_s: float, between=None) -> threading.Thread:
    """Write each frame on its own (a wake-up each), ``between(i)`` after frame i."""
    def run():
        for i, s in enumerate(seqs):
            os.write(rig.w, frames([s]))
            time.sleep(pause_s)
            if between is not None:
                between(i)
    t = threading.Thread(target=run)
    t.start()
    return t


def _expected_lines(rig: Rig) -> bytes:
    rows = np.frombuffer(bytes(rig.staged), SAMPLE_DTYPE)
    acc = rig.processor.acc(rows)
    gyro = (rows["gyro"].astype(float) - 2048.0) / 357.36
    static = np.where(rows["seq"] - 900 <= 400.0, 1, -1).astype(np.int8)
    return imu_lines(rows, acc, gyro, static, raw=True)


def test_wake_ups_take_no_gil_and_send_the_python_paths_bytes(rig):
    n = 12
    rig.ist[fp.IST_STAGE_LIMIT] = n * SAMPLE_DTYPE.itemsize  # returns once all are staged
    t = _feed(rig, range(5, 5 + n), 0.004)
    leftover, stopped = rig.step(5, 100, seconds=5.0)
    t.join()
    assert (leftover, stopped) == (b"", None) and rig.ist[fp.IST_REASON] == fp.R_DUE
    assert np.frombuffer(bytes(rig.staged), SAMPLE_DTYPE)["seq"].tolist() == list(range(100, 100 + n))
    # the parameters are read as the call starts (with the GIL): every wake-up is served without it
    batches = rig.ist[fp.IST_NOGIL]
    assert n // 2 <= batches <= n and rig.ist[fp.IST_FRAMES] == n
    assert rig.received() == _expected_lines(rig)
    rig.client.fold()
    assert rig.client.sent_messages == n and rig.client.sent_bytes == len(_expected_lines(rig))


def test_a_busy_client_lock_is_waited_for_and_handed_to_fanout(rig):
    """A wake-up that finds the client's lock held (the server thread at that client) sends nothing to it: it
    takes the lock when free and returns the delivery to fanout, which sends the line after what the holder did."""
    c = rig.client
    holding, release = threading.Event(), threading.Event()

    def holder():
        with c.lock:
            c.sock.send(b'{"class":"REPLY"}\n')  # the server thread's own send, under the lock
            holding.set()
            release.wait(5)

    def between(i):
        if i == 0:
            threading.Thread(target=holder).start()
            holding.wait(5)
            threading.Timer(0.1, release.set).start()

    t = _feed(rig, [5, 6], 0.02, between)
    leftover, stopped = rig.step(5, 100, seconds=5.0)
    t.join()
    assert leftover == b"" and stopped is not None and stopped[0][0] is c
    assert rig.ist[fp.IST_REASON] == fp.R_DELIVERY and rig.ist[fp.IST_SENT] == -1 and rig.ist[fp.IST_FRAMES] == 2
    assert release.is_set()  # it waited for the holder
    got = []
    other = threading.Thread(target=lambda: got.append(c.lock.acquire(timeout=0.1)))
    other.start()
    other.join()
    assert got == [False]  # the step handed the lock over held
    k = int(rig.ist[fp.IST_BATCH])
    finish_delivery(ImuBlock(rig.rows[:k].copy(), rig.acc[:k].copy(), rig.gyro[:k].copy(), rig.codes[:k].copy()),
                    stopped, 0, -1, time.monotonic())
    lines = rig.received().splitlines()
    assert [json.loads(x).get("seq") for x in lines] == [100, None, 101]  # its line after the holder's reply


def test_pending_output_closes_the_gate_between_wake_ups(rig):
    c = rig.client

    def between(i):
        if i == 0:
            with c.lock:
                c.queue.put([b"queued\n"])  # something queued goes first: the step may not send

    t = _feed(rig, [5, 6], 0.02, between)
    leftover, stopped = rig.step(5, 100, seconds=5.0)
    t.join()
    assert stopped is not None and rig.ist[fp.IST_SENT] == -1 and rig.ist[fp.IST_FRAMES] == 2
    assert rig.received().count(b"\n") == 1  # frame 5 only
    c.lock.release()


def test_record_lock_is_reentrant_owned_and_times_out():
    r = ClientRecord()
    assert r.lock() and r.lock(timeout=0.01)  # the holder takes it again
    r.unlock()
    got = []
    t = threading.Thread(target=lambda: got.extend([r.lock(timeout=0.05), r.lock(blocking=False)]))
    t.start()
    t.join()
    assert got == [False, False]
    with pytest.raises(RuntimeError, match="not held"):
        _unlock_elsewhere(r)
    r.unlock()
    assert r.lock(blocking=False)
    r.unlock()


def _unlock_elsewhere(r: ClientRecord) -> None:
    err = []

    def run():
        try:
            r.unlock()
        except RuntimeError as exc:
            err.append(exc)
    t = threading.Thread(target=run)
    t.start()
    t.join()
    raise err[0]


def _table_matches(srv: SocketServer) -> list:
    """The server's watchers as the C table holds them: (record, fd, raw, watch) each."""
    want = [(w.record, w.sock.fileno(), w.watch.raw, w.watch) for w in srv._watchers]
    table = srv.fast_box.table()
    assert table is not None
    assert [(e[0], e[1], e[2], e[3]) for e in table] == want
    return want


def test_the_table_follows_connect_watch_pending_output_disconnect_and_reload(tmp_path):
    srv = SocketServer(str(tmp_path / "g.sock"), config=ServerConfig(queue_messages=50)).start()
    socks = []
    try:
        for raw in (True, False, True):
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.connect(str(tmp_path / "g.sock"))
            socks.append(s)
        wait_until(lambda: len(srv._clients) == 3)
        assert srv.fast_box.table() == ()  # connected, none watching
        for s, raw in zip(socks, (True, False, True)):
            s.sendall(b'?WATCH={"enable":true,"raw":%s};\n' % (b"true" if raw else b"false"))
        wait_until(lambda: len(srv._watchers) == 3)
        assert [e[2] for e in _table_matches(srv)] == [True, False, True]
        # pending output: the client's gate closes (its record), the table keeps it
        slow = srv._watchers[1]
        with slow.lock:
            slow.queue.put([b"x\n"])
        assert slow.record.policy is None and len(_table_matches(srv)) == 3
        with slow.lock:
            slow.queue.take(1 << 20)
        assert slow.record.policy is slow.watch
        # a changed policy: a new watch object in the table, the gate on it
        socks[0].sendall(b'?WATCH={"enable":true,"raw":false};\n')
        wait_until(lambda: srv._watchers and srv._watchers[0].watch.raw is False)
        assert [e[2] for e in _table_matches(srv)] == [False, False, True]
        # a decimated watcher: the step reads box[0] (None) with the GIL
        socks[2].sendall(b'?WATCH={"enable":true,"rate":1};\n')
        wait_until(lambda: srv.fast_box.table() is None)
        assert srv.fast_watchers is None
        socks[2].sendall(b'?WATCH={"enable":false};\n')
        wait_until(lambda: len(srv._watchers) == 2)
        _table_matches(srv)
        # a disconnect: gone from the table before its socket closes
        socks[1].close()
        wait_until(lambda: len(srv._watchers) == 1)
        assert len(_table_matches(srv)) == 1
        srv.reconfigure(SimpleNamespace(queue_messages=10))  # a reload keeps the watchers
        _table_matches(srv)
        srv.publish(*block(3, 0))
        assert wait_until(lambda: socks[0].recv(1 << 16, socket.MSG_PEEK).count(b'"IMU"') >= 1)
    finally:
        for s in socks:
            s.close()
        srv.stop()


def test_every_record_is_staged_once_and_in_order_under_load(rig):
    """Frames in bursts while another thread churns the box, the client's lock and the engine's parameters
    (a plain and an extended calibration, each with its own gyro bias, swapped through Engine.set_params): every
    call adds exactly the records it counts, all in order, the client gets each line once, in order (stopped
    deliveries finished by fanout, as FastPath does), and each line is corrected wholly with one of the two
    parameter sets, never a mix."""
    total, limit, most = 3000, 64, 4096  # a read holds at most 65536 bytes: whole frames, none handed back
    rig.ist[fp.IST_STAGE_LIMIT] = limit * SAMPLE_DTYPE.itemsize
    rig.rows, rig.acc = np.zeros(most, SAMPLE_DTYPE), np.zeros((most, 3))
    rig.gyro, rig.codes = np.zeros(most), np.zeros(most, np.int8)
    rig.peer.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    done = threading.Event()
    got = bytearray()

    def reader():
        rig.peer.settimeout(0.2)
        while not done.is_set() or got.count(b"\n") < total:
            try:
                data = rig.peer.recv(1 << 16)
            except socket.timeout:
                if done.is_set():
                    break
                continue
            got.extend(data)

    def feeder():
        rng = np.random.default_rng(7)
        s = 0
        while s < total:
            k = min(int(rng.integers(1, 9)), total - s)
            os.write(rig.w, frames(range(s, s + k)))
            s += k
            time.sleep(0.0005)

    params = (engine_params(PLAIN, FS, (2048.0, 357.36), (900, True)),
              engine_params(EXTENDED, FS, (2000.0, 350.0), (900, True)))

    def churn():
        c = rig.client
        k = 0
        while not done.is_set():
            rig.server.fast_box[0] = fast_snapshot((c,))
            rig.processor.engine.set_params(params[k % 2])
            k += 1
            with c.lock:
                time.sleep(0.0002)

    threads = [threading.Thread(target=f) for f in (reader, feeder, churn)]
    for t in threads:
        t.start()
    expect, seq, calls, stopped_n, handed, nogil = 0, 0, 0, 0, [], 0
    try:
        while seq < total and calls < 10000:
            had = len(rig.staged)
            rig.ist[fp.IST_EXPECT], rig.ist[fp.IST_SEQ] = expect & 0xFFFF, seq
            leftover, stopped = step(rig.r, 0.2, most, rig.ist, rig.fst, rig.staged, rig.server.fast_box,
                                     rig.processor.engine, rig.rows, rig.acc, rig.gyro, rig.codes)
            calls += 1
            assert leftover == b""
            n, nogil = int(rig.ist[fp.IST_FRAMES]), nogil + int(rig.ist[fp.IST_NOGIL])
            assert len(rig.staged) - had == n * SAMPLE_DTYPE.itemsize
            expect, seq = int(rig.ist[fp.IST_EXPECT]), int(rig.ist[fp.IST_SEQ])
            if len(rig.staged) >= limit * SAMPLE_DTYPE.itemsize:  # handed to the analysis, as Gravcald does
                handed.append(bytes(rig.staged))
                rig.staged.clear()
            if stopped is not None:
                stopped_n += 1
                k = int(rig.ist[fp.IST_BATCH])
                finish_delivery(ImuBlock(rig.rows[:k].copy(), rig.acc[:k].copy(), rig.gyro[:k].copy(),
                                         rig.codes[:k].copy()), stopped, int(rig.ist[fp.IST_CLIENT]),
                                int(rig.ist[fp.IST_SENT]), time.monotonic())
    finally:
        done.set()
        for t in threads:
            t.join(10)
    assert all(len(h) >= limit * SAMPLE_DTYPE.itemsize for h in handed)
    rows = np.frombuffer(b"".join(handed) + bytes(rig.staged), SAMPLE_DTYPE)
    assert rows["seq"].tolist() == list(range(total))
    lines = [json.loads(x) for x in bytes(got).splitlines() if b'"IMU"' in x]
    assert [m["seq"] for m in lines] == list(range(total))
    assert stopped_n >= 1 and nogil >= 1  # both: batches without the GIL, deliveries the churn sent to fanout
    acc, gyro = np.array([m["acc"] for m in lines]), np.array([m["gyro"] for m in lines], dtype=float)
    sets = [(plain_block(rows, PLAIN.offset, PLAIN.sensitivity, STANDARD_GRAVITY),
             (rows["gyro"].astype(float) - 2048.0) / 357.36),
            (extended_model(EXTENDED, rows, FS, STANDARD_GRAVITY), (rows["gyro"].astype(float) - 2000.0) / 350.0)]
    which = [(np.abs(acc - a).max(axis=1) < 1e-4) & (np.abs(gyro - g) < 1e-5) for a, g in sets]
    assert (which[0] ^ which[1]).all()  # each line one set's, wholly: never the acc of one and the gyro of the other
    assert which[0].sum() > 0 and which[1].sum() > 0, (which[0].sum(), which[1].sum())


def test_poll_copies_the_newest_batchs_last_sample_and_refuses_bad_buffers(rig):
    from gravcal.daemon._fastpath import latest
    one = (np.zeros(1, SAMPLE_DTYPE), np.zeros((1, 3)), np.zeros(1), np.zeros(1, np.int8))
    arrays = (rig.ist, rig.rows, rig.acc, rig.gyro, rig.codes)
    assert latest(*arrays, *one) is False  # nothing published yet
    n = 3
    rig.ist[fp.IST_STAGE_LIMIT] = n * SAMPLE_DTYPE.itemsize
    t = _feed(rig, range(5, 5 + n), 0.004)
    rig.step(5, 100, seconds=5.0)
    t.join()
    assert latest(*arrays, *one) is True
    k = int(rig.ist[fp.IST_BATCH])
    assert one[0]["seq"][0] == 100 + n - 1 and one[0].tobytes() == rig.rows[k - 1:k].tobytes()
    assert one[1][0].tolist() == rig.acc[k - 1].tolist() and one[2][0] == rig.gyro[k - 1]
    assert one[3][0] == rig.codes[k - 1]
    for bad in ((np.zeros(2, SAMPLE_DTYPE),) + one[1:], (rig.ist[:3],) + arrays[1:]):
        with pytest.raises(ValueError, match="latest"):
            latest(*(bad if len(bad) == 5 else arrays), *(bad if len(bad) == 4 else one))
    rig.ist[fp.IST_BATCH] = 10 ** 6  # beyond the arrays: nothing is read
    assert latest(*arrays, *one) is False


def test_a_number_beyond_the_integer_formatting_takes_the_gil_for_its_line(rig):
    """acc ~1e300: the line kernel's integer path cannot write it, so that batch's lines are written with the
    GIL (PyOS_double_to_string), the same bytes as the Python encoder's, and the wake-ups still deliver."""
    from gravcal.core.calibration import Calibration
    rig.processor.set(Calibration("6", np.array([0.5, 0.51, 0.49]), np.diag([1e-302, 0.041, 0.039])),
                      (2048.0, 357.36), (900, True))
    n = 4
    rig.ist[fp.IST_STAGE_LIMIT] = n * SAMPLE_DTYPE.itemsize
    t = _feed(rig, range(5, 5 + n), 0.004)
    leftover, stopped = rig.step(5, 100, seconds=5.0)
    t.join()
    assert (leftover, stopped) == (b"", None) and rig.ist[fp.IST_FRAMES] == n
    assert rig.ist[fp.IST_NOGIL] == 0  # each batch took the GIL for its lines
    got = rig.received()
    assert b"e+" not in got and len(got.split(b"\n")[0]) > 300  # %f digits of a ~1e300 number
    assert got == _expected_lines(rig)
