"""The latency path's C step (daemon/_fastpath.c) against the Python path it stands in for.

The same byte stream goes through gravcald twice, on a pty, with the C step and without it; every
client must receive the same bytes (sample time ``t`` apart: it is the host's reception time, checked to
never run backwards). The stream holds the cases the C step hands to the Python path: a 16-bit wrap,
a gap, a CRC error, garbage, a frame split across writes, several frames in one read, a device restart,
a reconnect, a calibration change, a decimated watcher (its samples are chosen by reception time:
checked apart) and a raw one joining and leaving mid-stream. The calibration change is to an extended
calibration (temperature and supply terms, gravcald's default): the C step corrects it, and the samples after
it are the model's (Calibration.apply) at their temperature and supply.
"""
from __future__ import annotations

import json
import re
import socket
import threading
import time

import numpy as np

from gravcal.core.calibration import Calibration
from gravcal.clients.client import Client
from gravcal.daemon.config import Config
from gravcal.daemon.service import Gravcald
from gravcal.drivers import open_driver
from gravcal.core.samples import raw_triad
from gravcal.daemon.protocol import STANDARD_GRAVITY
from gravcal.drivers.codec import FrameDecoder, encode_frames
from support.correction_reference import extended_model
from gravcal.drivers.rigs.emulator import PtyLink
from gravcal.drivers.rigs.sources import pattern_blocks

TICKS_PER_SAMPLE = 5000  # 200 Hz at the driver's 1 MHz tick
# temperature and supply terms, their references away from the pattern's 25 °C and 3.3 V so that they act
EXTENDED = Calibration("6+temperature_offset+supply_offset", np.array([0.49, 0.51, 0.5]), np.diag([0.041] * 3),
                       metadata={"extended": {"terms": ["temperature_offset", "supply_offset"], "t_ref_c": 5.0,
                                              "v_ref": 3.0, "t0_s": 0.0},
                                 "params": {"oT_x": 4e-4, "oT_y": -3e-4, "oT_z": 2e-4,
                                            "oV_x": 0.02, "oV_y": -0.01, "oV_z": 0.015}})


class NoWindows:
    """A detector that never finds a window: `static` is then false for every sample, whatever the timing."""

    to_g = None
    last_detection = None

    def update(self, t, raw, aux):
        return []


def frames(seqs, ticks=None, seed=0) -> bytes:
    seqs = np.asarray(seqs, dtype=np.int64)
    s = next(pattern_blocks(seed=seed, fs=200, duration=seqs.shape[0] / 200, block=seqs.shape[0])).copy()
    s["seq"] = seqs & 0xFFFF
    s["tick"] = (seqs * TICKS_PER_SAMPLE if ticks is None else np.asarray(ticks)) & 0xFFFFFFFF
    return encode_frames(s)


class Reader:
    """A client collecting everything it receives."""

    def __init__(self, path: str, watch: str):
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.connect(path)
        self.sock.sendall(watch.encode() + b"\n")
        self.data = bytearray()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()
        end = time.monotonic() + 20
        while b'"class":"WATCH"' not in self.data:  # the server has its policy: what follows is sent to it
            assert time.monotonic() < end, "no WATCH reply"
            time.sleep(0.01)

    def _run(self) -> None:
        while True:
            try:
                got = self.sock.recv(1 << 16)
            except OSError:
                return
            if not got:
                return
            self.data += got

    def imu(self) -> int:
        return self.data.count(b'"class":"IMU"')

    def close(self) -> None:
        try:  # wakes the reading thread's recv (a close from another thread does not)
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:  # the daemon hung up already
            pass
        self._t.join(5)
        assert not self._t.is_alive(), "the reader thread did not end"
        self.sock.close()


def settle(d: Gravcald, reader: Reader, timeout: float = 20.0) -> None:
    """Wait until the daemon has published everything written and ``reader`` has it."""
    end, last, since = time.monotonic() + timeout, -1, time.monotonic()
    while time.monotonic() < end:
        n = d.server.published_samples
        if n != last:
            last, since = n, time.monotonic()
        elif time.monotonic() - since > 0.3 and reader.imu() >= n:
            return
        time.sleep(0.02)
    raise AssertionError(f"the daemon did not settle: published {d.server.published_samples}")


def start_daemon(tmp_path, fast: bool, driver, calibration: Calibration | None = None) -> Gravcald:
    """gravcald on ``driver`` without windows to analyse, its socket and state under ``tmp_path``, with
    (``fast``) or without the C step, started from ``calibration`` (a lab calibration file) when given."""
    cfg = Config()
    cfg.socket.path = str(tmp_path / f"g-{fast}.sock")
    cfg.state.directory = str(tmp_path / f"state-{fast}")
    if calibration is not None:
        path = tmp_path / f"lab-{fast}.json"
        path.write_text(calibration.to_json())
        cfg.state.lab_calibration = str(path)
    d = Gravcald(cfg, driver=driver, environ={}, detector=NoWindows())
    d.fast_path = fast
    d.start()
    return d


