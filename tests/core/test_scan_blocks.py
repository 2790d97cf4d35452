"""scan_chunk with blocks (core/_scankernel.c): the validation scan and block_pass's statistics of
the same chunk in one call (on a structured record's rows, the blocks computed a group ahead of the
scan, whose rows are then still in the cache). Every output is the bits of the two calls made
separately: the scan's state, runs and count, and each block's mean, scatter, aux means and usable
flag; with and without the row before the chunk, odd block counts, rows after the last whole block,
NaN and repeated runs at the chunk's ends, any layout."""
from __future__ import annotations

import numpy as np
import pytest

from gravcal.core._blockkernels import block_pass
from gravcal.core._scankernel import scan_chunk

CH = ("ax", "ay", "az")


def _records(n: int, dtype: str, seed: int, extra: int = 0) -> np.ndarray:
    fields = [("t", "<f8")] + [(c, dtype) for c in CH] + [("temp", "<f8")] + [(f"pad{i}", "<f4") for i in range(extra)]
    rec = np.zeros(n, dtype=fields)
    rng = np.random.default_rng(seed)
    rec["t"] = 1.7e9 + np.cumsum(rng.uniform(0.0095, 0.0105, n))
    for c in CH:  # quantised (repeats, ties at the extremes), spread so that the sums round
        rec[c] = rng.integers(-3, 4, n) * 0.25 + np.float64(0.3) * np.sin(np.arange(n))
    rec["temp"] = 25.0 + rng.normal(0.0, 0.1, n)
    return rec


