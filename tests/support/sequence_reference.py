"""The Python reference of the one-frame continuation check (drivers/_framekernel.c ``continuing`` and
``slcan_continuing``, and its per-frame row writers), the oracle its tests compare to: a frame that continues the
unwrapper's head while rule 2 alone decides it (nothing pending, no outage, no expectation), decided in Python
ints as SeqUnwrapper.unwrap decides it, then written as one SAMPLE_DTYPE row by the kernel's writer. The C step
takes frames by exactly this rule with a step of 1; the tests check the rule against the block path."""
from __future__ import annotations

import numpy as np

from gravcal.core.samples import FLAG_GAP_BEFORE, FLAG_PARTIAL, SAMPLE_DTYPE
from gravcal.drivers._framekernel import frame_header, frame_to_row, sample_to_row
from gravcal.drivers.can import _ALL
from gravcal.drivers.codec import FrameDecoder
from gravcal.drivers.sequence import MAX_U16, SeqUnwrapper


def continue_one(u: SeqUnwrapper, raw: int, tick: int | None) -> tuple[int, bool] | None:
    """(unwrapped seq, gap before) of one frame that continues ``u``'s head by 1..J (rule 2), applied to ``u``
    as :meth:`SeqUnwrapper.unwrap` applies it; None: not that case (nothing done)."""
    if u._pending or u._head is None or u._after_outage or u._expected is not None:
        return None
    step = (raw - u._head) & MAX_U16
    if not 1 <= step <= u.STRAY_JUMP_MIN:
        return None
    if step > 1:
        u.gaps += 1
        u.missing += step - 1
        u._fallback, u._jumped = u._head, [[-1, step - 1]]
    else:
        u._fallback, u._jumped = None, []
    u._head = u.last = u._head + step
    if tick is not None:
        if step == 1:
            u._learn_step(u._tick_last, tick, 1)
        u._tick_last = tick
    return u._head + u.offset, step > 1


class OneFrameUnwrapper(SeqUnwrapper):
    """A SeqUnwrapper that decides a one-frame read by :func:`continue_one` when it can."""

    def unwrap(self, seq_raw, ticks=None):
        if len(seq_raw) == 1:
            one = continue_one(self, int(seq_raw[0]), None if ticks is None else int(ticks[0]))
            if one is not None:
                return np.ones(1, bool), np.array([one[0]], np.int64), np.array([one[1]])
        return super().unwrap(seq_raw, ticks)


def decode_one(dec: FrameDecoder, frame: bytes) -> np.ndarray | None:
    """A read of exactly one intact frame that continues the stream, as one row (frame_to_row); None: anything
    else (nothing done: FrameDecoder.feed decides)."""
    if dec.tail or len(frame) != 29:
        return None
    head = frame_header(frame)
    one = None if head is None else continue_one(dec.unwrapper, *head)
    if one is None:
        return None
    row = np.empty(1, dtype=SAMPLE_DTYPE)
    frame_to_row(frame, row, one[0], FLAG_GAP_BEFORE if one[1] else 0)
    dec.count_frames(1)
    return row


def record_to_sample(record: tuple, unwrapper: SeqUnwrapper) -> np.ndarray | None:
    """One CAN record (seq, tick, gyro, t1[4], t2[2], temp_raw, vsupply_raw, present) that continues the stream,
    as one row (sample_to_row); None: not that case (nothing done: records_to_samples decides)."""
    seq, tick, gyro, t1, t2, temp_raw, vsupply_raw, present = record
    one = continue_one(unwrapper, seq, tick)
    if one is None:
        return None
    flags = (FLAG_PARTIAL if present != _ALL else 0) | (FLAG_GAP_BEFORE if one[1] else 0)
    row = np.empty(1, dtype=SAMPLE_DTYPE)
    sample_to_row(row, one[0], tick, gyro, t1, t2, temp_raw, vsupply_raw, flags)
    return row