def run_stream(tmp_path, fast: bool) -> tuple[dict[str, bytes], dict]:
    link = PtyLink(tmp_path / f"tty-{fast}" / "ttyGRAVCAL0")
    link.connect()
    d = start_daemon(tmp_path, fast, open_driver(link.spec + "?tick_hz=1000000"))
    cfg = d.cfg
    readers: dict[str, Reader] = {}
    out: dict[str, bytes] = {}  # a reader that left: what it received

    def write(data: bytes, per_write: int = 1, pause: float = 0.002) -> None:
        step = 29 * per_write
        for i in range(0, len(data), step):
            link.write(data[i:i + step], True)
            time.sleep(pause)

    try:
        ids = {}  # the server numbers clients from 1 in the order they connect (each Reader waits for its WATCH)
        for name, watch in (("plain", '{"enable":true}'), ("raw", '{"enable":true,"raw":true}'),
                            ("switch", '{"enable":true}'), ("leaver", '{"enable":true,"raw":true}')):
            readers[name] = Reader(cfg.socket.path, f"?WATCH={watch};")
            ids[name] = len(ids) + 1
        a = readers["plain"]
        seq = 65400
        write(frames(range(seq, seq + 200)))  # through the 16-bit wrap, one frame per read
        seq += 200
        write(frames(range(seq, seq + 60)), per_write=3)  # several frames per read
        seq += 60
        settle(d, a)
        # mid-stream: a full-rate watcher leaves (the step's send fails, the server closes it), one changes its
        # watch to raw, one asks for VERSION (output queued by the server thread: it goes before the samples)
        leaver = readers.pop("leaver")
        leaver.close()
        out["leaver"] = bytes(leaver.data)
        readers["switch"].sock.sendall(b'?WATCH={"raw":true};\n')
        a.sock.sendall(b"?VERSION;\n")
        end = time.monotonic() + 10
        while readers["switch"].data.count(b'"class":"WATCH"') < 2 or a.data.count(b'"class":"VERSION"') < 2:
            assert time.monotonic() < end, "no reply to the mid-stream requests"
            time.sleep(0.01)
        write(frames(range(seq + 5, seq + 8)))  # 5 samples lost, then frames that each arrive whole
        bad = bytearray(frames([seq + 8]))
        bad[12] ^= 0x40  # a bit error: the CRC fails
        link.write(bytes(bad) + b"\x00\xa5\x13junk", True)
        time.sleep(0.05)
        seq += 9
        write(frames(range(seq, seq + 20)))
        seq += 20
        write(frames(range(seq + 70, seq + 90)))  # a jump the unwrapper does not believe at once (a stray?)
        seq += 90
        settle(d, a)
        write(frames(range(0, 20), ticks=np.arange(20) * TICKS_PER_SAMPLE))  # the device restarted, no outage
        seq = 20
        split = frames(range(seq, seq + 3))
        link.write(split[:40], True)  # a frame split across two writes
        time.sleep(0.05)
        link.write(split[40:], True)
        seq += 3
        write(frames(range(seq, seq + 40)))
        seq += 40
        settle(d, a)
        cal = EXTENDED
        # a calibration accepted by the processing thread and its CALIB: the acquisition thread takes both
        d.processor.applied = cal
        d.processor.stage_message({"revision": 7, "model": cal.model, "accepted": True, "offset": cal.offset.tolist()})
        deadline = time.monotonic() + 10
        while d.processor.has_pending and time.monotonic() < deadline:  # taken before the next frames, on both paths
            time.sleep(0.01)
        taken_before = d._fast.taken if d._fast is not None else 0
        write(frames(range(seq, seq + 40)))
        seq += 40
        settle(d, a)
        taken_extended = (d._fast.taken if d._fast is not None else 0) - taken_before
        readers["decimated"] = Reader(cfg.socket.path, '?WATCH={"enable":true,"rate":20};')
        write(frames(range(seq, seq + 40)))
        seq += 40
        settle(d, a)
        dec = readers.pop("decimated")
        dec.close()
        out["decimated"] = bytes(dec.data)
        time.sleep(0.5)  # the server notices the hang-up
        write(frames(range(seq, seq + 40)))
        seq += 40
        settle(d, a)
        readers["late"] = Reader(cfg.socket.path, '?WATCH={"enable":true,"raw":true};')
        write(frames(range(seq, seq + 40)))
        seq += 40
        settle(d, a)
        link.disconnect()  # an unplugged adapter; the device restarts meanwhile (seq and tick from 0)
        time.sleep(0.6)
        link.connect()
        time.sleep(1.5)  # the driver reopens the port (backoff)
        write(frames(range(0, 60), ticks=np.arange(60) * TICKS_PER_SAMPLE))
        settle(d, a)
        write(frames(range(60, 120), ticks=np.arange(60, 120) * TICKS_PER_SAMPLE), per_write=2)
        settle(d, a)
        taken = d._fast.taken if d._fast is not None else 0
        with Client(cfg.socket.path) as c:
            polled = c.poll()["imu"][0]["seq"]
        ids["late"] = len(ids) + 2  # after the decimated watcher
        stats = {**d.driver.stats(), "taken_by_c": taken, "published": d.server.published_samples, "polled": polled,
                 "taken_extended": taken_extended, "fs": cfg.device.fs_hz,
                 "nogil": d._fast.nogil if d._fast is not None else 0,
                 "sent_and_received": sent_and_received(cfg.socket.path, readers, ids)}
    finally:
        out.update(stop_all(d, readers, link))
    return out, stats


