"""The frame kernel's slcan reader (drivers/_framekernel.c slcan_continuing, the daemon's C step on a CAN bus)
against the Python path for the same bytes: python-can's slcan line parser, the SampleAssembler,
records_to_samples with the unwrapper and the driver's stamping. Whole samples that continue the stream give
the same records bit for bit; anything else is refused whole (nothing written), whatever the bytes."""
from __future__ import annotations

import queue
from types import SimpleNamespace

import numpy as np
import pytest

from gravcal.core.samples import SAMPLE_DTYPE
from gravcal.drivers._framekernel import slcan_samples
from gravcal.drivers.base import Driver
from gravcal.drivers.can import SLCAN_SAMPLE_BYTES, SampleAssembler, pack_frames, records_to_samples
from gravcal.drivers.rigs.sources import pattern_blocks
from gravcal.drivers.sequence import SeqUnwrapper
from gravcal.drivers.slcan import BufferedSlcanBus

BASE = 0x2A0
TICK_HZ = 1e6
T_RECV = 1234.5


def slcan_bytes(seqs, seed=0, base=BASE) -> bytes:
    seqs = np.asarray(seqs, dtype=np.int64)
    s = next(pattern_blocks(seed=seed, fs=200, duration=seqs.shape[0] / 200, block=seqs.shape[0])).copy()
    s["seq"], s["tick"] = seqs & 0xFFFF, (seqs * 5000 + 7) & 0xFFFFFFFF
    out = b"".join(f"t{base + k:03X}{len(d)}{d.hex().upper()}\r".encode()
                   for parts in pack_frames(s) for k, d in enumerate(parts))
    return out


def python_path(data: bytes, expect: int, last_t: float) -> np.ndarray:
    """python-can's parse of the lines, the assembler, the unwrapper (its head just before ``expect``), and
    Driver._stamp of the block at T_RECV."""
    bus = BufferedSlcanBus.__new__(BufferedSlcanBus)  # its line buffer and parser, without a port
    bus._lines, bus._partial, bus._queue = __import__("collections").deque(), bytearray(), queue.Queue()
    bus._split(data)
    asm = SampleAssembler(BASE)
    while bus._lines:
        msg, _ = bus._recv_internal(0)
        if msg is not None:
            asm.on_message_received(msg)
    asm.poll(float("inf"))
    block = records_to_samples(asm.take(), primed(expect))
    fake = SimpleNamespace(_last_t=last_t, tick_hz=TICK_HZ, _rate=SimpleNamespace(update=lambda *a: None))
    Driver._stamp(fake, block, T_RECV)
    return block


def primed(expect: int) -> SeqUnwrapper:
    """An unwrapper whose stream has reached the sample before raw seq ``expect``."""
    unwrapper = SeqUnwrapper()
    unwrapper.unwrap((expect - np.array([2, 1])) & 0xFFFF, np.array([0, 5000]))  # a first one alone is pending
    return unwrapper


def c_path(data: bytes, expect: int, last_t: float, cap: int = 64) -> tuple[int, np.ndarray, np.ndarray]:
    """(k, the rows written, the whole buffer with a guard record after ``cap``)."""
    buf = np.zeros(cap + 1, SAMPLE_DTYPE)
    buf.view(np.uint8)[:] = 0xA5
    raw, seq0 = primed(expect).next_frame()
    assert raw == expect
    k, _ = slcan_samples(data, BASE, expect, seq0, TICK_HZ, T_RECV, last_t, buf[:cap])
    return k, buf[:k], buf


@pytest.mark.parametrize("start,n,last_t", [(100, 1, 0.0), (65530, 12, 0.0), (7, 5, T_RECV + 1.0)])
def test_whole_samples_give_the_python_paths_records_bit_for_bit(start, n, last_t):
    data = slcan_bytes(range(start, start + n), seed=start)
    assert len(data) == n * SLCAN_SAMPLE_BYTES
    want = python_path(data, start & 0xFFFF, last_t)
    k, got, _ = c_path(data, start & 0xFFFF, last_t)
    assert k == n == want.shape[0]
    assert want["flags"].max() == 0 and np.all(np.diff(want["seq"]) == 1)
    assert got.tobytes() == want.tobytes()


def test_lower_case_hex_reads_as_python_can_reads_it():
    data = slcan_bytes(range(40, 43), seed=3).replace(b"t", b"\x00").lower().replace(b"\x00", b"t")
    k, got, _ = c_path(data, 40, 0.0)
    assert k == 3 and got.tobytes() == python_path(data, 40, 0.0).tobytes()


def lines_of(data: bytes) -> list[bytes]:
    return [x + b"\r" for x in data.split(b"\r")[:-1]]


