"""The one-frame continuation rule (tests/support/sequence_reference.py, the rule the C step's frame kernel takes
frames by) decides every frame as SeqUnwrapper's block path does: same kept frames, unwrapped seq, gap flags and
counters, frame by frame."""
import numpy as np
import pytest

from gravcal.drivers.sequence import MAX_U16, SeqUnwrapper
from support.sequence_reference import OneFrameUnwrapper


def _stream(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Raw 16-bit seq and 32-bit ticks of a stream with losses, long jumps, duplicates, strays (some just ahead,
    which the unwrapper takes back when the stream continues behind them) and wraps."""
    seq, tick, s = [], [], int(rng.integers(0, 65536))
    for _ in range(n):
        r = rng.random()
        if r < 0.05:
            s += int(rng.integers(2, 60))  # a loss
        elif r < 0.06:
            s += int(rng.integers(100, 5000))  # a jump beyond the stray limit
        elif r < 0.08:
            seq.append(int(rng.integers(0, 65536)))  # a stray
            tick.append(int(rng.integers(0, 2**32)))
            continue
        elif r < 0.09:
            seq.append((s + int(rng.integers(2, 60))) & MAX_U16)  # a stray just ahead: looks like a small loss
            tick.append(int(rng.integers(0, 2**32)))
            continue
        elif r < 0.11 and seq:
            seq.append(seq[-1])  # a duplicate
            tick.append(tick[-1])
            continue
        else:
            s += 1
        seq.append(s & MAX_U16)
        tick.append((s * 5000) & 0xFFFFFFFF)
    return np.array(seq, np.uint16), np.array(tick, np.uint32)


def _run(seq, tick, one_path: bool, outages) -> tuple[list, dict]:
    u = OneFrameUnwrapper() if one_path else SeqUnwrapper()
    out = []
    for i in range(seq.shape[0]):
        if i in outages:
            u.expect_advance(outages[i])
        keep, s, gap = u.unwrap(seq[i:i + 1], tick[i:i + 1])
        out.append((keep.tolist(), s.tolist(), gap.tolist()))
    counters = {k: getattr(u, k) for k in ("last", "gaps", "missing", "duplicates", "strays", "strays_delivered",
                                            "restarts", "offset", "_head", "_tick_last")}
    return out, counters


@pytest.mark.parametrize("seed", range(8))
def test_one_frame_path_decides_as_the_block_path(seed):
    rng = np.random.default_rng(seed)
    seq, tick = _stream(rng, 3000)
    outages = {int(i): (None if rng.random() < 0.5 else float(rng.integers(1, 70000)))
               for i in rng.integers(1, 3000, 5)}
    fast, fast_counters = _run(seq, tick, True, outages)
    slow, slow_counters = _run(seq, tick, False, outages)
    assert fast == slow
    assert fast_counters == slow_counters
    assert slow_counters["gaps"] > 10 and slow_counters["strays"] > 10 and slow_counters["duplicates"] > 10
