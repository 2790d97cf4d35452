"""The C step alone (daemon/_fastpath.c): its lines against the Python encoder's, what it leaves to the
Python path, and bad arguments and arbitrary bytes (never out of bounds, never a crash)."""
from __future__ import annotations

import math
import os
import socket
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from gravcal.core.calibration import Calibration
from gravcal.core.samples import SAMPLE_DTYPE
from gravcal.daemon import fastpath as fp
from gravcal.daemon._fastpath import EP_N, Engine, WatcherBox, step
from gravcal.daemon.client_limits import ClientState
from gravcal.daemon.fanout import fast_snapshot
from gravcal.daemon.output_queue import OutputQueue
from gravcal.daemon.processing import engine_params
from gravcal.daemon.protocol import STANDARD_GRAVITY, WatchPolicy
from gravcal.drivers.codec import FrameDecoder, encode_frames
from gravcal.drivers.rigs.sources import pattern_blocks
from support.correction_reference import plain_block
from support.line_reference import imu_lines

MAX = 16
FS = 200.0
PLAIN = Calibration("6", np.array([0.5, 0.51, 0.49]), np.diag([0.04, 0.041, 0.039]))


def frames(seqs) -> bytes:
    seqs = np.asarray(seqs, dtype=np.int64)
    s = next(pattern_blocks(seed=3, fs=200, duration=seqs.shape[0] / 200, block=seqs.shape[0])).copy()
    s["seq"], s["tick"] = seqs & 0xFFFF, (seqs * 5000) & 0xFFFFFFFF
    return encode_frames(s)


class RigServer:
    """What the step reads of daemon/server.py's SocketServer: ``fast_box``, a WatcherBox whose one item is the watcher
    snapshot, and that item as ``fast_watchers``."""

    def __init__(self, snapshot):
        self.fast_box = WatcherBox(snapshot)

    fast_watchers = property(lambda self: self.fast_box[0], lambda self, value: self.fast_box.__setitem__(0, value))


class RigProcessor:
    """What the step takes of daemon/processing.py's Processor: its engine, whose parameters are set whole
    (Engine.set_params) as the processor sets them; ``cal`` the calibration they correct with."""

    def __init__(self, cal: Calibration = PLAIN, gyro=(2048.0, 357.36), analysed=(900, True)):
        self.engine = Engine()
        self.set(cal, gyro, analysed)

    def set(self, cal: Calibration, gyro, analysed) -> None:
        self.cal = cal
        self.engine.set_params(engine_params(cal, FS, gyro, analysed))

    def acc(self, rows: np.ndarray) -> np.ndarray:
        """The reference correction of a plain calibration (tests/support/correction_reference.py)."""
        return plain_block(rows, self.cal.offset, self.cal.sensitivity, STANDARD_GRAVITY)