def sent_and_received(path: str, readers: dict[str, Reader], ids: dict[str, int]) -> dict[str, tuple[int, int]]:
    """Per reader: (the messages STATUS says were sent to it, the lines it received), once both are stable."""
    end = time.monotonic() + 10
    while True:
        with Client(path) as c:
            per = {p["id"]: p["sent"] for p in c.status()["server"]["per_client"]}
        got = {name: (per.get(ids[name]), bytes(r.data).count(b"\n")) for name, r in readers.items()}
        if all(s == n for s, n in got.values()) or time.monotonic() > end:
            return got
        time.sleep(0.1)


T_FIELD = re.compile(rb'"t":(-?[0-9.]+|null)')


def without_t(data: bytes) -> tuple[bytes, list[float]]:
    ts = [float(m.group(1)) for m in T_FIELD.finditer(data)]
    return T_FIELD.sub(b'"t":T', data), ts


def stop_all(d: Gravcald, readers: dict[str, Reader], *links) -> dict[str, bytes]:
    """End the readers, then the daemon and the links: what each reader received."""
    out = {}
    for name, r in readers.items():
        r.close()
        out[name] = bytes(r.data)
    d.request_stop()
    d.shutdown()
    for link in links:
        link.close()
    return out


def decided(data: bytes) -> bytes:
    """``static`` null (no decision recent enough: the processing thread was behind the acquisition, a matter
    of the host's timing, not of the path) read as the only decision NoWindows makes, false."""
    return data.replace(b'"static":null', b'"static":false')


def assert_same_streams(slow: dict[str, bytes], fast: dict[str, bytes], min_imu: int = 1) -> None:
    """Each client received the same bytes without and with the C step, apart from ``t`` (the host's
    reception time), which never runs backwards, and a ``static`` left unknown while the detector lagged."""
    for name in slow:
        a, _ = without_t(decided(slow[name]))
        b, tb = without_t(decided(fast[name]))
        assert a.count(b'"IMU"') >= min_imu
        assert b == a, name
        assert np.all(np.diff(tb) >= 0), name  # sample time never runs backwards


def assert_same_counts(slow_stats: dict, fast_stats: dict, counters, min_share: float) -> None:
    """The run without the C step took nothing through it; the run with it took at least ``min_share`` of the
    published samples through C (the clean stretches) but not all (each case it does not take went through
    the Python path); and the driver's ``counters`` agree between the two runs."""
    assert slow_stats["taken_by_c"] == 0
    assert fast_stats["taken_by_c"] >= min_share * fast_stats["published"], fast_stats
    assert fast_stats["taken_by_c"] < fast_stats["published"], fast_stats
    if "nogil" in fast_stats:  # the step's buses (serial, slcan): its batches delivered without the GIL
        assert slow_stats["nogil"] == 0 and fast_stats["nogil"] >= 1, fast_stats
    for key in counters:
        assert fast_stats[key] == slow_stats[key], (key, fast_stats, slow_stats)


