"""Exactly repeated runs: the sparse run search and the chunked collector against a direct count."""
import math

import numpy as np
import pytest

from gravcal.core.repeats import RunCollector, flat_stretches, repeated_steps, true_runs


def _direct(raw, min_run=10):
    """The rule written out over every step: run boundaries from the sign changes of 'same'."""
    n = raw.shape[0]
    same = np.all(raw[1:] == raw[:-1], axis=1)
    d = np.diff(np.concatenate([[0], same.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    lengths = ends - starts
    short = lengths < min_run
    q = float(lengths[short].sum()) / max(n - 1 - int(lengths[~short].sum()), 1)
    expected = math.log(n) / math.log(1.0 / q) if 0 < q < 1 else (0.0 if q == 0 else math.inf)
    limit = max(min_run, 3.0 * expected)
    return [(int(a), int(b) + 1) for a, b, ln in zip(starts, ends, lengths) if ln >= limit], q


def _recording(seed, n=30_000):
    rng = np.random.default_rng(seed)
    raw = rng.integers(0, 30, size=(n, 3)).astype(np.float32)  # coarse: chance repeats
    for start in rng.integers(0, n - 50, 8):
        raw[start:start + rng.integers(15, 3000)] = raw[start]
    if seed % 2:  # runs touching both ends
        raw[:400] = raw[0]
        raw[-700:] = raw[-700]
    return raw


@pytest.mark.parametrize("seed", range(8))
def test_flat_stretches_equal_the_direct_count(seed):
    raw = _recording(seed)
    want, q = _direct(raw)
    got = flat_stretches(raw)
    assert want and got.runs == want and got.repeat_prob == pytest.approx(q, rel=1e-12)


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("chunk", [1, 7, 499, 4096])
def test_chunks_join_runs_across_their_borders(seed, chunk):
    raw = _recording(seed)
    runs = RunCollector()
    steps = raw.shape[0] - 1
    for i in range(0, steps, chunk):
        runs.add(repeated_steps(raw[i:min(steps, i + chunk) + 1]), i)
    got, whole = runs.result(raw.shape[0]), flat_stretches(raw)
    assert got.runs == whole.runs and got.repeat_prob == whole.repeat_prob


def test_true_runs_of_edges_and_nothing():
    s, ln = true_runs(np.array([True, True, False, True, False, False, True, True, True]))
    assert s.tolist() == [0, 3, 6] and ln.tolist() == [2, 1, 3]
    s, ln = true_runs(np.zeros(5, dtype=bool))
    assert s.size == ln.size == 0


def test_a_constant_recording_is_one_run():
    raw = np.ones((500, 3))
    assert flat_stretches(raw).runs == [(0, 500)]
