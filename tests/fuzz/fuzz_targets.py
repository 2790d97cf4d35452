"""One fuzz target per boundary where outside bytes enter gravcal: ``TARGETS[name](data)`` takes any bytes and
raises only when gravcal is wrong (an exception it should have turned into a counted loss or a one-line error, a
C kernel that disagrees with its Python reference, a request that ends the server, a traceback only printed).

Run by the suite on a fixed seed corpus and a fixed number of Hypothesis examples (test_fuzz_short.py), by
``python tests/fuzz/run.py NAME`` under atheris for long coverage-guided runs, and on the corpora the native
harnesses of the C kernels grow (native/, ``run.py NAME --replay``; docs/daemon.md, Security).
"""
from __future__ import annotations

import collections
import functools
import json
import os
import queue
import socket
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from gravcal.core.samples import SAMPLE_DTYPE
from gravcal.daemon.config import ConfigError, load_config
from gravcal.daemon.persistence import StateStore, load_lab_calibration
from gravcal.daemon.protocol import MAX_REQUEST_BYTES, WatchPolicy, encode_imu_joined
from gravcal.daemon.server import ServerConfig, SocketServer
from gravcal.drivers._framekernel import frame_header, frame_to_row, slcan_samples
from gravcal.drivers.base import Driver
from gravcal.drivers.can import SampleAssembler, records_to_samples
from gravcal.drivers.codec import FRAME_LEN, PAYLOAD_LEN, SYNC, FrameDecoder, crc16, decode_frames, scan
from gravcal.drivers.sequence import SeqUnwrapper
from gravcal.drivers.slcan import BufferedSlcanBus
from gravcal.errors import InputError
from gravcal.io.formats.sniff import sniff
from gravcal.io.recordings import read_recording

import gravcal  # noqa: E402 - the API's Calibration, imported with the rest so that atheris instruments it
from gravcal.api import Calibration as _ApiCalibration  # noqa: F401