class Rig:
    """A pipe as the bus, a socketpair as one plain watcher, a processor with a plain calibration."""

    def __init__(self, raw: bool = True):
        self.r, self.w = os.pipe()
        os.set_blocking(self.r, False)
        self.mine, self.peer = socket.socketpair()
        self.mine.setblocking(False)
        self.client = ClientState(id=1, sock=self.mine, queue=OutputQueue(100), connected=0.0,
                                  watch=WatchPolicy(True, raw, 0.0))
        self.server = RigServer(fast_snapshot((self.client,)))
        self.processor = RigProcessor()
        self.ist = np.zeros(fp.IST_N, np.int64)
        self.fst = np.zeros(fp.FST_N)
        self.ist[fp.IST_STAGE_LIMIT] = 1 << 30
        self.fst[fp.FST_TICK_HZ] = 1e6
        self.rows, self.acc = np.zeros(MAX, SAMPLE_DTYPE), np.zeros((MAX, 3))
        self.gyro, self.codes = np.zeros(MAX), np.zeros(MAX, np.int8)
        self.staged = bytearray()

    def step(self, expect: int, seq: int, seconds: float = 0.05):
        self.ist[fp.IST_EXPECT], self.ist[fp.IST_SEQ] = expect, seq
        return step(self.r, seconds, MAX, self.ist, self.fst, self.staged, self.server.fast_box,
                    self.processor.engine, self.rows, self.acc, self.gyro, self.codes)

    def received(self) -> bytes:
        self.peer.setblocking(False)
        out = b""
        while True:
            try:
                out += self.peer.recv(1 << 16)
            except BlockingIOError:
                return out

    def close(self) -> None:
        for fd in (self.r, self.w):
            os.close(fd)
        self.mine.close()
        self.peer.close()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def test_lines_and_records_are_the_python_paths(rig):
    os.write(rig.w, frames(range(65533, 65536)))  # one read of three frames, up to the wrap
    leftover, stopped = rig.step(65533, 1000)
    os.write(rig.w, frames([0]))
    leftover2, _ = rig.step(0, 1003)
    assert leftover == leftover2 == b"" and stopped is None
    assert rig.ist[fp.IST_FRAMES] == 1 and rig.ist[fp.IST_SEQ] == 1004 and rig.ist[fp.IST_EXPECT] == 1
    rows = np.frombuffer(bytes(rig.staged), SAMPLE_DTYPE)
    # the Python path's records for the same bytes: the decoder, then the driver's stamps
    ref = FrameDecoder().feed(frames(range(65533, 65536)) + frames([0]))
    for name in ("tick", "t1", "t2", "gyro", "temp", "vsupply", "flags"):
        np.testing.assert_array_equal(rows[name], ref[name])
    np.testing.assert_array_equal(rows["seq"], np.arange(1000, 1004))
    t = rows["t"]
    assert t[1] - t[0] == pytest.approx(5e-3, abs=1e-9) and t[2] - t[1] == pytest.approx(5e-3, abs=1e-9)
    assert t[3] >= t[2]
    acc = rig.processor.acc(rows)
    gyro = (rows["gyro"].astype(float) - 2048.0) / 357.36
    static = np.where(rows["seq"] - 900 <= 400.0, 1, -1).astype(np.int8)
    want = imu_lines(rows, acc, gyro, static, raw=True)
    assert rig.received() == want  # bit for bit: the numpy references' correction and lines
    assert rig.client.sent_messages == 0  # counted in the C record until folded
    rig.client.fold()
    assert rig.client.sent_messages == 4 and rig.client.sent_bytes == len(want)
    assert rig.ist[fp.IST_UNKNOWN] == 0


def test_whatever_is_not_the_common_case_is_handed_back_unconsumed(rig):
    cases = {
        "gap": frames([7]),
        "partial": frames([5])[:20],
        "crc": bytes([b ^ (i == 10) for i, b in enumerate(frames([5]))]),
        "garbage before": b"\x00" + frames([5]),
        "good then gap": frames([5, 6, 9]),
    }
    for name, data in cases.items():
        rig.staged.clear()
        os.write(rig.w, data)
        leftover, stopped = rig.step(5, 100)
        assert leftover == data, name
        assert rig.ist[fp.IST_REASON] == fp.R_BYTES and rig.ist[fp.IST_FRAMES] == 0, name
        assert not rig.staged and rig.received() == b"", name
    rig.server.fast_watchers = None  # a decimated watcher: nothing is read
    os.write(rig.w, frames([5]))
    assert rig.step(5, 100) == (b"", None) and rig.ist[fp.IST_REASON] == fp.R_NOT_PLAIN
    assert os.read(rig.r, 100) == frames([5])


def test_a_delivery_it_cannot_finish_stops_with_the_lock_held(rig):
    c = rig.client
    with c.lock:
        c.queue.put([b"queued\n"])  # something queued goes first
    os.write(rig.w, frames([5]))
    leftover, stopped = rig.step(5, 100)
    assert leftover == b"" and stopped is rig.server.fast_watchers
    assert rig.ist[fp.IST_REASON] == fp.R_DELIVERY and rig.ist[fp.IST_CLIENT] == 0 and rig.ist[fp.IST_SENT] == -1
    assert rig.ist[fp.IST_FRAMES] == 1 and rig.received() == b""
    got = []
    held = threading.Thread(target=lambda: got.append(c.lock.acquire(timeout=0.2)))
    held.start()
    held.join()
    assert got == [False]  # another thread cannot take it until the Python side releases it
    c.lock.release()
    with c.lock:
        c.queue.take(1 << 20)
        c.watch = WatchPolicy(True, False, 0.0)  # a changed policy: fanout decides
    os.write(rig.w, frames([6]))
    rig.step(6, 101)
    assert rig.ist[fp.IST_REASON] == fp.R_DELIVERY and rig.ist[fp.IST_SENT] == -1
    c.lock.release()


def test_a_full_socket_stops_with_what_it_took(rig):
    rig.mine.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
    for k in range(400):
        os.write(rig.w, frames([5 + k]))
        rig.step(5 + k, 100 + k)
        if rig.ist[fp.IST_REASON] == fp.R_DELIVERY:
            break
    assert rig.ist[fp.IST_REASON] == fp.R_DELIVERY and rig.ist[fp.IST_SENT] >= 0
    rig.client.lock.release()
    rig.client.fold()
    sent = rig.client.sent_bytes + rig.ist[fp.IST_SENT]
    assert len(rig.received()) == sent


