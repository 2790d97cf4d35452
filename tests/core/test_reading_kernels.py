"""The reading kernels' record forms against their any-layout forms and numpy, bit for bit.

scan_chunk (core/_scankernel.c) and block_pass (core/_blockkernels.c) read a structured record's
fields in place. Where t (float64) and the channels share one stride they take faster loops
(the scan: t directly followed by three float32 channels; the block pass: any one stride, two
blocks at a time). Given copies of the same columns (each its own stride) they take the loops
for any layout. Both must give the same bits, on rows built to break them: NaN and infinities
in every column, -0.0 beside 0.0 at the extremes, runs of repeated rows at and across the chunk's
ends, time steps that are zero, negative or NaN, t so large that its high half is a float32 NaN,
odd block counts and strides, float32 and float64 channels. The numpy oracles here write each
operation out in the kernels' order (per block, sums over the samples in sequence): they are the
kernels' numpy references in the package (core/_scankernel_reference.py, core/_blockkernels_reference.py).
"""
from __future__ import annotations

import numpy as np
import pytest

from gravcal.core._blockkernels import block_pass
from gravcal.core._scankernel import scan_chunk
from gravcal.core import _blockkernels_reference as block_reference
from gravcal.core import _scankernel_reference as scan_reference
from gravcal.core.repeats import chunk_runs, repeated_steps

CH = ("ax", "ay", "az")


def _records(n: int, dtype, seed: int, extra: int = 0, step: float = 0.01) -> np.ndarray:
    """t then the three channels (then ``extra`` float32 fields: a longer stride), quantised
    channels (frequent exact repeats and ties at the extremes)."""
    fields = [("t", "<f8")] + [(c, dtype) for c in CH] + [(f"pad{i}", "<f4") for i in range(extra)]
    rec = np.zeros(n, dtype=fields)
    rng = np.random.default_rng(seed)
    rec["t"] = 1.7e9 + step * np.arange(n)
    for c in CH:
        rec[c] = rng.integers(-3, 4, n) * 0.25
    return rec


def _spoil(rec: np.ndarray, seed: int, kind: str) -> None:
    """Adversarial rows of one kind, placed at random and at both ends."""
    rng = np.random.default_rng(seed)
    n = rec.shape[0]
    at = np.concatenate([[0, n - 1], rng.integers(0, n, 6)])
    if kind == "repeats":  # runs of every length, at the start, the end and inside
        for a in rng.integers(0, n - 30, 12):
            rec[a:a + rng.integers(2, 30)][list(CH)] = rec[a][list(CH)]
        rec[:14][list(CH)] = rec[0][list(CH)]
        rec[-12:][list(CH)] = rec[-12][list(CH)]
    elif kind == "zeros":  # -0.0 and 0.0 tie at the minimum of non-negative channels
        for c in CH:
            rec[c] = np.abs(rec[c])
            rec[c][rng.integers(0, n, 20)] = -0.0
            rec[c][rng.integers(0, n, 20)] = 0.0
        rec["ax"][0] = -0.0
        rec["ay"][0] = 0.0
    elif kind in ("nan", "inf", "-inf"):
        bad = {"nan": np.nan, "inf": np.inf, "-inf": -np.inf}[kind]
        for i in at:
            rec[CH[rng.integers(0, 3)]][i] = bad
    elif kind == "t":  # steps of zero and below, a NaN and an infinite time, -0.0 after 0.0
        rec["t"][at[2]] = rec["t"][at[2] - 1]
        rec["t"][at[3]:] -= 5.0
        rec["t"][at[4]] = np.nan
        rec["t"][at[5]] = np.inf
    elif kind == "t_zero":
        rec["t"] = 0.0
        rec["t"][1::2] = -0.0
    elif kind == "t_huge":  # finite times whose high half reads as a float32 NaN or infinity
        rec["t"] = np.linspace(1e307, 1.7e308, n)


def _fresh() -> np.ndarray:
    return np.array([np.inf] * 3 + [-np.inf] * 3 + [0.0] * 6 + [np.inf, 1.0])