# in memory where there is a tmpfs: a file written and read per input costs ~2 ms on this host's disk, 50 us there
_TMP = Path(tempfile.mkdtemp(prefix="gravcal-fuzz-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None))


# -- the serial frame decoder and its C kernel -----------------------------------------------------------
def _seal(stream: bytes, consecutive: bool) -> bytes:
    """Every whole 29-byte chunk of ``stream`` made a frame with a valid CRC (raw seq counting up from the first
    chunk's if ``consecutive``): a fuzzer mutating payloads keeps reaching the intact-frame paths. The native
    harness (native/framekernel_fuzz.c) seals the same way, so its corpus replays here."""
    s = bytearray(stream)
    seq0 = int.from_bytes(s[3:5], "little") if len(s) >= FRAME_LEN else 0
    for p in range(0, len(s) - FRAME_LEN + 1, FRAME_LEN):
        s[p:p + 3] = SYNC + bytes([PAYLOAD_LEN])
        if consecutive:
            s[p + 3:p + 5] = ((seq0 + p // FRAME_LEN) & 0xFFFF).to_bytes(2, "little")
        s[p + 27:p + 29] = crc16(s[p:p + 27]).to_bytes(2, "big")
    return bytes(s)


def frame_decoder(data: bytes) -> None:
    """Byte 0 where the stream is cut into two reads, byte 1 a mode (bit 0: _seal, bit 1: consecutive), then
    the stream. The streaming decoder in two reads equals the stateless decode of the whole (the same frames,
    CRC collisions included); at every frame the stateless scan finds and every 7th byte, the C kernel's
    header and row equal the Python reference's."""
    if len(data) < 2:
        return
    mode, stream = data[1], data[2:]
    if mode & 1:
        stream = _seal(stream, bool(mode & 2))
    cut = data[0] % (len(stream) + 1)
    dec = FrameDecoder()
    got = np.concatenate([dec.feed(stream[:cut]), dec.feed(stream[cut:])])
    want = decode_frames(stream)
    assert got.shape[0] <= want.shape[0]  # the unwrapper may drop strays and duplicates, never invent
    assert set(got["tick"].tolist()) <= set(want["tick"].tolist())
    starts = set(scan(stream, final=True).starts) | set(range(0, max(0, len(stream) - FRAME_LEN + 1), 7))
    intact = []
    for p in sorted(starts):
        frame = stream[p:p + FRAME_LEN]
        # scan's first step: no sync word at 0, no frame at 0 (scan itself on the windows that have one)
        ref = frame.startswith(SYNC) and scan(frame, final=True).starts == [0]
        head = frame_header(frame)
        assert (head is not None) == ref, (p, head)
        if ref:
            intact.append((frame, head))
    if intact:  # the reference's rows of all intact windows in one pass: each is a frame, so is their sequence
        rows = decode_frames(b"".join(f for f, _ in intact))
        assert rows.shape[0] == len(intact)
        rows["flags"] = mode
        mine = np.empty(1, SAMPLE_DTYPE)
        for (frame, head), row in zip(intact, rows):
            assert head == (int(row["seq"]), int(row["tick"]))
            frame_to_row(frame, mine, int(row["seq"]), mode)
            assert mine[0].tobytes() == row.tobytes()


# -- slcan lines: python-can's parser at the CAN driver's boundary, and the C reader against it ---------------
BASE = 0x100


def _python_slcan(data: bytes, unwrapper: SeqUnwrapper) -> tuple[np.ndarray, int]:
    """python-can's parse of every line (what it raises on a garbled one is counted, as CanDriver._recv does),
    the assembler, the unwrapper, the driver's stamping at t=1000: (block, garbled lines)."""
    bus = BufferedSlcanBus.__new__(BufferedSlcanBus)  # its line buffer and parser, without a port
    bus._lines, bus._partial, bus._queue = collections.deque(), bytearray(), queue.Queue()
    bus._split(data)
    asm = SampleAssembler(BASE)
    garbled = 0
    while bus._lines:
        try:
            msg, _ = bus._recv_internal(0)
        except Exception:  # noqa: BLE001 - the driver's rule: any parser exception is one garbled line
            garbled += 1
            continue
        if msg is not None:
            asm.on_message_received(msg)
    asm.poll(float("inf"))
    block = records_to_samples(asm.take(), unwrapper)
    fake = SimpleNamespace(_last_t=0.0, tick_hz=1e6, _rate=SimpleNamespace(update=lambda *a: None))
    if block.shape[0]:  # as read() does
        Driver._stamp(fake, block, 1000.0)
    return block, garbled


def _primed(expect: int) -> SeqUnwrapper:
    u = SeqUnwrapper()
    u.unwrap((expect - np.array([2, 1])) & 0xFFFF, np.array([0, 5000]))
    return u


def slcan_lines(data: bytes) -> None:
    """Any bytes as slcan lines: the Python path never raises beyond a counted garbled line; the C reader takes
    either nothing or exactly the records the Python path gives, bit for bit."""
    expect = int.from_bytes(data[:2].ljust(2, b"\0"), "little")
    data = data[2:]
    want, _ = _python_slcan(data, _primed(expect))
    buf = np.zeros(65, SAMPLE_DTYPE)
    buf.view(np.uint8)[:] = 0xA5
    raw, seq0 = _primed(expect).next_frame()
    k, _ = slcan_samples(data, BASE, raw, seq0, 1e6, 1000.0, 0.0, buf[:64])
    assert buf[64:].view(np.uint8).tolist() == [0xA5] * SAMPLE_DTYPE.itemsize  # nothing past the rows given
    if k:
        assert buf[:k].tobytes() == want.tobytes(), (k, want.shape)


# -- socket requests through the real server ----------------------------------------------------------
_SERVER: SocketServer | None = None
_CONN: socket.socket | None = None  # one client connection, reused while the server keeps no state of an input
_CONN_ID = -1  # the server's id of that client
HANG_UP = b"\x04"  # an input ending in ^D: the client half-closes after it (as `echo ... | nc -U` does)


def _server() -> SocketServer:
    global _SERVER
    if _SERVER is None or not _SERVER.alive:
        _SERVER = SocketServer(str(_TMP / "fuzz.sock"), config=ServerConfig(
            request_rate_hz=1e6, request_burst=10**6, idle_timeout_s=1e9),  # budget and idle limit: tested elsewhere
            status_provider=lambda: {"device": {"bus": "fuzz"}}).start()
    return _SERVER


def _connect(srv: SocketServer) -> socket.socket:
    c = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    c.settimeout(5)
    c.connect(srv.address)
    banner = b""
    while not banner.endswith(b"\n"):
        chunk = c.recv(4096)
        assert chunk, "the server hung up before its VERSION banner"
        banner += chunk
    assert json.loads(banner)["class"] == "VERSION", banner[:200]
    return c


def _hang_up() -> None:
    global _CONN
    if _CONN is not None:
        _CONN.close()
        _CONN = None


def socket_request(data: bytes) -> None:
    """Bytes a client sends (cut into lines as sent), then ``?WATCH={"enable":false};?VERSION;`` and a marker
    line: every reply is one JSON line, the VERSION asked for comes back (nothing lost the client its answer)
    unless the server hung up at its stated limit (oversized requests), and the server thread lives on. Ending
    in ^D, the client sends the WATCH and VERSION as a last line without its newline and half-closes instead of
    sending the marker: the server answers what it got, that line included, then hangs up.
    The connection is reused while the server holds nothing of an input that could change the next one's
    answers (no oversized request counted, the default WATCH policy): each input is answered as on a fresh one."""
    global _CONN, _CONN_ID
    srv = _server()
    data = data[: 4 * MAX_REQUEST_BYTES]
    hang_up = data.endswith(HANG_UP)
    if hang_up:
        _hang_up()
        c = _connect(srv)
        c.sendall(data[:-1] + b'\n?WATCH={"enable":false};?VERSION;')  # a last line without its newline ...
        c.shutdown(socket.SHUT_WR)  # ... then half-closed: the server answers what it got, then hangs up
        marker = None
    else:
        if _CONN is not None and _CONN_ID not in srv._clients:
            _hang_up()  # the server let it go between inputs (stopped, restarted): a fresh one
        if _CONN is None:
            _CONN = _connect(srv)
            _CONN_ID = max(list(srv._clients), default=-1)  # the newest: ours (the only client that connects)
        c, n = _CONN, 0
        while b"END%d" % n in data:  # a command no reply to this input can name
            n += 1
        marker = b"'?END%d'" % n
        c.sendall(data + b'\n?WATCH={"enable":false};?VERSION;\n?END%d\n' % n)
    out = bytearray()
    try:
        while not (marker and out.endswith(b"\n") and marker in out[out.rfind(b"\n", 0, len(out) - 1) + 1:]):
            chunk = c.recv(1 << 16)
            if not chunk:
                break
            out += chunk
    except ConnectionResetError:  # the server hung up on bytes it had not read: judged below
        pass
    except BaseException:
        _hang_up()
        raise
    finally:
        if hang_up:
            c.close()
    lines = bytes(out).split(b"\n")
    assert lines[-1] == b"", bytes(out[-200:])
    for line in lines[:-1]:
        msg = json.loads(line)
        assert isinstance(msg, dict) and isinstance(msg.get("class"), str), line[:200]
    assert srv.alive
    hung_up_at_limit = any(b"longer than" in x for x in lines)
    complete = marker is None or (len(lines) >= 2 and marker in lines[-2])
    if not complete or hang_up:
        _hang_up()
        assert complete or hung_up_at_limit, lines[-3:]  # the server ended the connection only at its stated limit
    if hang_up and not hung_up_at_limit or complete and not hang_up:
        assert json.loads(lines[-2 if hang_up else -3])["class"] == "VERSION", lines[-3:]
    if _CONN is not None:
        client = srv._clients.get(_CONN_ID)
        if client is None or client.oversize_count or client.watch != WatchPolicy():
            _hang_up()  # the next input starts on a fresh connection


# -- the IMU line: the C line kernel against the block encoder's %-templates -------------------------------
IMU_INPUT = 90  # a SAMPLE_DTYPE row (56), acc 3 float64 (24), gyro float64 (8), the static code (int8), raw (bit 0)


def imu_line(data: bytes) -> None:
    """Any bits in every field of a sample (NaN payloads, subnormals, 1e308, negative zero, any integer): the
    one-sample line (the C kernel) is byte for byte the block encoder's, and valid JSON. The native harness
    (native/linekernel_fuzz.c) reads inputs the same way, so its corpus replays here."""
    buf = data[:IMU_INPUT].ljust(IMU_INPUT, b"\0")
    row = np.frombuffer(buf[:56], SAMPLE_DTYPE)
    acc = np.frombuffer(buf[56:80], "<f8").reshape(1, 3)
    gyro = np.frombuffer(buf[80:88], "<f8")
    static = np.array([int.from_bytes(buf[88:89], "little", signed=True)])
    raw = bool(buf[89] & 1)
    one = encode_imu_joined(row, acc, gyro, static, raw=raw)
    two = encode_imu_joined(np.concatenate([row, row]), np.concatenate([acc, acc]), np.concatenate([gyro, gyro]),
                            np.concatenate([static, static]), raw=raw)
    assert two == one + one, (one, two)
    msg = json.loads(one)
    assert msg["class"] == "IMU" and one.endswith(b"}\n") and one.count(b"\n") == 1


# -- files the daemon and the command line read ---------------------------------------------------------
def _file(name: str, data: bytes) -> Path:
    p = _TMP / name
    p.write_bytes(data)
    return p


def config_file(data: bytes) -> None:
    """gravcald.toml: a Config or one ConfigError line."""
    try:
        load_config(_file("gravcald.toml", data))
    except ConfigError as exc:
        assert "\n" not in str(exc) and len(str(exc)) < 2000, str(exc)[:300]


def state_file(data: bytes) -> None:
    """state.json: loaded, or moved aside with one note; never an exception."""
    d = _TMP / "state"
    d.mkdir(exist_ok=True)
    for old in d.iterdir():
        old.unlink()
    (d / "state.json").write_bytes(data)
    res = StateStore(d).load()
    assert len(res.notes) == 1 and "\n" not in res.notes[0]
    assert res.state is None or res.moved_to is None


def calibration_json(data: bytes) -> None:
    """A lab or --start calibration: a Calibration or one InputError line (the daemon's and the API's loaders)."""
    p = _file("cal.json", data)
    for load in (load_lab_calibration, lambda q: gravcal.Calibration.from_json(Path(q).read_bytes())):
        try:
            load(p)
        except (InputError, ValueError) as exc:
            assert "\n" not in str(exc).strip() and len(str(exc)) < 2000, str(exc)[:300]


# -- recordings: sniffing and reading -----------------------------------------------------------------
SUFFIXES = (".csv", ".csv.gz", ".npy", ".gt3x", ".agdc", ".cwa", ".bin")


_READERS_IMPORTED = False


def recording(data: bytes) -> None:
    """Any bytes under each recording suffix: sniffed by content, read or refused with one InputError line, in
    under 30 s of this process's CPU (the readers' lazy imports, seconds instrumented, done before any is timed)."""
    global _READERS_IMPORTED
    if not _READERS_IMPORTED:
        _READERS_IMPORTED = True
        for seed in corpus("recording"):
            recording(seed)
    suffix = SUFFIXES[data[0] % len(SUFFIXES)] if data else ".csv"
    p = _file("rec" + suffix, data[1:])
    sniff(p)
    t0 = time.process_time()
    try:
        read_recording(p, check_saturation=True)
    except (InputError, ValueError) as exc:
        text = str(exc)
        assert "\n" not in text.strip() and len(text) < 2000 and "Traceback" not in text, text[:300]
    assert time.process_time() - t0 < 30.0


def _nothing_printed(target):
    """``target``, failing also on an exception Python could only print ("Exception ignored in ..."): one raised
    in a callback of a third-party parser, which the user would see as a bare traceback."""
    @functools.wraps(target)
    def run(data: bytes) -> None:
        seen = []
        old, sys.unraisablehook = sys.unraisablehook, seen.append
        try:
            target(data)
        finally:
            sys.unraisablehook = old
        assert not seen, f"printed, not raised: {seen[0].exc_type.__name__}: {seen[0].exc_value} in {seen[0].object!r}"
    return run


TARGETS = {f.__name__: _nothing_printed(f) for f in (frame_decoder, slcan_lines, socket_request, imu_line,
                                                     config_file, state_file, calibration_json, recording)}


def corpus(name: str) -> list[bytes]:
    """The seed corpus of ``name``: tests/fuzz/corpus/NAME/* (each a file; crashes found become entries)."""
    folder = Path(__file__).with_name("corpus") / name
    return [p.read_bytes() for p in sorted(folder.iterdir())] if folder.is_dir() else []


def cleanup() -> None:
    _hang_up()
    if _SERVER is not None:
        _SERVER.stop()
    for root, dirs, files in os.walk(_TMP, topdown=False):
        for f in files:
            os.unlink(os.path.join(root, f))
        for d in dirs:
            os.rmdir(os.path.join(root, d))