@pytest.mark.parametrize("seed", range(20))
def test_arbitrary_bytes_are_handed_back_or_taken_whole(rig, seed):
    rng = np.random.default_rng(seed)
    good = frames(range(50, 50 + int(rng.integers(1, 6))))
    data = bytearray(good)
    for _ in range(int(rng.integers(0, 4))):  # flips, cuts and insertions
        i = int(rng.integers(0, len(data)))
        op = rng.integers(0, 3)
        if op == 0:
            data[i] ^= 1 << int(rng.integers(0, 8))
        elif op == 1:
            del data[i:]
        else:
            data[i:i] = rng.integers(0, 256, int(rng.integers(1, 40)), dtype=np.uint8).tobytes()
    if data:
        os.write(rig.w, bytes(data))
    leftover, _ = rig.step(50, 0)
    if bytes(data) == good:
        assert leftover == b"" and rig.ist[fp.IST_FRAMES] == len(good) // 29
    else:
        assert leftover == bytes(data) and rig.ist[fp.IST_FRAMES] == 0


def test_bad_arguments_are_refused_with_a_message(rig):
    args = [rig.r, 0.01, MAX, rig.ist, rig.fst, rig.staged, rig.server.fast_box, rig.processor.engine, rig.rows,
            rig.acc, rig.gyro, rig.codes]
    for i, bad, exc, words in [
        (8, np.zeros(MAX - 1, SAMPLE_DTYPE), ValueError, "rows holds"),
        (9, np.zeros((MAX - 1, 3)), ValueError, "acc holds"),
        (3, np.zeros(3, np.int64), ValueError, "ist holds"),
        (2, 0, ValueError, "max_frames"),
        (2, 100000, ValueError, "max_frames"),
        (0, -1, ValueError, "fd >= 0"),
        (1, math.nan, ValueError, "seconds"),
        (5, b"not a bytearray", TypeError, "bytearray"),
        (8, b"\0" * (56 * MAX), TypeError, "read-write"),
    ]:
        a = list(args)
        a[i] = bad
        with pytest.raises(exc, match=words):
            step(*a)
    os.write(rig.w, frames([5]))
    rig.server.fast_watchers = "not a tuple"
    with pytest.raises(TypeError, match="watcher snapshot"):
        rig.step(5, 0)
    rig.server.fast_watchers = ((1, 2),)
    with pytest.raises(TypeError, match="watcher entry"):
        rig.step(5, 0)
    assert rig.ist[fp.IST_FRAMES] == 1  # read before the error: accounted
    rig.server.fast_watchers = ((rig.client, object(), 3, True, rig.client.watch, rig.client.lock.acquire,
                                 rig.client.lock.release_unchanged),)  # not a ClientRecord
    os.write(rig.w, frames([6]))
    with pytest.raises(TypeError, match="watcher entry"):
        rig.step(6, 1)
    rig.server.fast_watchers = ()
    os.write(rig.w, frames([5]))
    with pytest.raises(ValueError, match="the engine has no parameters"):
        step(rig.r, 0, MAX, rig.ist, rig.fst, rig.staged, rig.server.fast_box, Engine(), rig.rows, rig.acc,
             rig.gyro, rig.codes)
    with pytest.raises(TypeError, match="Engine"):
        step(rig.r, 0, MAX, rig.ist, rig.fst, rig.staged, rig.server.fast_box, rig.processor, rig.rows, rig.acc,
             rig.gyro, rig.codes)
    for bad, words in ((np.zeros(5), "EP_N float64"), (np.zeros(EP_N, np.float32), "EP_N float64")):
        with pytest.raises(ValueError, match=words):
            rig.processor.engine.set_params(bad)
    v = engine_params(PLAIN, FS)
    v[-3] = 0.5  # the decision's "still" flag
    with pytest.raises(ValueError, match="decision flags"):
        rig.processor.engine.set_params(v)
    assert rig.step(5, 0) == (b"", None) and rig.ist[fp.IST_FRAMES] == 1  # the refused vectors changed nothing


