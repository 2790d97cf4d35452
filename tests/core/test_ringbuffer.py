"""Ring buffer: FIFO order, overwrite-oldest accounting, never grows."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from gravcal.core.ringbuffer import RingBuffer
from gravcal.core.samples import SAMPLE_DTYPE, empty


def _block(start, n):
    b = empty(n)
    b["seq"] = np.arange(start, start + n)
    return b


def test_fifo_order_across_wrap():
    rb = RingBuffer(8)
    rb.push(_block(0, 5))
    assert rb.pop(3)["seq"].tolist() == [0, 1, 2]
    rb.push(_block(5, 5))  # wraps around the end of storage
    assert len(rb) == 7
    assert rb.pop()["seq"].tolist() == [3, 4, 5, 6, 7, 8, 9]
    assert rb.overwritten == 0


def test_overwrite_oldest_counts_lost_rows():
    rb = RingBuffer(10)
    assert rb.push(_block(0, 7)) == 0
    assert rb.push(_block(7, 6)) == 3  # 13 rows into 10 slots: the 3 oldest go
    assert rb.overwritten == 3
    assert rb.pop()["seq"].tolist() == list(range(3, 13))


def test_block_larger_than_capacity_keeps_newest():
    rb = RingBuffer(4)
    rb.push(_block(0, 2))
    lost = rb.push(_block(2, 9))
    assert lost == 2 + 9 - 4
    assert rb.pop()["seq"].tolist() == [7, 8, 9, 10]


def test_never_grows_and_rejects_wrong_dtype():
    rb = RingBuffer(16)
    storage = rb._data
    for i in range(50):
        rb.push(_block(i * 7, 7))
    assert rb._data is storage and rb._data.shape == (16,)
    with pytest.raises(TypeError, match="ring buffer holds"):
        rb.push(np.zeros(3))
    with pytest.raises(ValueError, match="capacity must be positive"):
        RingBuffer(0)


def test_latest_and_peek_do_not_consume():
    rb = RingBuffer(5)
    rb.push(_block(0, 8))
    assert rb.latest(2)["seq"].tolist() == [6, 7]
    assert rb.peek(2)["seq"].tolist() == [3, 4]
    assert len(rb) == 5


@settings(max_examples=200, deadline=None)
@given(cap=st.integers(1, 40), ops=st.lists(st.tuples(st.booleans(), st.integers(0, 60)), max_size=40))
def test_matches_reference_deque(cap, ops):
    """Against a plain-list model: same rows out, same overwrite count, pushed = popped + size + lost."""
    rb, ref, nxt, lost = RingBuffer(cap), [], 0, 0
    for is_push, k in ops:
        if is_push:
            rb.push(_block(nxt, k))
            ref.extend(range(nxt, nxt + k))
            nxt += k
            over = max(0, len(ref) - cap)
            lost += over
            del ref[:over]
        else:
            out = rb.pop(k)["seq"].tolist()
            assert out == ref[:k]
            del ref[:k]
    assert rb.overwritten == lost
    assert rb.pushed == rb.popped + len(rb) + rb.overwritten
    assert rb.peek()["seq"].tolist() == ref
    assert rb.dtype == SAMPLE_DTYPE
