"""The reading scan's block statistics (core.fastdetect.BlockFeed) equal block_stats' bit for bit."""
from __future__ import annotations

import numpy as np
import pytest

import gravcal.daemon.recordings as recordings
from gravcal.core.fastdetect import BlockFeed, block_length, block_stats
from gravcal.core.pipeline import calibrate_recording
from gravcal.core.samples import raw_triad
from gravcal.core.simulate import simulate
from gravcal.daemon.recordings import recording_from_arrays


def _recording(seed: int, n: int, k: int, gap: bool):
    rng = np.random.default_rng(seed)
    fs = 100.0
    t = 1000.0 + np.arange(n) / fs + rng.uniform(-1e-4, 1e-4, n)
    if gap:
        t[n // 3:] += 0.5  # a gap: the blocks around it are not usable
    x = rng.normal(0.5, 0.01, size=(n, 3)).astype(np.float32)
    aux = rng.normal(25.0, 1.0, size=(n, k)) if k else None
    return t, x, aux, fs


def _feed(t, x, aux, fs_est, pieces):
    n = t.shape[0]
    feed = BlockFeed(n, fs_est, 0 if aux is None else aux.shape[1], x.dtype)
    i = 0
    for m in pieces:
        j = min(n, i + m)
        tp = np.concatenate([[t[i - 1] if i else np.nan], t[i:j]])
        feed.add(tp, np.ascontiguousarray(x[i:j].T), None if aux is None else aux[i:j])
        i = j
        if i == n:
            break
    return feed


def _assert_same(a, b):
    for name in ("mean", "scatter", "aux", "usable"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert (a.fs, a.block_n) == (b.fs, b.block_n)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("k", [0, 1, 2])
@pytest.mark.parametrize("gap", [False, True])
def test_feed_in_any_pieces_equals_block_stats(seed, k, gap):
    t, x, aux, fs = _recording(seed, 100_003 + 977 * seed, k, gap)
    ref = block_stats(t, lambda c, i, j: x[i:j, c], t.shape[0], fs, aux=aux)
    rng = np.random.default_rng(100 + seed)
    pieces = rng.integers(1, 70_000, size=t.shape[0])  # pieces that straddle block_stats' chunks
    got = _feed(t, x, aux, fs * (1 + 1e-9), pieces).result(fs)
    assert got is not None
    assert gap == (not got.usable.all())
    _assert_same(got, ref)


def test_feed_refuses_what_block_stats_would_compute_otherwise():
    t, x, aux, fs = _recording(0, 50_000, 0, gap=False)
    t[20_000:] += 0.0148 - 0.01  # one step of 14.8 ms: usable at 100 Hz (< 15 ms), not at 102 Hz
    pieces = [65_536]
    assert _feed(t, x, aux, fs, pieces).result(fs) is not None
    assert _feed(t, x, aux, fs, pieces).result(102.0) is None  # the step would be classed otherwise
    assert block_length(130.0) != block_length(fs)
    assert _feed(t, x, aux, fs, pieces).result(130.0) is None  # another block length
    assert _feed(t, x, aux, fs, [30_000]).result(fs) is None  # rows missing


def test_read_gives_the_blocks_of_its_rows_and_none_after_a_drop(monkeypatch):
    monkeypatch.setattr(recordings, "SCAN_CHUNK", 7_777)
    t, x, aux, fs = _recording(1, 60_000, 1, gap=True)
    rec = recording_from_arrays(t, x, temp=aux[:, 0])
    assert rec.blocks is None  # not asked for
    rec = recordings._validate(recordings.Path("<arrays>"), {"t": t, "_triad": x, "temp": aux[:, 0]},
                               recordings.Where(path=recordings.Path("<arrays>")), ("t", "ax", "ay", "az", "temp"),
                               min_samples=10, check_saturation=True, blocks_from=1)
    ref = block_stats(rec.t, lambda c, i, j: rec.raw[i:j, c], rec.n_samples, rec.fs, aux=rec.temp)
    _assert_same(rec.blocks, ref)
    x2 = x.copy()
    x2[123, 1] = np.nan  # a dropped row: the scan's blocks are not those of the kept rows
    rec2 = recordings._validate(recordings.Path("<arrays>"), {"t": t, "_triad": x2},
                                recordings.Where(path=recordings.Path("<arrays>")), ("t", "ax", "ay", "az"),
                                min_samples=10, check_saturation=True, blocks_from=1)
    assert rec2.n_dropped == 1 and rec2.blocks is None
    x3 = x.copy()
    x3[1000:1400, 0] = x[:, 0].max()  # 400 clipped rows (0.7 %) at the maximum: dropped as saturated
    rec3 = recordings._validate(recordings.Path("<arrays>"), {"t": t, "_triad": x3},
                                recordings.Where(path=recordings.Path("<arrays>")), ("t", "ax", "ay", "az"),
                                min_samples=10, check_saturation=True, blocks_from=1)
    assert rec3.n_saturated >= 400 and rec3.blocks is None


def test_calibration_uses_given_blocks_only_when_they_are_of_its_rows(monkeypatch):
    import gravcal.core.pipeline as pipeline  # noqa: PLC0415

    sim = simulate("six_position", seed=3, duration=300.0)
    t, raw = sim.samples["t"], raw_triad(sim.samples)
    fs = 1.0 / float(np.median(np.diff(t)))
    bs = block_stats(t, lambda c, i, j: raw[i:j, c], t.shape[0], fs)
    a = calibrate_recording(t, raw, fs=fs, detection="blocks")
    computed = []
    real = pipeline._block_stats
    monkeypatch.setattr(pipeline, "_block_stats", lambda *a, **k: computed.append(1) or real(*a, **k))
    b = calibrate_recording(t, raw, fs=fs, detection="blocks", blocks=bs)
    assert computed == []
    np.testing.assert_array_equal(a.calibration.offset, b.calibration.offset)
    np.testing.assert_array_equal(a.calibration.sensitivity, b.calibration.sensitivity)
    assert a.n_windows == b.n_windows > 0
    calibrate_recording(t[:-100], raw[:-100], fs=fs, detection="blocks", blocks=bs)  # other rows: computed anew
    assert computed == [1]