def test_a_stopped_delivery_is_finished_even_when_the_accounting_fails(rig):
    """The step returns with a client's lock held; FastPath.run must hand that delivery to the fanout
    (which releases the lock) even if applying the counters raises, or the client stays locked out."""
    finished = []
    rig.server.finish_publish = lambda block, snapshot, index, sent: (finished.append(block.samples["seq"].tolist()),
                                                                        snapshot[index][0].lock.release())

    def fail(*_):
        raise RuntimeError("counters")

    driver = SimpleNamespace(fast_entry=lambda: (rig.r, 5, 100, 0.0), fast_consumed=fail, tick_hz=1e6,
                             unread=lambda data: None)
    path = fp.FastPath(driver, rig.processor, rig.server, max_frames=MAX, stage_bytes=1 << 30)
    with rig.client.lock:
        rig.client.queue.put([b"queued\n"])  # something queued goes first: the step stops at this client
    os.write(rig.w, frames([5]))
    with pytest.raises(RuntimeError, match="counters"):
        path.run(rig.staged, seconds=0.05)
    assert finished == [[100]]
    got = []
    t = threading.Thread(target=lambda: got.append(rig.client.lock.acquire(timeout=1.0)))
    t.start()
    t.join()
    assert got == [True], "the client's lock stayed held"


def test_the_gate_follows_every_change_made_under_the_clients_lock(rig):
    """The step sends only while the client's record holds the snapshot's policy: closing the client, queueing
    output for it or changing its watch (each under its lock, as the server does) stops the step before any
    byte goes out; once the output is flushed the step sends again."""
    c = rig.client
    cases = [("closed", lambda: setattr(c, "closed", True)),
             ("queued", lambda: c.queue.put([b"queued\n"])),
             ("partial line", lambda: setattr(c, "out", memoryview(b"rest\n"))),
             ("drop to announce", lambda: setattr(c, "dropped_unreported", 3)),
             ("watch changed", lambda: setattr(c, "watch", WatchPolicy(True, True, 0.0)))]
    for k, (name, change) in enumerate(cases):
        with c.lock:
            change()
        os.write(rig.w, frames([5 + k]))
        leftover, stopped = rig.step(5 + k, 100 + k)
        assert rig.ist[fp.IST_REASON] == fp.R_DELIVERY and rig.ist[fp.IST_SENT] == -1, name
        assert rig.received() == b"", name
        c.lock.release()
        with c.lock:  # undone: the step may send again
            c.closed, c.out, c.dropped_unreported = False, None, 0
            c.queue.take(1 << 20)
            c.watch = rig.server.fast_watchers[0][4]
    os.write(rig.w, frames([10]))
    rig.step(10, 200)
    assert rig.ist[fp.IST_REASON] == fp.R_DUE and rig.received().count(b"\n") == 1


def test_counters_stay_in_the_record_until_folded(rig):
    c = rig.client
    for k in range(5):
        os.write(rig.w, frames([5 + k]))
        rig.step(5 + k, 100 + k)
    got = rig.received()
    assert (c.sent_messages, c.sent_bytes) == (0, 0)
    c.last_progress = 1.0
    stats = c.stats(0.0)  # STATUS folds first
    assert stats["sent"] == c.sent_messages == 5 and c.sent_bytes == len(got)
    assert c.last_progress > 1.0  # the step's time.monotonic() of the last send
    assert c.record.take() == (0, 0, 0.0)


def test_a_calibration_swapped_mid_step_applies_from_the_next_wake_up(rig):
    """The step copies the engine's parameters again whenever Engine.set_params swapped them: a swap corrects the
    next sample with the new calibration, within the same call."""
    new = Calibration("6", np.array([0.47, 0.52, 0.5]), np.diag([0.042, 0.04, 0.038]))
    got = []

    def feed():
        os.write(rig.w, frames([5]))
        while not got:
            got.append(rig.received()) if rig.peer.recv(1, socket.MSG_PEEK) else None
        rig.processor.set(new, (2000.0, 350.0), (None, False))
        os.write(rig.w, frames([6]))

    t = threading.Thread(target=feed)
    t.start()
    rig.ist[fp.IST_EXPECT], rig.ist[fp.IST_SEQ] = 5, 100
    step(rig.r, 0.5, MAX, rig.ist, rig.fst, rig.staged, rig.server.fast_box, rig.processor.engine, rig.rows,
         rig.acc, rig.gyro, rig.codes)
    t.join()
    rows = np.frombuffer(bytes(rig.staged), SAMPLE_DTYPE)
    assert rows.shape[0] == 2
    second = rows[1:]
    gyro = (second["gyro"].astype(float) - 2000.0) / 350.0
    want = imu_lines(second, rig.processor.acc(second), gyro, np.array([-1], np.int8), raw=True)
    assert rig.received() == want


