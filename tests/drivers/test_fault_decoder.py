"""Decoder fuzzing: mutated frame streams through codec.FrameDecoder.

Mutations (tests/support/faults_decoder.py MutatedStream): bit flips, truncations, drops, bytes
inserted into / deleted from a frame, garbage, fake candidates, duplicated, partially copied,
spliced, stray old and foreign (CRC-valid, random seq) frames. Properties: no exception
escapes; every intact frame (unmodified, not overlapped by a mutation) comes out with its exact
fields and its unwrapped seq; damaged frames are counted as CRC/length rejects. Long mode:
``python bench/bench_faults.py --long --only decoder`` (2*10^6 frames).
"""

import numpy as np
import pytest
from gravcal.core.samples import FLAG_GAP_BEFORE
from gravcal.drivers.codec import FRAME_LEN, FrameDecoder, SeqUnwrapper, encode_frames
from hypothesis import given, settings
from hypothesis import strategies as st
from support import faults_decoder as bf


def check(fig: dict) -> None:
    assert fig["exceptions"] == 0
    assert fig["lost_intact"] == 0, fig
    assert fig["recovered"] + fig["excused_by_crc_collision"] == fig["intact"]
    # what reaches the client beyond the original samples: only foreign (CRC-valid, random)
    # frames that could not be told from the stream (the last of a read, or the very first)
    assert fig["extra_delivered"] <= fig["foreign_inserted"]


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 400), p_frame=st.floats(0, 0.6),
       p_between=st.floats(0, 0.6), chunk=st.integers(2, 700))
def test_mutated_streams_recover_every_intact_frame(seed, n, p_frame, p_between, chunk):
    rng = np.random.default_rng(seed)
    ms = bf.MutatedStream(n, rng, p_frame=p_frame, p_between=p_between)
    got, stats = bf.decode_in_chunks(ms.data, rng, max_chunk=chunk)
    fig = bf.judge_decoder(ms, got, stats)
    fig["exceptions"] = 0
    check(fig)
    # a damaged frame whose sync and length byte survived (and that is not the stream's last) is a counted reject
    rejects = stats["crc_errors"] + stats["length_errors"]
    assert rejects <= fig["sync_candidates"]
    if ms.rejectable and p_between == 0:
        assert rejects > 0, (ms.rejectable, ms.counts)


def test_twenty_thousand_heavily_mutated_frames():
    fig = bf.run_decoder(20_000, seed=7, p_frame=0.25, p_between=0.25)
    check(fig)
    assert fig["mutations"] > 8000 and fig["crc_errors"] > 2000 and fig["strays"] > 500
    assert fig["duplicates"] > 100


def test_a_stray_frame_does_not_shift_later_sequence_numbers():
    u = SeqUnwrapper()
    # an old frame replayed (behind), then a foreign one far ahead, inside one read
    keep, seq, gap = u.unwrap(np.array([100, 101, 60, 102, 40000, 103, 104], np.uint16))
    np.testing.assert_array_equal(seq, [100, 101, 102, 103, 104])
    assert not gap.any() and u.strays == 2 and u.gaps == 0
    # a foreign frame as the last of a read is delivered; the next read goes on from before it
    _, seq, gap = u.unwrap(np.array([105, 9000], np.uint16))
    _, seq2, gap2 = u.unwrap(np.array([106, 107], np.uint16))
    np.testing.assert_array_equal(seq2, [106, 107])
    assert u.strays_delivered == 1 and not gap2.any()
    # a device that restarts its counter: three frames that continue each other are believed
    _, seq3, gap3 = u.unwrap(np.array([0, 1, 2, 3], np.uint16))
    assert seq3[0] > 107 and np.all(np.diff(seq3) == 1) and gap3[0]


def _frames(seqs, seed=0):
    s = bf.random_samples(len(seqs), np.random.default_rng(seed))
    s["seq"] = seqs
    return s


@pytest.mark.parametrize("foreign, start", [(43409, 33287), (60000, 1000)], ids=["behind", "ahead-wrapping"])
@pytest.mark.parametrize("split", [None, 1], ids=["one-read", "foreign-read-alone"])
def test_a_foreign_first_frame_does_not_shift_the_stream(foreign, start, split):
    # Minimised from the long run (2*10^6 frames, one 50k batch lost 37.5k frames): the stream
    # began with a damaged frame, then a foreign CRC-valid frame (seq 43409), then the real
    # stream at 33287. The foreign frame anchored the unwrapping; the real frames read as a
    # device restart behind it and every later seq came out 2**16 too high. The same happens
    # when the real stream lies ahead of the foreign frame across the 16-bit wrap.
    real = _frames(start + np.arange(4))
    data = encode_frames(_frames([foreign], seed=1)) + encode_frames(real)
    dec = FrameDecoder()
    reads = [data] if split is None else [data[:FRAME_LEN * split], data[FRAME_LEN * split:]]
    got = np.concatenate([dec.feed(r) for r in reads])
    real_out = got[got["tick"] != _frames([foreign], seed=1)["tick"][0]]
    np.testing.assert_array_equal(real_out["seq"], start + np.arange(4))  # raw values, unshifted
    np.testing.assert_array_equal(real_out["tick"], real["tick"])
    assert not (real_out["flags"][1:] & FLAG_GAP_BEFORE).any()
    st_ = dec.stats()
    assert st_["strays"] == 1 and st_["gaps"] == 0 and st_["missing"] == 0
    # removed when it shared the read with the real frames, else already delivered (and counted)
    assert got.shape[0] == (4 if split is None else 5) and st_["strays_delivered"] == (split or 0)