def test_clients_receive_the_same_bytes_with_and_without_the_c_step(tmp_path):
    slow, slow_stats = run_stream(tmp_path, fast=False)
    fast, fast_stats = run_stream(tmp_path, fast=True)
    assert_same_counts(slow_stats, fast_stats, ("frames", "crc_errors", "gaps", "missing", "restarts", "reconnects",
                                                "samples"), min_share=0.6)
    assert slow_stats["gaps"] >= 2 and slow_stats["crc_errors"] >= 1 and slow_stats["reconnects"] == 1
    assert set(fast) == set(slow) == {"plain", "raw", "switch", "leaver", "decimated", "late"}
    # STATUS's per-client counts (the C step's folded in) are what each client received
    for st in (slow_stats, fast_stats):
        assert set(st["sent_and_received"]) == {"plain", "raw", "switch", "late"}
        for name, (sent, received) in st["sent_and_received"].items():
            assert sent == received > 100, (name, st["sent_and_received"])
    # which samples a decimated watcher gets depends on their reception times: served, in order
    for got in (slow.pop("decimated"), fast.pop("decimated")):
        seqs = [json.loads(x)["seq"] for x in got.splitlines() if b'"IMU"' in x]
        assert len(seqs) >= 2 and np.all(np.diff(seqs) > 0)
    assert_same_streams(slow, fast)
    lines = [json.loads(x) for x in fast["raw"].splitlines()]
    imu = [m for m in lines if m["class"] == "IMU"]
    seqs = np.array([m["seq"] for m in imu])
    assert fast_stats["polled"] == slow_stats["polled"] == seqs[-1]  # ?POLL: the newest sample
    assert np.all(np.diff(seqs) >= 1)
    assert any(m["flags"] & 1 for m in imu)  # a gap flagged (FLAG_GAP_BEFORE)
    assert sum(m["class"] == "CALIB" for m in lines) == 2  # at WATCH, and the change
    # the extended calibration: corrected in C, each sample the model's at its temperature and supply
    assert slow_stats["taken_extended"] == 0 and fast_stats["taken_extended"] == 40, fast_stats
    after = next(i for i, m in enumerate(lines) if m["class"] == "CALIB" and m.get("revision") == 7)
    got = [m for m in lines[after:] if m["class"] == "IMU"][:40]
    rows = FrameDecoder().feed(frames(range(got[0]["seq"], got[0]["seq"] + 40)))
    rows["seq"] = [m["seq"] for m in got]
    want = extended_model(EXTENDED, rows, fast_stats["fs"], STANDARD_GRAVITY)
    acc = np.array([m["acc"] for m in got])
    np.testing.assert_allclose(acc, want, rtol=0, atol=6e-6)  # the line's 5 decimals
    assert np.abs(EXTENDED.apply_reference(raw_triad(rows)) * STANDARD_GRAVITY - want).min() > 0.05  # terms act


def test_a_slow_reader_beside_the_c_step_loses_only_whole_counted_lines(tmp_path):
    """A reader that stops reading fills its socket: the C step hands the rest of each block to fanout, which
    queues it behind what is pending (bounded, the oldest dropped and announced); a plain reader beside it
    gets every sample, and the slow one, once it reads again, whole lines in order with the loss counted."""
    link = PtyLink(tmp_path / "tty" / "ttyGRAVCAL0")
    link.connect()
    cfg = Config()
    cfg.socket.path = str(tmp_path / "g.sock")
    cfg.socket.queue_messages = 50
    cfg.state.directory = str(tmp_path / "state")
    d = Gravcald(cfg, driver=open_driver(link.spec), environ={}, detector=NoWindows())
    d.start()
    try:
        good = Reader(cfg.socket.path, '?WATCH={"enable":true};')
        slow = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        slow.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        slow.connect(cfg.socket.path)
        slow.sendall(b'?WATCH={"enable":true,"raw":true};\n')
        time.sleep(0.3)
        for k in range(0, 600, 2):
            link.write(frames(range(k, k + 2)), True)
            time.sleep(0.002)
        settle(d, good)
        n = d.server.published_samples
        taken = d._fast.taken
        with Client(cfg.socket.path) as c:  # ?POLL answers with the newest sample the C step published
            polled = c.poll()["imu"][0]
        slow.settimeout(1.0)
        data = b""
        while True:
            try:
                got = slow.recv(1 << 16)
            except socket.timeout:
                break
            if not got:
                break
            data += got
    finally:
        d.request_stop()
        d.shutdown()
        link.close()
        good.close()
    assert good.imu() == n == 600 and taken > 0
    msgs = [json.loads(x) for x in data.splitlines()]  # whole lines only
    seqs = [m["seq"] for m in msgs if m["class"] == "IMU"]
    dropped = sum(m["count"] for m in msgs if m["class"] == "DROPPED")
    assert dropped > 0 and np.all(np.diff(seqs) > 0)
    assert len(seqs) + dropped == n
    assert seqs[-1] == good_last_seq(good) == polled["seq"]
    assert polled["class"] == "IMU" and len(polled["acc"]) == 3


def good_last_seq(r: Reader) -> int:
    return [json.loads(x) for x in bytes(r.data).splitlines() if b'"IMU"' in x][-1]["seq"]