def _scan(t, xs, prev, state, min_run, kernel=scan_chunk):
    runs = np.empty((t.shape[0] // min_run + 2, 2), np.int64)
    n_runs, n_rep = kernel(t, *xs, prev, state, runs, min_run)
    return state, n_runs, n_rep, runs[:n_runs].copy()


def _scan_oracle(t, x, prev, state, min_run):
    """scan_chunk's state, runs and count by its numpy reference (core/_scankernel_reference.py)."""
    return _scan(t, [x[:, 0], x[:, 1], x[:, 2]], prev, state.copy(), min_run, scan_reference.scan_chunk)


def _same_scan(a, b) -> None:
    assert a[0].tobytes() == b[0].tobytes(), (a[0], b[0])  # every bit: -0.0 is not 0.0 here
    assert a[1:3] == b[1:3]
    np.testing.assert_array_equal(a[3], b[3])


KINDS = ["plain", "repeats", "zeros", "nan", "inf", "-inf", "t", "t_zero", "t_huge"]


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("extra, order", [(0, 1), (1, 1), (2, 1), (0, -1), (1, -3)])
@pytest.mark.parametrize("with_prev", [False, True])
def test_scan_record_form_equals_the_any_layout_form_and_numpy(kind, extra, order, with_prev):
    rec = _records(3001, "<f4", seed=len(kind) + extra, extra=extra)
    _spoil(rec, seed=extra + 7, kind=kind)
    rec = rec[::order]  # strides of 20, 24, 28 bytes, backwards and every third row
    t, xs = rec["t"], [rec[c] for c in CH]
    prev = np.array([t[0] - 0.01, *(x[0] for x in xs)], dtype=np.float64) if with_prev else None
    for min_run in (1, 10):
        for state in (_fresh(), _scan(t[:500], xs and [x[:500] for x in xs], None, _fresh(), 1)[0]):
            record = _scan(t, xs, prev, state.copy(), min_run)  # the fields in place
            copies = _scan(t.copy(), [x.copy() for x in xs], prev, state.copy(), min_run)  # each its own stride
            _same_scan(record, copies)
            _same_scan(record, _scan_oracle(t, np.column_stack(xs), prev, state, min_run))


@pytest.mark.parametrize("kind", ["plain", "repeats", "zeros", "nan", "t"])
def test_scan_of_float64_records_equals_numpy(kind):
    rec = _records(2000, "<f8", seed=3)
    _spoil(rec, seed=4, kind=kind)
    t, xs = rec["t"], [rec[c] for c in CH]
    _same_scan(_scan(t, xs, None, _fresh(), 10), _scan_oracle(t, np.column_stack(xs), None, _fresh(), 10))


def test_scan_runs_join_across_chunk_borders_as_in_one_piece():
    rec = _records(4000, "<f4", seed=9)
    _spoil(rec, seed=2, kind="repeats")
    rec[990:1030][list(CH)] = rec[990][list(CH)]  # a run across the border at 1000
    rec[1999:2001][list(CH)] = rec[1999][list(CH)]  # a one-step run on the border at 2000
    t, xs = rec["t"], [rec[c] for c in CH]
    whole = _scan(t, xs, None, _fresh(), 10)
    st, n_rep, runs = _fresh(), 0, []
    for i in range(0, 4000, 1000):
        prev = None if i == 0 else np.array([t[i - 1], *(x[i - 1] for x in xs)])
        st, _, k, r = _scan(t[i:i + 1000], [x[i:i + 1000] for x in xs], prev, st, 10)
        n_rep += k
        runs += [(a + max(i - 1, 0), b) for a, b in r]  # chunk steps to the recording's (datapass)
    assert st.tobytes() == whole[0].tobytes() and n_rep == whole[2]
    # a run crossing a border is reported by both chunks at their ends: joined, it is the one-piece run
    joined: list[list[int]] = []
    for a, b in runs:
        if joined and joined[-1][0] + joined[-1][1] == a:
            joined[-1][1] += b
        else:
            joined.append([a, b])
    assert [tuple(r) for r in joined if r[1] >= 10] == [tuple(r) for r in whole[3] if r[1] >= 10]


# ---- block_pass ----------------------------------------------------------------------------------

def _blocks(xs, t, B, b0, nb, max_step, first):
    out = np.full((3, nb), 7.0), np.full((6, nb), 7.0, np.float32), np.empty((0, nb)), np.ones(nb, bool)
    block_pass(*xs, t if first else t, None, B, b0, max_step, *out)
    return out


def _block_oracle(x, t, B, max_step, first):
    """Block statistics by block_pass's numpy reference (core/_blockkernels_reference.py: every float64
    operation in the kernel's order)."""
    m = x.shape[0] // B
    out = np.empty((3, m)), np.empty((6, m), np.float32), np.empty((0, m)), np.empty(m, bool)
    block_reference.block_pass(x[:m * B, 0], x[:m * B, 1], x[:m * B, 2], t[:m * B + (0 if first else 1)], None, B, 0,
                               max_step, *out)
    return out[0], out[1], out[3]


@pytest.mark.parametrize("dtype", ["<f4", "<f8"])
@pytest.mark.parametrize("kind", ["plain", "nan", "inf", "t", "t_zero", "zeros"])
@pytest.mark.parametrize("B, m", [(10, 41), (10, 40), (1, 7), (3, 1), (7, 2)])
@pytest.mark.parametrize("extra, order", [(0, 1), (1, 1), (0, -1)])
def test_block_pass_paired_form_equals_one_block_form_and_numpy(dtype, kind, B, m, extra, order):
    L = B * m
    rec = _records(L + 1, dtype, seed=B + m, extra=extra)
    for c in CH:  # spread values, so that the sums round
        rec[c] = rec[c] * np.float64(1.1) + np.float64(0.3) * np.sin(np.arange(L + 1))
    _spoil(rec, seed=m, kind=kind)
    rec = rec[::order]
    nb, b0, max_step = m + 3, 2, 0.015
    for first in (False, True):  # t with the row before the chunk, or the recording's first row
        t = rec["t"][1:] if first else rec["t"]
        xs = [rec[c][1:] for c in CH]
        paired = _blocks(xs, t, B, b0, nb, max_step, first)  # one stride: two blocks a lane each
        single = _blocks([x.copy() for x in xs], t.copy(), B, b0, nb, max_step, first)  # any layout
        for a, b in zip(paired, single):
            assert a.tobytes() == b.tobytes()
        mean, scatter, usable = _block_oracle(np.column_stack(xs), t, B, max_step, first)
        sl = slice(b0, b0 + m)
        assert paired[0][:, sl].tobytes() == mean.tobytes()
        assert paired[1][:, sl].tobytes() == scatter.tobytes()
        np.testing.assert_array_equal(paired[3][sl], usable)
        assert (paired[0][:, :b0] == 7.0).all() and (paired[0][:, b0 + m:] == 7.0).all()  # nothing else written
        if kind == "plain":  # forwards every step is good; backwards every one is negative
            assert usable.all() if order > 0 else not usable[1:].any()


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("min_run", [1, 2, 10, 64])
@pytest.mark.parametrize("with_prev", [False, True])
def test_scan_runs_of_every_length_at_every_offset(seed, min_run, with_prev):
    """Runs from 1 step to several hundred, starting and ending anywhere (the record form finds runs
    64 rows at a time): its runs are the any-layout form's and chunk_runs' of numpy's repeats."""
    rng = np.random.default_rng(seed)
    n = 5000
    rec = _records(n + 1, "<f4", seed=seed)
    rec["ax"] = rng.integers(0, 2, n + 1)  # a repeat every other step at random
    rec["ay"] = rec["az"] = 1.0
    rec["ax"][1000:1500] = np.arange(500) % 2  # no repeat for 500 rows: whole words without one
    for a in rng.integers(1500, n - 300, 10):
        rec["ax"][a:a + rng.integers(60, 300)] = 5.0  # runs across one or more words
    t, xs = rec["t"][1:], [rec[c][1:] for c in CH]
    prev = np.array([rec["t"][0], *(rec[c][0] for c in CH)], dtype=np.float64) if with_prev else None
    record = _scan(t, xs, prev, _fresh(), min_run)
    _same_scan(record, _scan(t.copy(), [x.copy() for x in xs], prev, _fresh(), min_run))
    _same_scan(record, _scan_oracle(t, np.column_stack(xs), prev, _fresh(), min_run))
    assert record[1] >= 3 and record[3][:, 1].max() >= 60 and record[2] > n // 3


@pytest.mark.parametrize("head, tail", [(1, 1), (2, 1), (1, 2), (3, 3), (0, 1), (1, 0)])
@pytest.mark.parametrize("n", [8, 9, 64, 65, 66, 129, 1000])
@pytest.mark.parametrize("with_prev", [False, True])
def test_scan_keeps_short_runs_at_the_chunk_ends(head, tail, n, with_prev):
    """Runs of a few steps touching the chunk's first or last step are kept whatever min_run (they
    may join a neighbour's), including one-step runs and runs ending on a 64-row word border."""
    rec = _records(n + 1, "<f4", seed=n)
    rec["ax"] = np.arange(n + 1) % 2 + 10.0 * np.arange(n + 1)  # no repeat anywhere
    rec["ay"] = rec["az"] = 1.0
    first = 0 if with_prev else 1  # the row the chunk's first step ends on
    rec["ax"][first + 1:first + 1 + head] = rec["ax"][first]  # `head` repeated steps from the first
    if tail:
        rec["ax"][-tail - 1:] = rec["ax"][-tail - 1]  # `tail` repeated steps to the last
    t, xs = rec["t"][1:], [rec[c][1:] for c in CH]
    prev = np.array([rec["t"][0], *(rec[c][0] for c in CH)], dtype=np.float64) if with_prev else None
    record = _scan(t, xs, prev, _fresh(), 10)
    _same_scan(record, _scan(t.copy(), [x.copy() for x in xs], prev, _fresh(), 10))
    _same_scan(record, _scan_oracle(t, np.column_stack(xs), prev, _fresh(), 10))
    assert record[2] == head + tail and record[1] == (head > 0) + (tail > 0)
