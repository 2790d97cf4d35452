"""lotters_chain in two halves (the norm and x; y, z and the within-block std gate), as
core.fastdetect.lotters_still runs it on two threads for long recordings without the vector lanes: every
detection signal, every scatter and the still mask bit for bit those of the one call on all four channels;
and the vector lanes (AVX2) bit for bit the scalar loops.

Blocks with unusable runs (held at the last usable one, NaN scatter inside), a first usable block
after 0, movement and stillness, orders 2 and 4 (the constant-trip-count forms and the general one).
"""
from __future__ import annotations

import numpy as np
import pytest

import gravcal.core.fastdetect as fastdetect
from gravcal.core._blockkernels import lotters_chain
from gravcal.core.calibration import Calibration
from gravcal.core.butterworth import butter_sos, sos_rest_state

B = 10
FS = 100.0


def _blocks(nb: int, seed: int) -> fastdetect.BlockStats:
    """Block statistics of a wearer: postures held for a few seconds, movement between, sensor noise;
    a few runs of unusable blocks (a gap) whose statistics are NaN."""
    rng = np.random.default_rng(seed)
    posture = np.repeat(rng.normal(size=(3, nb // 200 + 1)), 200, axis=1)[:, :nb]
    posture /= np.linalg.norm(posture, axis=0)
    moving = np.repeat(rng.random(nb // 40 + 1) < 0.2, 40)[:nb]
    acc = posture + moving * 0.3 * rng.standard_normal((3, nb)) + 0.002 * rng.standard_normal((3, nb))
    mean = 0.5 + 0.04 * acc + np.array([[0.01], [-0.02], [0.005]])
    scat = (B * (0.04 * (0.004 + 0.2 * moving)) ** 2 * rng.random((6, nb))).astype(np.float32)
    scat[3:] *= 0.1  # cross terms smaller than the diagonal ones
    usable = np.ones(nb, dtype=bool)
    usable[:3] = False  # the first usable block is not the first
    for s in rng.integers(10, nb - 10, size=max(1, nb // 5000)):
        usable[s:s + rng.integers(1, 8)] = False
    mean[:, ~usable] = np.nan
    scat[:, ~usable] = np.nan
    return fastdetect.BlockStats(FS, B, np.ascontiguousarray(mean), np.ascontiguousarray(scat), np.zeros((0, nb)),
                                 usable)


def _args(bs: fastdetect.BlockStats, order: int, to_g: Calibration):
    o, kinv = fastdetect._to_g_affine(to_g)
    sos_hp, sos_lp = butter_sos(order, 0.5, "highpass", FS / B), butter_sos(order, 0.5, "lowpass", FS / B)
    return (bs.mean, bs.usable, bs.scatter, o, kinv, sos_hp, sos_lp, np.ascontiguousarray(sos_rest_state(sos_hp)))


TO_G = Calibration("start", np.array([0.51, 0.48, 0.505]), np.diag([0.04, 0.041, 0.039]) + 0.001)


def spy_on_chain(monkeypatch) -> list:
    """Records each lotters_chain call's (order,) or (order, first channel, gate)."""
    calls: list = []
    real = fastdetect.lotters_chain

    def spy(*args):
        calls.append(args[8:9] + args[14:])
        return real(*args)

    monkeypatch.setattr(fastdetect, "lotters_chain", spy)
    return calls


@pytest.mark.parametrize("order", [2, 4])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_two_halves_are_the_one_call_bit_for_bit(order, seed):
    bs = _blocks(30_000, seed)
    nb, b0 = len(bs), int(np.argmax(bs.usable))
    args = _args(bs, order, TO_G)
    thr = 0.02
    limits = (thr, thr ** 2 * B, b0)
    one, trace1 = np.zeros(nb, dtype=bool), np.full((7, nb), np.nan)
    lotters_chain(*args, 4, *limits, one, trace1)
    a, b = np.zeros(nb, dtype=bool), np.zeros(nb, dtype=bool)
    trace2 = np.full((7, nb), np.nan)
    lotters_chain(*args, 2, *limits, a, trace2, 0, False)  # |a| and x, no gate
    lotters_chain(*args, 4, *limits, b, trace2, 2, True)  # y, z and the gate
    np.testing.assert_array_equal(trace2[:4], trace1[:4])  # each channel's signal
    np.testing.assert_array_equal(trace2[4:][:, bs.usable], trace1[4:][:, bs.usable])  # the per-axis scatter
    np.testing.assert_array_equal(a & b, one)
    assert 0.1 < one.mean() < 0.9  # both decisions are compared
    assert (a & ~b).any() and (b & ~a).any()  # and each half decides some blocks the other does not


@pytest.mark.parametrize("order", [2, 4])
@pytest.mark.parametrize("nb, seed", [(30_000, 0), (30_001, 1), (30_002, 2), (1_027, 5), (43, 6)])
def test_vector_lanes_are_the_scalar_loops_bit_for_bit(order, nb, seed):
    """Where the CPU has AVX2, the blocks' own decisions run four blocks per vector and (order 2, all four
    channels) the four channels' filters in the lanes of one vector: every signal, scatter and still flag
    equals the one-block-one-channel loops' (vector=False), for the one call, the two halves and the norm
    alone; block counts off the multiples of 4 and of the chunk, unusable runs inside and at the start."""
    bs = _blocks(nb, seed)
    b0 = int(np.argmax(bs.usable))
    args = _args(bs, order, TO_G)
    limits = (0.02, 0.02 ** 2 * B, b0)
    for chans, first, gate in ((4, 0, True), (2, 0, False), (4, 2, True), (1, 0, True)):
        runs = []
        for vector in (False, True):
            still, trace = np.zeros(nb, dtype=bool), np.full((7, nb), np.nan)
            lotters_chain(*args, chans, *limits, still, trace, first, gate, vector)
            runs.append((still, trace))
        (s0, t0), (s1, t1) = runs
        np.testing.assert_array_equal(t1[first:chans], t0[first:chans])
        if gate:
            np.testing.assert_array_equal(t1[4:], t0[4:])  # NaN where a block's scatter is NaN, in both
        np.testing.assert_array_equal(s1, s0)
        if nb > 1000:
            assert 0.05 < s0.mean() < 0.95


def test_lotters_still_runs_one_call_in_the_vector_lanes(monkeypatch):
    """Order 2 where the kernel filters the four channels in one vector: one call, equal to the two halves."""
    bs = _blocks(40_000, 3)
    monkeypatch.setattr(fastdetect, "CHAIN_LANES_MIN_BLOCKS", 1000)
    monkeypatch.setattr(fastdetect, "CHAIN_VECTOR", False)
    halves = fastdetect.lotters_still(bs, TO_G)
    calls = spy_on_chain(monkeypatch)
    monkeypatch.setattr(fastdetect, "CHAIN_VECTOR", True)
    np.testing.assert_array_equal(fastdetect.lotters_still(bs, TO_G), halves)
    assert calls == [(4,)]
    calls.clear()
    fastdetect.lotters_still(bs, TO_G, order=4)  # no vector form of order 4: the halves
    assert sorted(calls) == [(2, 0, False), (4, 2, True)]


def test_lotters_still_on_two_threads_equals_one(monkeypatch):
    bs = _blocks(40_000, 3)
    monkeypatch.setattr(fastdetect, "CHAIN_VECTOR", False)  # the halves also where the CPU has the vector lanes
    monkeypatch.setattr(fastdetect, "CHAIN_LANES_MIN_BLOCKS", 1 << 62)
    single = fastdetect.lotters_still(bs, TO_G)
    calls = spy_on_chain(monkeypatch)
    monkeypatch.setattr(fastdetect, "CHAIN_LANES_MIN_BLOCKS", 1000)
    lanes = fastdetect.lotters_still(bs, TO_G)
    assert sorted(calls) == [(2, 0, False), (4, 2, True)]  # the two halves ran
    np.testing.assert_array_equal(lanes, single)
    assert 0.1 < single.mean() < 0.9
    calls.clear()
    norm_only = fastdetect.lotters_still(bs, TO_G, per_axis=False)  # the norm alone: one call
    assert calls == [(1,)]
    assert norm_only.sum() >= single.sum()


def test_first_channel_is_checked():
    bs = _blocks(2_000, 4)
    args = _args(bs, 2, TO_G)
    still = np.zeros(len(bs), dtype=bool)
    for chans, first in ((4, 4), (2, -1), (1, 1)):
        with pytest.raises(ValueError, match="first channel"):
            lotters_chain(*args, chans, 0.02, 0.004, 3, still, None, first, True)
