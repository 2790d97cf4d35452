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
import math
from dataclasses import dataclass, field, fields

import numpy as np

from ..core.samples import FLAG_GAP_BEFORE, SAMPLE_DTYPE

SYNC = b"\xa5\x5a"
PAYLOAD_LEN = 24
FRAME_LEN = len(SYNC) + 1 + PAYLOAD_LEN + 2  # 29 bytes
MAX_U16 = 0xFFFF

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


def _volts(code: int) -> float:
    """_adc_volts for one code, the same float64 operations in Python."""
    return code * (ADC_VREF_V / (1 << ADC_BITS)) if code <= ADC_FULL_SCALE else math.nan


def wire_to_samples(rec: np.ndarray) -> np.ndarray:
    """SAMPLE_DTYPE block from wire records: seq is the raw 16-bit counter, t is NaN, flags 0."""
    if rec.shape[0] == 1:  # one frame per wake-up is the common case: one record assignment, no array passes
        _, _, seq, tick, t1, t2, gyro, temp_raw, vsupply_raw, _ = rec[0].item()
        out = np.zeros(1, dtype=SAMPLE_DTYPE)
        out[0] = (math.nan, seq, tick, t1, t2, gyro, (_volts(temp_raw) - TEMP_OFFSET_V) / TEMP_SLOPE_V_PER_C,
                  _volts(vsupply_raw) * VSUPPLY_DIVIDER, 0)
        return out
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


# ---------------------------------------------------------------- sequence numbers
class _Pending:
    """A frame, or a run of frames, the stream has not confirmed yet (SeqUnwrapper rule 4)."""

    AHEAD, RETAKE, HELD = "ahead", "retake", "held"
    __slots__ = ("kind", "value", "run", "delivered")

    def __init__(self, kind: str, value: int) -> None:
        self.kind = kind
        self.value = value  # unwrapped value of its newest frame (raw seq = value mod 2**16)
        self.run = 1  # frames so far
        self.delivered: list[list[int]] = []  # [block index (-1: an earlier block), samples counted missing]