def refused_cases() -> dict[str, tuple[bytes, int]]:
    good = slcan_bytes(range(500, 503), seed=9)
    ls = lines_of(good)
    timing_short = ls[0][:4] + b"7" + ls[0][5:-3] + b"\r"  # TIMING with a dlc of 7
    chip_long = ls[1][:4] + b"8" + ls[1][5:-1] + b"00\r"  # CHIP_A with a dlc of 8
    bad_lo = bytearray(ls[6])
    bad_lo[5:7] = b"FF"  # a CHIP_B of another sample
    return {
        "a gap": (good, 499),
        "a seq ahead": (good, 501),
        "a TIMING of the wrong dlc": (b"".join([timing_short] + ls[1:]), 500),
        "a CHIP_A of the wrong dlc": (b"".join(ls[:1] + [chip_long] + ls[2:]), 500),
        "a dlc digit off, the line's length right": (b"".join([ls[0][:4] + b"7" + ls[0][5:]] + ls[1:]), 500),
        "a CHIP_B of another sample": (b"".join(ls[:6] + [bytes(bad_lo)] + ls[7:]), 500),
        "frames out of order": (b"".join([ls[1], ls[0]] + ls[2:]), 500),
        "a frame of another id": (good.replace(b"t2A3", b"t2A7", 1), 500),
        "an extended frame": (good.replace(b"t2A0", b"T000002A0", 1)[:-9] + b"\r", 500),
        "a remote frame": (good.replace(b"t2A1", b"r2A1", 1), 500),
        "a BELL": (good[:-1] + b"\a", 500),
        "a garbled digit": (good.replace(b"t2A2", b"t2G2", 1), 500),
        "a partial sample": (good[:-SLCAN_SAMPLE_BYTES + 20], 500),
        "a partial line": (good[:-3], 500),
        "an empty line first": (b"\r" + good[:-1], 500),
        "nothing": (b"", 500),
    }


@pytest.mark.parametrize("case", sorted(refused_cases()))
def test_anything_but_whole_continuing_samples_is_refused_whole(case):
    data, expect = refused_cases()[case]
    k, _, buf = c_path(data, expect, 0.0)
    assert k == 0, case
    assert np.all(buf.view(np.uint8) == 0xA5), case  # nothing written


def test_more_samples_than_rows_are_refused():
    data = slcan_bytes(range(10, 15))
    assert c_path(data, 10, 0.0, cap=5)[0] == 5
    k, _, buf = c_path(data, 10, 0.0, cap=4)
    assert k == 0 and np.all(buf.view(np.uint8) == 0xA5)


def test_fuzzed_bytes_are_taken_whole_as_python_reads_them_or_refused_never_out_of_bounds():
    rng = np.random.default_rng(14)
    good = slcan_bytes(range(65534, 65540), seed=1)
    alphabet = np.frombuffer(b"0123456789ABCDEFabcdeftTrR\r\a xZ", np.uint8)
    taken = 0
    for trial in range(3000):
        data = bytearray(good[: rng.integers(0, len(good) + 1)] if trial % 3 == 0 else good)
        for _ in range(rng.integers(0, 4)):
            if data:
                data[rng.integers(0, len(data))] = alphabet[rng.integers(0, alphabet.shape[0])]
        cap = int(rng.integers(1, 8))
        k, got, buf = c_path(bytes(data), 65534, 0.0, cap=cap)
        assert np.all(buf[cap:].view(np.uint8) == 0xA5)  # the guard record after the rows
        if k == 0:
            assert np.all(buf.view(np.uint8) == 0xA5)
            continue
        taken += 1
        assert k * SLCAN_SAMPLE_BYTES == len(data) and k <= cap
        assert got.tobytes() == python_path(bytes(data), 65534, 0.0).tobytes()
    assert 100 < taken < 3000


@pytest.mark.parametrize("args,err,text", [
    ((b"", BASE, 0, 0, TICK_HZ, 0.0, 0.0, np.zeros(3, np.uint8)), ValueError, "56-byte"),
    ((b"", 0x7FD, 0, 0, TICK_HZ, 0.0, 0.0, np.zeros(1, SAMPLE_DTYPE)), ValueError, "base_id"),
    ((b"", BASE, 0x10000, 0, TICK_HZ, 0.0, 0.0, np.zeros(1, SAMPLE_DTYPE)), ValueError, "16-bit"),
    (("t", BASE, 0, 0, TICK_HZ, 0.0, 0.0, np.zeros(1, SAMPLE_DTYPE)), TypeError, "bytes-like"),
    ((b"", BASE, 0, 0, TICK_HZ, 0.0, 0.0, bytes(56)), TypeError, "read-write"),
])
def test_bad_arguments_are_clear_errors(args, err, text):
    with pytest.raises(err, match=text):
        slcan_samples(*args)
