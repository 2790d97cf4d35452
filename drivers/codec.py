"""The logger's sample frame: one wire format shared by the serial link and the I2C FIFO.

Byte layout (docs/protocol.md has the worked example)::

    off len field
    0   2   sync          0xA5 0x5A
    2   1   length        payload length in bytes, always 24 for this layout
    3   2   seq           16-bit sample counter, little-endian, wraps
    5   4   tick          device timer tick (TICK_HZ), little-endian, wraps
    9   8   t1[4]         ADXL210 T1 high times ax, ay, az, ax2 [timer counts], u16 LE each
    17  4   t2[2]         ADXL210 periods T2 chip A, chip B [timer counts], u16 LE each
    21  2   gyro          ENC-03J conditioned output [ADC counts], u16 LE
    23  2   temp_raw      temperature sensor [12-bit ADC counts], u16 LE
    25  2   vsupply_raw   supply through a 1:3 divider [12-bit ADC counts], u16 LE
    27  2   crc           CRC-16/CCITT-FALSE over bytes 0..26, BIG-endian

The CRC is sent most significant byte first so that the CRC over a whole intact frame
is 0 (CCITT-FALSE has no reflection and no final XOR): the decoder checks one call of
``binascii.crc_hqx(frame, 0xFFFF) == 0`` per candidate frame.

Decoding is streaming and self-synchronising: every sync position is a candidate, a
candidate that fails (wrong length, bad CRC) costs only itself, and the search resumes at
the next byte, so garbage, bit errors and truncated frames never hide the next good frame.
"""
from __future__ import annotations

import binascii
from dataclasses import dataclass, field, fields

import numpy as np

from ..core.samples import FLAG_GAP_BEFORE, SAMPLE_DTYPE
from .sequence import MAX_U16, SeqUnwrapper  # SeqUnwrapper: part of the codec's interface

SYNC = b"\xa5\x5a"
PAYLOAD_LEN = 24
FRAME_LEN = len(SYNC) + 1 + PAYLOAD_LEN + 2  # 29 bytes

TICK_HZ = 1_000_000
"""Nominal device tick rate [Hz] (1 µs ticks; the 32-bit counter wraps every 71.6 min)."""

# Housekeeping ADC: 12 bits against a 2.500 V reference.
ADC_BITS = 12
ADC_VREF_V = 2.5
ADC_FULL_SCALE = (1 << ADC_BITS) - 1  # 4095, the largest valid code
ADC_MISSING = 0xFFFF
"""Raw code meaning "not measured"; decodes to NaN. Codes 4096..65534 are reserved (NaN too)."""
TEMP_OFFSET_V = 0.500  # TMP36-style sensor: V = 0.500 V + 10 mV/°C * T
TEMP_SLOPE_V_PER_C = 0.010
VSUPPLY_DIVIDER = 3.0  # supply reaches the ADC through a 20k/10k divider

WIRE_DTYPE = np.dtype(
    [
        ("sync", ">u2"),
        ("length", "u1"),
        ("seq", "<u2"),
        ("tick", "<u4"),
        ("t1", "<u2", (4,)),
        ("t2", "<u2", (2,)),
        ("gyro", "<u2"),
        ("temp_raw", "<u2"),
        ("vsupply_raw", "<u2"),
        ("crc", ">u2"),
    ]
)
assert WIRE_DTYPE.itemsize == FRAME_LEN

_SYNC_WORD = int.from_bytes(SYNC, "big")