class SeqUnwrapper:
    """Unwraps the device's 16-bit counter to int64, finds gaps and drops stray frames.

    A step of d = (seq - previous) mod 2**16 means d-1 samples are missing. A *stray* is a
    CRC-valid frame that is not the next part of the stream (an old frame repeated by a
    buffering adapter, a frame spliced from elsewhere, the rare garbage that passes the CRC);
    it must be dropped without shifting later sequence numbers by 2**16. The *head* is the
    last frame believed; with J = STRAY_JUMP_MIN and R = STRAY_RESYNC_RUN each frame is:

    1. a duplicate (d = 0 from the head or from a pending frame): dropped;
    2. the next part of the stream (1 <= d <= J from the head): believed at once, every
       pending frame was a stray;
    3. the continuation of a pending run: ahead of the head by at most J, behind it by exactly
       1 (in a row). The run is believed once it is long enough: 2 frames ahead of the head
       (a long loss), R behind it (see 4); the other pending frames were strays;
    4. otherwise a new pending run:
       - *ahead*: more than J ahead of the head (or at start-up, when nothing is known),
         delivered at once (the last frame of a read can only be judged by the next read);
       - *retake*: in the hole of the head's latest jump, continuing the head from before it
         (the jump was a stray, e.g. two that continued each other), delivered at once;
         believed after R in a row, which takes the jump back (its frames were strays);
       - *held*: anywhere else behind the head (an old frame), held back; R in a row are
         believed: the device restarted its counter (one gap of the samples since the restart,
         not of a 16-bit wrap; the output seq continues after them, ``restarts`` counts it).

    A stray found in the read it came with is removed from it; one delivered with an earlier
    read is counted in ``strays_delivered``. Unwrapped values start at the raw value of the
    first genuine frame. A forward step cannot be told from a wrap: after a long outage the
    caller passes the expected advance (from host time) to ``expect_advance``; the next frame
    is then believed, with the multiples of 2**16 that bring it nearest that advance.
    """

    STRAY_JUMP_MIN = 64  # J: a larger forward step is believed only with a continuation
    STRAY_RESYNC_RUN = 3  # R: frames in a row that outweigh a believed frame ahead of them
    MAX_PENDING = 8  # more open runs than this: the oldest is forgotten (as delivered or held)

    def __init__(self) -> None:
        self.last: int | None = None  # unwrapped value of the last frame delivered
        self._head: int | None = None  # unwrapped value of the last frame believed
        self._pending: list[_Pending] = []
        self._fallback: int | None = None  # the head before its latest jump (None: no jump since)
        self._jumped: list[list[int]] = []  # the frames that jump delivered, as _Pending.delivered
        self._expected: float | None = None
        self._keep: np.ndarray | None = None  # the block being unwrapped, frame by frame
        self._seq: np.ndarray | None = None
        self._gap: np.ndarray | None = None
        self.gaps = 0  # gap events
        self.missing = 0  # samples missing in those gaps
        self.duplicates = 0
        self.strays = 0  # frames dropped as strays, or found to be strays after delivery
        self.strays_delivered = 0  # of which already delivered with an earlier read
        self.restarts = 0  # the device's counter started again from 0 (its missed samples are in `missing`)
        self.offset = 0  # output seq - internal value: restarts keep the output continuous
        self._after_outage = False
        self._tick_period: float | None = None  # device ticks per sample
        self._tick_last: int | None = None

    def expect_advance(self, samples: float | None) -> None:
        """After an outage: about ``samples`` samples went by (None: unknown)."""
        self._expected = None if samples is None else float(samples)
        self._after_outage = True

    def unwrap(self, seq_raw: np.ndarray, ticks: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(keep mask, unwrapped seq of kept frames, gap-before flag of kept frames); ``ticks`` (the
        frames' device ticks) let a device restart behind an outage be told from a long loss."""
        s = np.asarray(seq_raw).astype(np.int64)
        if s.shape[0] == 0:
            return np.zeros(0, bool), np.zeros(0, np.int64), np.zeros(0, bool)
        t = None if ticks is None else np.asarray(ticks).astype(np.int64)
        hint, self._expected = self._expected, None
        after, self._after_outage = self._after_outage, False
        restarted = after and t is not None and self._restarted(int(s[0]), int(t[0]), hint)
        if restarted:
            self._rebase(int(s[0]))
        keep, seq, gap = self._unwrap(s, None if restarted else hint)
        if restarted and keep[0] and s[0] > 0:
            gap[0] = True
        if t is not None:
            self._learn_ticks(s, t, keep)
        return keep, seq, gap

    # -------------------------------------------------------- device restarts (sequence and tick from 0)
    def _learn_ticks(self, s: np.ndarray, t: np.ndarray, keep: np.ndarray) -> None:
        if s.shape[0] >= 2 and bool((((s[1:] - s[:-1]) & MAX_U16) == 1).all()):
            self._tick_period = ((int(t[-1]) - int(t[0])) & 0xFFFFFFFF) / (s.shape[0] - 1)
        kept = np.flatnonzero(keep)
        if kept.shape[0]:
            self._tick_last = int(t[kept[-1]])

    def _restarted(self, raw: int, tick: int, hint: float | None) -> bool:
        """The first frame after an outage is a restarted device's: its seq and tick both count from a
        recent boot, and its tick does not continue the stream's (by seq, and by the host's clock)."""
        tp, last_tick = self._tick_period, self._tick_last
        if self.last is None or not tp or last_tick is None:
            return False
        if abs(tick / tp - raw) > 2 + 0.01 * raw:  # not both counting from a boot
            return False
        advance = ((tick - last_tick) & 0xFFFFFFFF) / tp  # samples elapsed if the device ran on
        step = (raw - self.last) & MAX_U16
        k = max(0, round((advance - step) / 65536.0))
        if abs(advance - step - 65536 * k) > 2 + 1e-3 * advance:  # one crystal paces ticks and samples
            return True
        # ticks that continue by coincidence (a short session before and after): fewer samples than the
        # host saw go by between noticing the outage and reopening (which lies inside the true interval)
        return hint is not None and advance < 0.5 * hint - 50

    def _rebase(self, raw: int) -> None:
        """A restart: ``raw`` samples of the new session were missed; the output continues after them."""
        step = (raw - self.last) & MAX_U16 or 65536
        value = self.last + step  # the internal value of the frame (same residue mod 2**16)
        self.offset += self.last + 1 + raw - value
        self._head = self.last = value - 1  # the frame then continues the stream (rule 2)
        self._pending, self._fallback, self._jumped = [], None, []
        self.restarts += 1
        if raw > 0:
            self.gaps += 1
            self.missing += raw

    def _unwrap(self, s: np.ndarray, hint: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = s.shape[0]
        if hint is not None and self.last is None:
            hint = None  # nothing delivered yet: nothing to advance from
        # Fast path, the common case: no open question and a block that continues itself.
        if not self._pending and bool((((s[1:] - s[:-1]) & MAX_U16) == 1).all()):
            if self._head is None and n >= 2:  # a first read: rule 3 at start-up
                seq = int(s[0]) + np.arange(n, dtype=np.int64)
                self._head = self.last = int(seq[-1])
                return np.ones(n, bool), seq + self.offset, np.zeros(n, bool)
            if self._head is not None:
                step = (int(s[0]) - self._head) & MAX_U16
                if hint is not None:
                    step += 65536 * max(0, round((hint - step) / 65536.0))
                if 1 <= step <= self.STRAY_JUMP_MIN or (hint is not None and step >= 1):  # rule 2
                    seq = self._head + step + np.arange(n, dtype=np.int64)
                    gap = np.zeros(n, bool)
                    gap[0] = step > 1
                    self.gaps += int(gap[0])
                    self.missing += step - 1
                    jump = n == 1 and step > 1 and hint is None
                    self._fallback, self._jumped = (self._head, [[-1, step - 1]]) if jump else (None, [])
                    self._head = self.last = int(seq[-1])
                    return np.ones(n, bool), seq + self.offset, gap
        return self._unwrap_frames(s.tolist(), hint)

    # -------------------------------------------------------- frame by frame: the rules
    def _unwrap_frames(self, frames: list[int], hint: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = len(frames)
        self._keep, self._seq, self._gap = np.zeros(n, bool), np.zeros(n, np.int64), np.zeros(n, bool)
        start = 0
        if hint is not None:  # after an outage: believe the frame delivered last, then the hint
            self._head, self._pending, self._fallback, self._jumped = self.last, [], None, []
            step = (frames[0] - self.last) & MAX_U16
            step += 65536 * max(0, round((hint - step) / 65536.0))
            if step:  # (else a duplicate: rule 1)
                self._head += step
                self._deliver(0, self._head, step - 1)
                start = 1
        for i in range(start, n):
            self._frame(i, frames[i])
        for delivered in [p.delivered for p in self._pending] + [self._jumped]:
            for frame in delivered:
                frame[0] = -1  # delivered with an earlier read from now on
        keep, seq, gap = self._keep, self._seq, self._gap
        self._keep = self._seq = self._gap = None
        return keep, seq[keep], gap[keep]

    def _frame(self, i: int, x: int) -> None:
        J, R = self.STRAY_JUMP_MIN, self.STRAY_RESYNC_RUN
        head = self._head
        d = (x - head) & MAX_U16 if head is not None else 0
        if head is not None and d == 0:  # rule 1
            self.duplicates += 1
            return
        if head is not None and d <= J:  # rule 2
            self._drop_pending()
            self._fallback, self._jumped = (head, [[i, d - 1]]) if d > 1 else (None, [])
            self._believe(i, head + d, d - 1)
            return
        best, best_d = None, 0
        for p in self._pending:
            dp = (x - p.value) & MAX_U16
            if dp == 0:  # rule 1
                self.duplicates += 1
                return
            if (dp <= J if p.kind == _Pending.AHEAD else dp == 1) and (best is None or dp < best_d):
                best, best_d = p, dp
        if best is not None:  # rule 3
            p = best
            p.run += 1
            p.value += best_d
            if p.run < (2 if p.kind == _Pending.AHEAD else R):
                self._add(p, i, 0)
            else:
                self._confirm(p, i, best_d)
            return
        # rule 4
        fallback = self._fallback
        df = (x - fallback) & MAX_U16 if fallback is not None else 0
        if fallback is not None and 0 < df < head - fallback:
            p = _Pending(_Pending.RETAKE, fallback + df)
            self._add(p, i, df - 1)
        elif head is None or d < 0x8000:
            p = _Pending(_Pending.AHEAD, head + d if head is not None else x)
            # at start-up nothing is known before it: a discontinuity, no samples counted missing
            self._add(p, i, d - 1, gap=None if head is not None else self.last is not None)
        else:
            p = _Pending(_Pending.HELD, head + d)
            self.strays += 1
        self._pending.append(p)
        if len(self._pending) > self.MAX_PENDING:
            del self._pending[0]  # forgotten: it stays as delivered (or held back)

    def _add(self, p: _Pending, i: int, missing: int, gap: bool | None = None) -> None:
        """Frame ``i`` joins the pending run ``p``: delivered now, unless the run is held back."""
        if p.kind == _Pending.HELD:
            self.strays += 1  # (taken back if the run is believed)
            return
        p.delivered.append([i, missing])
        self._deliver(i, p.value, missing, gap)

    def _confirm(self, p: _Pending, i: int, d: int) -> None:
        """Rule 3: frame ``i`` (``d`` after the run's last frame) makes ``p`` believed."""
        head = self._head
        self._pending.remove(p)
        if p.kind == _Pending.RETAKE:  # the head's latest jump was a stray after all
            for at, missing in self._jumped:
                self._disown(at, missing)
            # the other frames delivered from the same hole may be the stream too: left as they are
            self._pending = [q for q in self._pending if q.kind != _Pending.RETAKE]
            self._drop_pending()
            self._fallback, self._jumped = None, []
            self._believe(i, p.value, d - 1)
        elif p.kind == _Pending.HELD:  # the counter restarted from 0: the held-back frames are in its gap
            self.strays -= p.run - 1
            self._drop_pending()
            self._fallback, self._jumped = None, []
            raw = p.value & MAX_U16  # samples since the restart not delivered (not a wrap's 2**16)
            self.offset += self.last + 1 + raw - p.value
            self.restarts += 1
            self._believe(i, p.value, raw)
        else:  # a long loss (or the start): can still be taken back while nothing follows it
            self._drop_pending()
            if head is not None:
                self._fallback, self._jumped = head, p.delivered + [[i, d - 1]]
            else:
                self._fallback, self._jumped = None, []
            self._believe(i, p.value, d - 1)

    # -------------------------------------------------------- bookkeeping
    def _believe(self, i: int, value: int, missing: int) -> None:
        self._head = value
        self._deliver(i, value, missing)

    def _deliver(self, i: int, value: int, missing: int, gap: bool | None = None) -> None:
        self._keep[i], self._seq[i] = True, value + self.offset
        self._gap[i] = missing > 0 if gap is None else gap
        if missing > 0:
            self.gaps += 1
            self.missing += missing
        self.last = value

    def _drop_pending(self) -> None:
        """Every pending run was a stray (a held-back one was counted when it came)."""
        for p in self._pending:
            for at, missing in p.delivered:
                self._disown(at, missing)
        self._pending = []

    def _disown(self, at: int, missing: int) -> None:
        """A delivered frame was a stray: removed from this block, or counted as delivered."""
        self.strays += 1
        if missing > 0:
            self.gaps -= 1
            self.missing -= missing
        if at >= 0:
            self._keep[at] = False
        else:
            self.strays_delivered += 1


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