def test_a_run_of_foreign_frames_does_not_confirm_itself():
    # Minimised from the long run (seed 0, batch 21 lost 1912 frames): three foreign frames in a
    # row, each ahead of or between the others, were taken as losses confirming each other; the
    # real stream then read as one more forward jump and every later seq was 2**16 too high.
    u = SeqUnwrapper()
    keep, seq, gap = u.unwrap(np.array([35288, 35289, 943, 9325, 8120, 35293, 35294], np.uint16))
    np.testing.assert_array_equal(seq, [35288, 35289, 35293, 35294])
    np.testing.assert_array_equal(keep, [1, 1, 0, 0, 0, 1, 1])
    assert u.strays == 3 and (u.gaps, u.missing) == (1, 3) and gap.tolist() == [0, 0, 1, 0]


def _unwrap_reads(u: SeqUnwrapper, reads: list[list[int]]) -> tuple[list[int], list[bool]]:
    """Unwrapped seq and gap flags of everything delivered for ``reads`` (one unwrap each)."""
    seq, gap = [], []
    for r in reads:
        _, s, g = u.unwrap(np.array(r, np.uint16))
        seq += s.tolist()
        gap += g.tolist()
    return seq, gap


@pytest.mark.parametrize("split", [False, True], ids=["one-read", "frame-per-read"])
def test_a_late_copy_in_the_hole_of_a_small_jump_does_not_remove_the_jump(split):
    # Minimised from the hypothesis example seed=13304, n=397, p_frame=p_between=0.55,
    # chunk=396 (and long-mode seed 0 batch 19): 25447 believed, an old copy (25413), a
    # genuine jump of 6 to 25453, a foreign frame (49358), then a late copy of 25452 (in the
    # jump's hole). The late copy took the jump back and the genuine 25453 was removed.
    frames = [25447, 25413, 25453, 49358, 25452, 25455]
    u = SeqUnwrapper()
    seq, gap = _unwrap_reads(u, [[f] for f in frames] if split else [frames])
    genuine = [25447, 25453, 25455]
    assert [s for s in seq if s in genuine] == genuine  # every genuine frame, unshifted
    # what else reached the client was disowned later (a read's last frame is judged by the next)
    assert len(seq) - len(genuine) == u.strays_delivered == (2 if split else 0)
    assert u.strays == 3 and (u.gaps, u.missing) == (2, 6)
    assert [g for s, g in zip(seq, gap) if s in genuine] == [False, True, True]


@pytest.mark.parametrize("split", [False, True], ids=["one-read", "frame-per-read"])
def test_two_foreign_frames_that_continue_each_other_are_taken_back(split):
    # A foreign frame far ahead, then another within STRAY_JUMP_MIN of it: they confirm each
    # other like a long loss would. The real stream then continues the head from before that
    # jump: its second frame takes the jump back (1 in 1000 pairs of foreign frames in a row).
    frames = [100, 101, 30000, 30005, 103, 104, 105]
    u = SeqUnwrapper()
    seq, gap = _unwrap_reads(u, [[f] for f in frames] if split else [frames])
    real = [100, 101, 103, 104, 105]
    assert [s for s in seq if s < 30000] == real
    assert u.strays == 2 and u.strays_delivered == (2 if split else 0)
    assert (u.gaps, u.missing) == (1, 1) and [g for s, g in zip(seq, gap) if s < 30000] == [0, 0, 1, 0, 0]
    # the stream goes on from there: no multiple of 2**16 slipped in
    _, s2, g2 = u.unwrap(np.array([106, 107], np.uint16))
    assert s2.tolist() == [106, 107] and not g2.any()


def test_a_foreign_frame_that_looks_like_a_small_loss_is_taken_back():
    # A foreign frame within STRAY_JUMP_MIN ahead is believed at once (an ordinary loss); the
    # real frames that follow lie in its hole and continue the frame before it.
    u = SeqUnwrapper()
    keep, seq, gap = u.unwrap(np.array([100, 101, 130, 102, 103, 104], np.uint16))
    np.testing.assert_array_equal(seq, [100, 101, 102, 103, 104])
    np.testing.assert_array_equal(keep, [1, 1, 0, 1, 1, 1])
    assert u.strays == 1 and (u.gaps, u.missing) == (0, 0) and not gap.any()


def test_a_lone_late_frame_behind_the_stream_changes_nothing():
    # frames behind the head are held back: one (or two in a row) is a stray, never a restart
    u = SeqUnwrapper()
    seq, gap = _unwrap_reads(u, [[500, 501], [470], [471], [502, 503]])
    assert seq == [500, 501, 502, 503] and not any(gap) and u.strays == 2