def crc16(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no xorout); check value 0x29B1."""
    return binascii.crc_hqx(data, 0xFFFF)


# ---------------------------------------------------------------- housekeeping conversions
def _adc_volts(raw: np.ndarray) -> np.ndarray:
    raw = np.asarray(raw)
    v = raw.astype(np.float64) * (ADC_VREF_V / (1 << ADC_BITS))
    return np.where(raw > ADC_FULL_SCALE, np.nan, v)


def _adc_code(volts: np.ndarray) -> np.ndarray:
    volts = np.asarray(volts, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        code = np.clip(np.rint(volts * ((1 << ADC_BITS) / ADC_VREF_V)), 0, ADC_FULL_SCALE)
    return np.where(np.isfinite(volts), code, ADC_MISSING).astype(np.uint16)


def temp_from_raw(raw: np.ndarray) -> np.ndarray:
    """Temperature [°C] from 12-bit ADC codes: T = (code·2.5 V/4096 − 0.5 V) / 10 mV/°C."""
    return (_adc_volts(raw) - TEMP_OFFSET_V) / TEMP_SLOPE_V_PER_C


def temp_to_raw(temp_c: np.ndarray) -> np.ndarray:
    """ADC codes for temperatures [°C]; saturates at 0 / 4095 like the ADC, NaN -> ADC_MISSING."""
    return _adc_code(TEMP_OFFSET_V + TEMP_SLOPE_V_PER_C * np.asarray(temp_c, dtype=np.float64))


def vsupply_from_raw(raw: np.ndarray) -> np.ndarray:
    """Supply voltage [V] from 12-bit ADC codes: V = code·2.5 V/4096 · 3 (1:3 divider)."""
    return _adc_volts(raw) * VSUPPLY_DIVIDER


def vsupply_to_raw(volts: np.ndarray) -> np.ndarray:
    """ADC codes for supply voltages [V]; saturates at 0 / 4095, NaN -> ADC_MISSING."""
    return _adc_code(np.asarray(volts, dtype=np.float64) / VSUPPLY_DIVIDER)


# ---------------------------------------------------------------- encoding
def _check_u16(name: str, values: np.ndarray) -> np.ndarray:
    values = np.asarray(values)
    if values.size and (values.min() < 0 or values.max() > MAX_U16):
        raise ValueError(
            f"{name} = {int(values.max())} counts does not fit the 16-bit wire field "
            f"(0..{MAX_U16}); the logger's timer/ADC cannot produce it"
        )
    return values.astype(np.uint16)


def to_wire(samples: np.ndarray) -> np.ndarray:
    """Wire records (WIRE_DTYPE, CRC filled) for a SAMPLE_DTYPE block.

    ``seq`` is sent modulo 2**16; temp/vsupply are quantised by the ADC conversion above.
    Raises ValueError if a timer count does not fit 16 bits.
    """
    samples = np.asarray(samples)
    if samples.dtype != SAMPLE_DTYPE:
        raise TypeError(f"expected SAMPLE_DTYPE samples, got {samples.dtype}")
    rec = np.zeros(samples.shape[0], dtype=WIRE_DTYPE)
    rec["sync"] = _SYNC_WORD
    rec["length"] = PAYLOAD_LEN
    rec["seq"] = (samples["seq"] & MAX_U16).astype(np.uint16)
    rec["tick"] = samples["tick"]
    rec["t1"] = _check_u16("T1", samples["t1"])
    rec["t2"] = _check_u16("T2", samples["t2"])
    rec["gyro"] = samples["gyro"]
    rec["temp_raw"] = temp_to_raw(samples["temp"])
    rec["vsupply_raw"] = vsupply_to_raw(samples["vsupply"])
    raw = rec.view(np.uint8).reshape(-1, FRAME_LEN)
    mv = memoryview(raw.reshape(-1))
    crc = [binascii.crc_hqx(mv[i : i + FRAME_LEN - 2], 0xFFFF) for i in range(0, len(mv), FRAME_LEN)]
    rec["crc"] = crc
    return rec


def encode_frames(samples: np.ndarray) -> bytes:
    """The byte stream for a SAMPLE_DTYPE block: FRAME_LEN bytes per sample."""
    return to_wire(samples).tobytes()


def wire_to_samples(rec: np.ndarray) -> np.ndarray:
    """SAMPLE_DTYPE block from wire records: seq is the raw 16-bit counter, t is NaN, flags 0."""
    out = np.zeros(rec.shape[0], dtype=SAMPLE_DTYPE)
    out["t"] = np.nan
    out["seq"] = rec["seq"]
    out["tick"] = rec["tick"]
    out["t1"] = rec["t1"]
    out["t2"] = rec["t2"]
    out["gyro"] = rec["gyro"]
    out["temp"] = temp_from_raw(rec["temp_raw"])
    out["vsupply"] = vsupply_from_raw(rec["vsupply_raw"])
    return out


def wire_roundtrip(samples: np.ndarray) -> np.ndarray:
    """What a receiver gets for ``samples`` (quantised temp/vsupply), keeping seq/t/flags.

    The emulator records this as "what was sent" so tests compare exact values.
    """
    out = wire_to_samples(to_wire(samples))
    out["seq"] = samples["seq"]
    out["t"] = samples["t"]
    out["flags"] = samples["flags"]
    return out


# ---------------------------------------------------------------- scanning
@dataclass
class ScanResult:
    """Where intact frames start in a buffer and what was rejected on the way."""

    starts: list[int]  # byte offsets of intact frames, increasing, non-overlapping
    keep_from: int  # bytes before this offset are consumed; the rest may hold a partial frame
    crc_errors: int
    length_errors: int


def scan(buf: bytes, *, final: bool = False) -> ScanResult:
    """Find the intact frames in ``buf``.

    Candidates are sync positions (``bytes.find``, C speed); each is accepted if its length
    byte is PAYLOAD_LEN and its CRC checks; after a rejection the search continues at the next
    byte, so a damaged or truncated frame never swallows the good frame after it. Unless
    ``final``, the last FRAME_LEN-1 bytes not inside an accepted frame are kept for later.
    """
    buf = bytes(buf)
    n = len(buf)
    mv = memoryview(buf)
    crc = binascii.crc_hqx
    good: list[int] = []
    pos = 0  # first byte not inside an accepted frame
    crc_errors = length_errors = 0
    p = buf.find(SYNC)
    last = n - FRAME_LEN
    while 0 <= p <= last:
        if buf[p + 2] != PAYLOAD_LEN:
            length_errors += 1
        elif crc(mv[p : p + FRAME_LEN], 0xFFFF) == 0:
            good.append(p)
            pos = p + FRAME_LEN
            p = buf.find(SYNC, pos)
            continue
        else:
            crc_errors += 1
        p = buf.find(SYNC, p + 1)
    keep_from = n if final else max(pos, n - (FRAME_LEN - 1))
    return ScanResult(good, keep_from, crc_errors, length_errors)


def gather(buf: bytes, starts: list[int]) -> np.ndarray:
    """WIRE_DTYPE records of the frames starting at ``starts`` (zero-copy when contiguous)."""
    k = len(starts)
    if k == 0:
        return np.zeros(0, dtype=WIRE_DTYPE)
    if starts[-1] - starts[0] == (k - 1) * FRAME_LEN:
        return np.frombuffer(buf, dtype=WIRE_DTYPE, count=k, offset=starts[0])
    mv = memoryview(buf)
    return np.frombuffer(b"".join([mv[p : p + FRAME_LEN] for p in starts]), dtype=WIRE_DTYPE)


def decode_frames(buf: bytes | bytearray | memoryview) -> np.ndarray:
    """Stateless: all intact frames in ``buf`` as SAMPLE_DTYPE (seq = raw 16-bit counter)."""
    return wire_to_samples(gather(buf, scan(buf, final=True).starts))


# ---------------------------------------------------------------- streaming decoder
@dataclass
class DecoderStats:
    frames: int = 0  # intact frames decoded
    crc_errors: int = 0  # candidates with a sync and the right length but a bad CRC
    length_errors: int = 0  # candidates with a sync but an impossible length byte
    bytes_skipped: int = 0  # bytes not inside any intact frame (garbage, damaged frames)
    gaps: int = 0
    missing: int = 0
    duplicates: int = 0
    strays: int = 0  # out-of-sequence frames dropped (SeqUnwrapper)
    strays_delivered: int = 0  # of which already delivered (the last frame of a read)

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass
class FrameDecoder:
    """Streaming decoder: bytes in, SAMPLE_DTYPE samples out (t = NaN; the driver stamps it).

    Keeps at most FRAME_LEN-1 bytes between calls. Sets FLAG_GAP_BEFORE after sequence gaps.
    """

    unwrapper: SeqUnwrapper = field(default_factory=SeqUnwrapper)
    _stats: DecoderStats = field(default_factory=DecoderStats)
    tail: bytes = b""  # the start of a frame not complete yet

    def feed(self, data: bytes | bytearray | memoryview) -> np.ndarray:
        buf = self.tail + bytes(data) if self.tail else bytes(data)
        res = scan(buf)
        st = self._stats
        st.crc_errors += res.crc_errors
        st.length_errors += res.length_errors
        ngood = len(res.starts)
        st.bytes_skipped += res.keep_from - ngood * FRAME_LEN
        self.tail = buf[res.keep_from :]
        if ngood == 0:
            return np.zeros(0, dtype=SAMPLE_DTYPE)
        samples = wire_to_samples(gather(buf, res.starts))
        keep, seq, gap = self.unwrapper.unwrap(samples["seq"], samples["tick"])
        samples = samples[keep]
        samples["seq"] = seq
        samples["flags"][gap] |= FLAG_GAP_BEFORE
        st.frames += samples.shape[0]
        return samples

    def count_frames(self, n: int) -> None:
        """``n`` intact frames were decoded outside (the daemon's C step, drivers/serial.py fast_entry)."""
        self._stats.frames += n

    def discard_partial(self) -> None:
        """Forget a partial frame (after a reconnect the bytes that follow are unrelated)."""
        self._stats.bytes_skipped += len(self.tail)
        self.tail = b""

    def stats(self) -> dict[str, int]:
        st = self._stats
        u = self.unwrapper
        st.gaps, st.missing, st.duplicates, st.strays, st.strays_delivered = (
            u.gaps, u.missing, u.duplicates, u.strays, u.strays_delivered)
        return {**st.as_dict(), "restarts": u.restarts}