def _spoil(rec: np.ndarray, kind: str, seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = rec.shape[0]
    if kind == "repeats":  # runs at both ends, across block borders and inside
        rec[:23][list(CH)] = rec[0][list(CH)]
        tail = min(17, n // 2)
        rec[-tail:][list(CH)] = rec[-tail][list(CH)]
        for a in rng.integers(0, n - 70, 8) if n > 140 else ():
            rec[a:a + rng.integers(2, 70)][list(CH)] = rec[a][list(CH)]
    elif kind == "nan":  # in a channel at the first and last rows and inside, in temp inside
        rec["ax"][0], rec["az"][n - 1], rec["ay"][n // 2] = np.nan, np.nan, np.inf
        rec["temp"][n // 3] = np.nan
    elif kind == "t":  # a step of zero, one backwards, one too long, a NaN time
        rec["t"][n // 5] = rec["t"][n // 5 - 1]
        rec["t"][n // 2:] -= 3.0
        rec["t"][2 * n // 3:] += 0.5
        rec["t"][n - 2] = np.nan
    elif kind == "zeros":  # -0.0 and 0.0 at the extremes
        for c in CH:
            rec[c] = np.abs(rec[c])
            rec[c][rng.integers(0, n, 9)] = -0.0
            rec[c][rng.integers(0, n, 9)] = 0.0


def _fresh() -> np.ndarray:
    return np.array([np.inf] * 3 + [-np.inf] * 3 + [0.0] * 6 + [np.inf, 1.0])


def _outputs(nb: int, k: int):
    return np.full((3, nb), 7.0), np.full((6, nb), 7.0, np.float32), np.full((k, nb), 7.0), np.ones(nb, bool)


def _both(t, xs, aux, prev, B, b0, n_blocks, nb, max_step, min_run, t_before_chunk):
    """(fused call, separate calls): each the scan's (state, n_runs, n_repeats, runs) and the blocks."""
    k = 0 if aux is None else (1 if aux.ndim == 1 else aux.shape[1])
    out = []
    for fused in (True, False):
        st, runs, blk = _fresh(), np.zeros((t.shape[0] // min_run + 2, 2), np.int64), _outputs(nb, k)
        if fused:
            n_runs, n_rep = scan_chunk(t, *xs, prev, st, runs, min_run, (aux, B, b0, n_blocks, max_step, *blk))
        else:
            n_runs, n_rep = scan_chunk(t, *xs, prev, st, runs, min_run)
            L = n_blocks * B
            tb = t[:L] if prev is None else np.concatenate([[t_before_chunk], t[:L]])
            block_pass(*(x[:L] for x in xs), tb, None if aux is None else aux[:L], B, b0, max_step, *blk)
        out.append(((st, n_runs, n_rep, runs[:n_runs].copy()), blk))
    return out


def _same(a, b) -> None:
    (sa, blka), (sb, blkb) = a, b
    assert sa[0].tobytes() == sb[0].tobytes(), (sa[0], sb[0])  # every bit: -0.0 is not 0.0 here
    assert sa[1:3] == sb[1:3]
    np.testing.assert_array_equal(sa[3], sb[3])
    for name, x, y in zip(("mean", "scatter", "aux_mean", "usable"), blka, blkb):
        assert x.tobytes() == y.tobytes(), name


@pytest.mark.parametrize("kind", ["plain", "repeats", "nan", "t", "zeros"])
@pytest.mark.parametrize("B, n_blocks, rest", [(10, 307, 0), (10, 306, 7), (1, 501, 0), (3, 1, 2), (7, 2, 0),
                                               (200, 5, 13), (10, 0, 9)])
@pytest.mark.parametrize("with_prev", [False, True])
def test_fused_call_equals_the_scan_and_block_pass_on_record_rows(kind, B, n_blocks, rest, with_prev):
    n = n_blocks * B + rest
    rec = _records(n + 1, "<f4", seed=B + n_blocks + rest)
    _spoil(rec, kind, seed=n)
    t, xs, aux = rec["t"][1:], [rec[c][1:] for c in CH], rec["temp"][1:]
    prev = np.array([rec["t"][0], *(rec[c][0] for c in CH)], dtype=np.float64) if with_prev else None
    for a in (None, aux, np.column_stack([aux, aux * 2.0])):
        for min_run in (1, 10):
            fused, apart = _both(t, xs, a, prev, B, 3, n_blocks, n_blocks + 5, 0.015, min_run, rec["t"][0])
            _same(fused, apart)
    if kind == "plain" and n_blocks:
        assert fused[1][3][3:3 + n_blocks].any() and (fused[1][0][:, :3] == 7.0).all()  # only its blocks written


@pytest.mark.parametrize("dtype, extra, order", [("<f4", 1, 1), ("<f4", 0, -1), ("<f8", 0, 1)])
@pytest.mark.parametrize("kind", ["plain", "repeats", "nan", "t"])
def test_fused_call_in_any_layout_equals_the_two_calls(dtype, extra, order, kind):
    """Strides the record loop does not take (a longer record, backwards, float64 channels) and
    contiguous copies: the scan of that layout, then the blocks, in the one call."""
    rec = _records(2 * 414 + 1, dtype, seed=len(kind), extra=extra)[::order]
    _spoil(rec, kind, seed=3)
    t, xs = rec["t"][1:], [rec[c][1:] for c in CH]
    prev = np.array([rec["t"][0], *(rec[c][0] for c in CH)], dtype=np.float64)
    for cols in ((t, xs), (t.copy(), [x.copy() for x in xs])):
        fused, apart = _both(*cols, None, prev, 9, 0, 92, 92, 0.015, 10, rec["t"][0])
        _same(fused, apart)


def test_chunks_of_any_split_give_the_one_piece_blocks_and_scan():
    """The pass's chunks at other borders (each with the row before it): the same blocks, state and
    repeated steps as one call over every row, runs joined across borders."""
    B, nb = 10, 400
    rec = _records(nb * B + 6, "<f4", seed=11)
    _spoil(rec, "repeats", seed=5)
    rec[1995:2030][list(CH)] = rec[1995][list(CH)]  # a run across the border at 2000
    t, xs = rec["t"], [rec[c] for c in CH]
    whole_st, whole_blk = _fresh(), _outputs(nb, 0)
    runs = np.zeros((len(t) + 2, 2), np.int64)
    _, whole_rep = scan_chunk(t, *xs, None, whole_st, runs, 10, (None, B, 0, nb, 0.015, *whole_blk))
    for size in (B, 7 * B, 2000, 2990):
        st, blk, n_rep = _fresh(), _outputs(nb, 0), 0
        for i in range(0, len(t), size):
            j = min(i + size, len(t))
            prev = None if i == 0 else np.array([t[i - 1], *(x[i - 1] for x in xs)])
            k = max(0, min(j, nb * B) - i) // B
            n_rep += scan_chunk(t[i:j], *(x[i:j] for x in xs), prev, st, np.zeros(((j - i) // 10 + 2, 2), np.int64),
                                10, (None, B, i // B, k, 0.015, *blk))[1]
        assert st.tobytes() == whole_st.tobytes() and n_rep == whole_rep
        for x, y in zip(blk, whole_blk):
            assert x.tobytes() == y.tobytes()


@pytest.mark.parametrize("blocks, error, match", [
    ((None, 10, 0, 11, 0.015), TypeError, "blocks must be"),
    ("no", TypeError, "blocks must be"),
    ((None, 10, 0, 11, 0.015, "MEAN"), ValueError, "11 blocks of 10 samples do not fit the chunk's 100 rows"),
    ((None, 0, 0, 1, 0.015, "MEAN"), ValueError, "block_n >= 1"),
    ((None, 10, 9, 2, 0.015, "MEAN"), ValueError, r"blocks \[9, 11\) lie outside the 10 output blocks"),
    ((np.zeros(99), 10, 0, 10, 0.015, "MEAN"), ValueError, "aux must have the chunk's 100 rows"),
])
def test_bad_blocks_arguments_are_refused_by_name(blocks, error, match):
    rec = _records(100, "<f4", seed=1)
    out = _outputs(10, 0)
    if isinstance(blocks, tuple) and len(blocks) == 6:
        blocks = blocks[:5] + out
    with pytest.raises(error, match=match):
        scan_chunk(rec["t"], *(rec[c] for c in CH), None, _fresh(), None, 1, blocks)
