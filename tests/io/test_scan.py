"""The validation scan's chunked statistics equal the same statistics over the whole arrays."""
from __future__ import annotations

import numpy as np
import pytest

import gravcal.io.recordings as recordings


def _columns(seed: int, n: int, dtype, backwards: bool = True):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.005, 0.015, n))
    raw = rng.integers(-40, 40, size=(n, 3)).astype(dtype)  # coarse: ties at the extremes across chunks
    raw[rng.integers(0, n, 50), rng.integers(0, 3, 50)] = 40  # a pile-up at the maximum
    if backwards:
        t[rng.integers(1, n)] = t[rng.integers(0, n)]  # a step that is not positive somewhere
    return t, raw


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("chunk", [1000, 997, 1 << 16])
@pytest.mark.parametrize("backwards", [False, True])
def test_chunked_scan_equals_whole_array_statistics(monkeypatch, seed, dtype, chunk, backwards):
    monkeypatch.setattr(recordings, "SCAN_CHUNK", chunk)
    t, raw = _columns(seed, 10_001, dtype, backwards)
    sc = recordings._scan(t, raw, [], None)
    assert sc.finite
    assert sc.min_dt == np.diff(t).min()
    np.testing.assert_array_equal(sc.lo, raw.min(axis=0))
    np.testing.assert_array_equal(sc.hi, raw.max(axis=0))
    np.testing.assert_array_equal(sc.n_lo, (raw == raw.min(axis=0)).sum(axis=0))
    np.testing.assert_array_equal(sc.n_hi, (raw == raw.max(axis=0)).sum(axis=0))


@pytest.mark.parametrize("where", ["t", "ax", "az", "extra"])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("row", [0, 1, 999, 1000, 10_049])
def test_any_non_finite_value_is_found(monkeypatch, where, bad, row):
    monkeypatch.setattr(recordings, "SCAN_CHUNK", 1000)
    t, raw = _columns(0, 10_050, np.float32)  # a last chunk of 50 rows
    extra = np.zeros(t.shape[0])
    if where == "t":
        t[row] = bad
    elif where == "extra":
        extra[row] = bad
    else:
        raw[row, {"ax": 0, "az": 2}[where]] = bad
    assert not recordings._scan(t, raw, [extra], None).finite
    assert recordings._scan(*_columns(0, 10_050, np.float32), [np.zeros(t.shape[0])], None).finite


@pytest.mark.parametrize("min_run", [5, 10])
def test_filler_runs_from_the_limit_on_and_none_shorter(min_run):
    from gravcal.core.diagnosis.noise import flat_stretches

    codes = np.arange(1000, dtype=np.float64)  # no repeat by chance: the limit is min_run
    codes[100:100 + min_run + 1] = codes[100]  # min_run repeated steps: filler
    codes[500:500 + min_run] = codes[500]  # one step fewer: kept
    raw = np.column_stack([codes, codes + 1.0, -codes])
    flats = flat_stretches(raw, min_run=min_run)
    assert flats.runs == [(100, 100 + min_run + 1)]
    assert recordings._filler_stretches(raw, min_run=min_run).runs == flats.runs


# chunk 1 (every row a chunk border: every run starts and ends on one) costs a Python step per row, so once;
# chunk 61 puts borders inside every stretch (20..800 rows) at seed-dependent offsets for each seed
@pytest.mark.parametrize("seed, chunk", [(0, 1)] + [(s, c) for s in range(4) for c in (61, 997, 1 << 16)])
@pytest.mark.parametrize("dtype", [np.float32, np.int32])
@pytest.mark.parametrize("bad", ["none", "nan", "saturated"])
def test_filler_found_by_the_scan_is_flat_stretches_of_the_kept_rows(monkeypatch, seed, chunk, dtype, bad):
    """The validation scan finds the filler on the rows it keeps: equal to flat_stretches of what is left
    after NaN rows (dropped, then scanned again) and saturated rows (dropped after the scan)."""
    from gravcal.core.diagnosis.noise import flat_stretches

    monkeypatch.setattr(recordings, "SCAN_CHUNK", chunk)
    rng = np.random.default_rng(seed)
    n = 6_000
    t = np.cumsum(rng.uniform(0.009, 0.011, n))
    raw = rng.integers(0, 30, size=(n, 3)).astype(np.float64)  # coarse: chance repeats
    if bad == "saturated":
        raw[:, 2] += rng.integers(0, 2000, n) * (rng.random(n) < 0.3)  # spread values under a pile-up
    for start in rng.integers(0, n - 50, 5):
        raw[start:start + rng.integers(20, 800)] = raw[start]
    if bad == "nan":
        raw[rng.integers(0, n, 40), 1] = np.nan
    elif bad == "saturated":
        raw[rng.integers(0, n, 150), 2] = 3000.0  # a pile-up at the maximum
    raw = raw if bad == "nan" else raw.astype(dtype)
    rec = recordings.recording_from_arrays(t, raw, exclude_filler=True)
    kept = recordings.recording_from_arrays(t, raw, exclude_filler=False).raw
    assert kept.shape[0] < n or bad == "none"
    flats = flat_stretches(kept)
    assert flats.runs and rec.n_filler == flats.n_samples - len(flats.runs)
    drop = np.zeros(kept.shape[0], dtype=bool)
    for a, b in flats.runs:
        drop[a + 1:b] = True
    np.testing.assert_array_equal(rec.raw, kept[~drop])


@pytest.mark.parametrize("chunk", [1000, 997, 1 << 16])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_steps_and_repeats_across_chunk_borders_are_counted(monkeypatch, chunk, dtype):
    """The step into a chunk's first row and its repeat of the row before are the scan's too: a
    repeated time and a repeated triad placed on a border, and rows that repeat in only two channels."""
    monkeypatch.setattr(recordings, "SCAN_CHUNK", chunk)
    rng = np.random.default_rng(chunk)
    n = 10_000
    t = np.cumsum(rng.uniform(0.005, 0.015, n))
    raw = rng.integers(0, 6, size=(n, 3)).astype(dtype)  # coarse: many repeats of two channels, some of three
    t[2000] = t[1999]  # a zero step: on a border for chunk 1000
    raw[5000] = raw[4999]  # a repeated triad on a border for chunk 1000
    raw[2 * 997] = raw[2 * 997 - 1]  # and for chunk 997
    sc = recordings._scan(t, raw, [], None, repeats=True)
    assert sc.min_dt == 0.0 == np.diff(t).min()
    same = (raw[1:] == raw[:-1]).all(axis=1)
    two = (raw[1:, :2] == raw[:-1, :2]).all(axis=1)
    assert sc.repeats.n_repeats == int(same.sum()) and two.sum() > 2 * same.sum()