def test_the_stall_check_sees_the_steps_last_send(rig):
    """A client the step fed, with output pending now: its progress (what the server's stall check compares
    with stall_timeout_s) is the step's last send, not the last one the Python path counted."""
    c = rig.client
    os.write(rig.w, frames([5]))
    before = time.monotonic()
    rig.step(5, 100)
    with c.lock:
        c.queue.put([b"queued\n"])
    assert c.pending() and c.last_progress == 0.0
    assert before <= c.progress() <= time.monotonic()


def test_on_a_tty_every_frame_is_taken_as_it_arrives(rig):
    """The step waits edge-triggered on a terminal (VMIN one frame, as drivers/serial.py sets it): each arrival
    must be read whole when it wakes the step, or its bytes would wait for the next frame. Three frames in
    one write and a frame split across two writes all reach the
    client within the one call, which returns once they are staged, long before its deadline."""
    import pty
    import termios
    import tty as ttymod

    master, slave = pty.openpty()
    try:
        ttymod.setraw(slave)
        attrs = termios.tcgetattr(slave)
        attrs[6][termios.VMIN], attrs[6][termios.VTIME] = 29, 0
        termios.tcsetattr(slave, termios.TCSANOW, attrs)
        os.set_blocking(slave, False)
        rig.ist[fp.IST_STAGE_LIMIT] = 4 * SAMPLE_DTYPE.itemsize
        wire = frames(range(5, 9))

        def feed():
            for part in (wire[:87], wire[87:100], wire[100:]):
                os.write(master, part)
                time.sleep(0.02)

        t = threading.Thread(target=feed)
        t.start()
        rig.ist[fp.IST_EXPECT], rig.ist[fp.IST_SEQ] = 5, 100
        t0 = time.monotonic()
        leftover, stopped = step(slave, 10.0, MAX, rig.ist, rig.fst, rig.staged, rig.server.fast_box,
                                 rig.processor.engine, rig.rows, rig.acc, rig.gyro, rig.codes)
        elapsed = time.monotonic() - t0
        t.join()
    finally:
        os.close(master)
        os.close(slave)
    assert (leftover, stopped) == (b"", None) and rig.ist[fp.IST_REASON] == fp.R_DUE
    rows = np.frombuffer(bytes(rig.staged), SAMPLE_DTYPE)
    np.testing.assert_array_equal(rows["seq"], np.arange(100, 104))
    assert rig.received().count(b"\n") == 4
    assert elapsed < 5.0  # returned on the stage limit, not at the 10 s deadline with bytes left unread


def test_the_servers_snapshot_box_is_read_at_every_wake_up(rig):
    """A server with ``fast_box`` (daemon/server.py): the step holds the box for the call and reads its table
    per wake-up, so a watcher leaving mid-call gets no further line; a box that is not a WatcherBox is refused."""
    rig.server = SimpleNamespace(fast_box=WatcherBox(fast_snapshot((rig.client,))))
    rig.ist[fp.IST_STAGE_LIMIT] = 2 * SAMPLE_DTYPE.itemsize
    got = []

    def feed():
        os.write(rig.w, frames([5]))
        while not got:
            got.append(rig.received()) if rig.peer.recv(1, socket.MSG_PEEK) else None
        rig.server.fast_box[0] = ()  # the watcher left: the next wake-up sends to nobody
        os.write(rig.w, frames([6]))

    t = threading.Thread(target=feed)
    t.start()
    leftover, stopped = rig.step(5, 100, seconds=5.0)
    t.join()
    assert (leftover, stopped) == (b"", None)
    assert np.frombuffer(bytes(rig.staged), SAMPLE_DTYPE)["seq"].tolist() == [100, 101]
    assert got[0].count(b"\n") == 1 and rig.received() == b""
    for bad in ([], [()], ((),), None):
        rig.server = SimpleNamespace(fast_box=bad)
        with pytest.raises(TypeError, match="WatcherBox"):
            rig.step(7, 102)


def test_the_box_holds_exactly_one_item():
    """The step reads a WatcherBox's table without the GIL: it can be replaced, never emptied or grown."""
    box = WatcherBox(())
    assert len(box) == 1 and box[0] == ()
    box[0] = None
    assert box[0] is None
    for index in (1, -2):
        with pytest.raises(IndexError, match="one item"):
            box[index] = ()
    with pytest.raises(IndexError, match="one item"):
        del box[0]
    with pytest.raises(IndexError, match="one item"):
        box[1]
    assert box[0] is None

