"""calibrate_recording's progress(done, total) callback: increasing, reaching the fixed total."""
from __future__ import annotations

import numpy as np
import pytest

import gravcal.core.fastdetect as fastdetect
from gravcal.core.pipeline import calibrate_recording
from gravcal.core.samples import raw_triad
from gravcal.core.simulate import simulate


@pytest.fixture(scope="module")
def recording():
    sim = simulate("loetters", seed=3, duration=600.0)
    return sim.samples["t"], raw_triad(sim.samples)


def _calls(t, raw, **kw):
    calls = []
    report = calibrate_recording(t, raw, progress=lambda d, n: calls.append((d, n)), **kw)
    return report, calls


@pytest.mark.parametrize("chunk_blocks", [4096, 256])
def test_block_pass_and_stages_count_up_to_the_total(recording, monkeypatch, chunk_blocks):
    monkeypatch.setattr(fastdetect, "CHUNK_BLOCKS", chunk_blocks)
    t, raw = recording
    report, calls = _calls(t, raw, detection="blocks")
    done = np.array([d for d, _ in calls])
    totals = {n for _, n in calls}
    chunks = fastdetect.pass_chunks(len(t), fastdetect.block_length(100.0))
    assert totals == {chunks + 4}  # one total for the whole call: the chunks and four stages
    assert done[0] == 0 and done[-1] == chunks + 4
    assert np.all(np.diff(done) > 0)  # each chunk and stage once, in order, even from two threads
    assert len(calls) == chunks + 5
    plain = calibrate_recording(t, raw, detection="blocks")  # the callback does not change the result
    np.testing.assert_array_equal(report.calibration.offset, plain.calibration.offset)


def test_stream_detection_reports_its_stages(recording):
    t, raw = recording
    _, calls = _calls(t, raw, detection="stream")
    assert [d for d, _ in calls] == [0, 1, 2, 3, 4] and {n for _, n in calls} == {4}


def test_block_stats_progress_from_threads_is_increasing(recording):
    t, raw = recording
    calls = []
    fastdetect.block_stats(t, lambda c, i, j: raw[i:j, c], len(t), 100.0, block_n=2, threads=2,
                           progress=lambda d, n: calls.append((d, n)))
    n_chunks = fastdetect.pass_chunks(len(t), 2)
    assert n_chunks > 2
    assert [d for d, _ in calls] == list(range(1, n_chunks + 1)) and {n for _, n in calls} == {n_chunks}
