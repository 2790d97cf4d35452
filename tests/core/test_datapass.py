"""The reading pass (core.datapass.scan_columns): the same validation statistics in one or two
threads and any chunking, and block statistics equal to core.fastdetect.block_stats' bit for bit."""
from __future__ import annotations

import numpy as np
import pytest

import gravcal.core.fastdetect as fastdetect
from gravcal.core.datapass import fs_from, scan_columns
from gravcal.core.repeats import flat_stretches
from gravcal.core.samples import raw_triad
from gravcal.core.simulate import simulate
from tests.support.smaps import mapped_kb


def _records(seed: int, n: int, gaps: bool = True) -> np.ndarray:
    """A .npy-like record array (t f8, ax ay az f4, temp f4) at ~100 Hz with chance repeats,
    filler runs across chunk borders and (``gaps``) steps outside (0, 1.5/fs]."""
    rng = np.random.default_rng(seed)
    rec = np.empty(n, dtype=[("t", "<f8"), ("ax", "<f4"), ("ay", "<f4"), ("az", "<f4"), ("temp", "<f4")])
    rec["t"] = 1.7e9 + np.cumsum(rng.uniform(0.0099, 0.0101, n))
    if gaps:
        rec["t"][rng.integers(1, n, 8)] += 0.5  # gaps: those blocks are unusable
    codes = rng.integers(0, 12, size=(n, 3)).astype(np.float32) * np.float32(0.01) + np.float32(0.5)
    for start in rng.integers(0, n - 900, 6):
        codes[start:start + rng.integers(20, 900)] = codes[start]
    codes[rng.integers(0, n), 0], codes[rng.integers(0, n), 1] = 0.9, 0.1  # extremes reached in one chunk only
    rec["ax"], rec["ay"], rec["az"] = codes.T
    rec["temp"] = 25.0 + rng.normal(0.0, 0.1, n)
    return rec


def _triad(rec: np.ndarray) -> np.ndarray:
    return np.ndarray(shape=(rec.shape[0], 3), dtype=np.float32, buffer=rec, offset=8, strides=(rec.strides[0], 4))


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("chunk", [61, 997, 1 << 16])
def test_one_or_two_threads_and_any_chunking_give_the_same_statistics(seed, chunk):
    rec = _records(seed, 30_011)
    t, raw = rec["t"], _triad(rec)
    one = scan_columns(t, raw, [rec["temp"]], None, chunk=chunk, repeats=True, threads=1)
    two = scan_columns(t, raw, [rec["temp"]], None, chunk=chunk, repeats=True, threads=2)
    whole = raw.astype(np.float64)
    for sc in (one, two):
        assert sc.finite and sc.min_dt == np.diff(t).min()
        np.testing.assert_array_equal(sc.lo, whole.min(axis=0))
        np.testing.assert_array_equal(sc.hi, whole.max(axis=0))
        np.testing.assert_array_equal(sc.n_lo, (whole == whole.min(axis=0)).sum(axis=0))
        np.testing.assert_array_equal(sc.n_hi, (whole == whole.max(axis=0)).sum(axis=0))
        flats, found = flat_stretches(whole), sc.repeats.result(len(t))
        assert found.runs == flats.runs and found.repeat_prob == flats.repeat_prob
        assert sc.repeats.n_repeats == int((whole[1:] == whole[:-1]).all(axis=1).sum())
    assert one.dt_medians == two.dt_medians and len(one.dt_medians) >= 1


@pytest.mark.parametrize("chunk_blocks", [7, 64, 4096])
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("with_aux", [False, True])
def test_blocks_of_the_pass_are_block_stats(monkeypatch, chunk_blocks, threads, with_aux):
    monkeypatch.setattr(fastdetect, "CHUNK_BLOCKS", chunk_blocks)
    rec = _records(5, 20_007)  # not a whole number of blocks: the last 7 rows are scanned only
    t, raw = rec["t"], _triad(rec)
    aux = rec["temp"] if with_aux else None
    sc = scan_columns(t, raw, [], None, chunk=1000, blocks=True, aux=aux, threads=threads)
    fs = fs_from(sc.dt_medians)
    ref = fastdetect.block_stats(t, lambda c, i, j: raw[i:j, c], len(t), fs, aux=aux, threads=1)
    bs = sc.blocks
    assert bs.fs == ref.fs == fs and bs.block_n == ref.block_n == 10 and len(bs) == len(ref) == 2000
    for name in ("mean", "scatter", "aux", "usable"):
        np.testing.assert_array_equal(getattr(bs, name), getattr(ref, name), err_msg=name)
    assert 0 < (~bs.usable).sum() <= 16  # the gaps made some blocks unusable
    assert sc.lo.tolist() == raw.astype(np.float64).min(axis=0).tolist()


@pytest.mark.parametrize("row", [0, 12_345, 20_006])
def test_a_non_finite_value_stops_the_pass_without_blocks(row):
    rec = _records(1, 20_007)
    rec["ay"][row] = np.nan
    sc = scan_columns(rec["t"], _triad(rec), [], None, chunk=1000, blocks=True, repeats=True)
    assert not sc.finite and sc.blocks is None


def test_progress_counts_each_chunk_once_in_order():
    rec = _records(2, 50_000)
    calls = []
    scan_columns(rec["t"], _triad(rec), [], None, chunk=997, progress=lambda d, n: calls.append((d, n)), threads=2)
    n_chunks = -(-50_000 // 997)
    assert [d for d, _ in calls] == list(range(1, n_chunks + 1)) and {n for _, n in calls} == {n_chunks}


def _write_npy(path, rec):
    np.save(path, rec)
    return path


def _simulated(seed: int, duration: float) -> np.ndarray:
    """A simulated session as the bench's week is stored (t f8, ax ay az f4) with temp f4."""
    sim = simulate("loetters", seed=seed, duration=duration).samples
    rec = np.empty(len(sim), dtype=[("t", "<f8"), ("ax", "<f4"), ("ay", "<f4"), ("az", "<f4"), ("temp", "<f4")])
    rec["t"], rec["temp"] = sim["t"], sim["temp"]
    rec["ax"], rec["ay"], rec["az"] = raw_triad(sim).T
    return rec


def test_read_recording_keeps_the_blocks_only_when_no_row_is_dropped(tmp_path):
    from gravcal.io.recordings import read_recording, write_recording

    rec = _simulated(4, 300.0)
    r = read_recording(_write_npy(tmp_path / "ok.npy", rec), blocks=True, exclude_filler=True)
    ref = fastdetect.block_stats(r.t, lambda c, i, j: r.raw[i:j, c], r.n_samples, r.fs, aux=r.temp)
    assert r.blocks is not None and r.blocks.fs == r.fs
    for name in ("mean", "scatter", "aux", "usable"):
        np.testing.assert_array_equal(getattr(r.blocks, name), getattr(ref, name), err_msg=name)
    assert read_recording(tmp_path / "ok.npy").blocks is None  # only when asked for

    bad = rec.copy()
    bad["ax"][1000] = np.nan
    assert read_recording(_write_npy(tmp_path / "nan.npy", bad), blocks=True).blocks is None
    clipped = rec.copy()
    top = np.quantile(clipped["ax"], 0.99)
    clipped["ax"] = np.minimum(clipped["ax"], top)  # 1 % of the samples at the rail: dropped
    r = read_recording(_write_npy(tmp_path / "clipped.npy", clipped), blocks=True)
    assert r.n_saturated > 0 and r.blocks is None
    flat = rec.copy()
    flat[5000:5400][["ax", "ay", "az"]] = flat[5000][["ax", "ay", "az"]]  # idle-sleep filler
    r = read_recording(_write_npy(tmp_path / "filler.npy", flat), blocks=True, exclude_filler=True)
    assert r.n_filler > 0 and r.blocks is None
    kept = read_recording(tmp_path / "filler.npy", blocks=True, exclude_filler=False)
    assert kept.n_filler == 0 and kept.blocks is not None
    write_recording(tmp_path / "vsupply.npy", simulate("loetters", seed=4, duration=60.0).samples)
    assert read_recording(tmp_path / "vsupply.npy", blocks=True).blocks is None  # calibrating adds the supply


def test_calibrating_with_the_reading_pass_blocks_changes_nothing(tmp_path):
    from gravcal.core.pipeline import calibrate_recording
    from gravcal.io.recordings import read_recording

    rec = read_recording(_write_npy(tmp_path / "rec.npy", _simulated(7, 600.0)), blocks=True)
    assert rec.blocks is not None
    kw = dict(temp=rec.temp, vsupply=None, fs=rec.fs, detection="blocks")
    given = calibrate_recording(rec.t, rec.raw, blocks=rec.blocks, **kw)
    own = calibrate_recording(rec.t, rec.raw, **kw)
    assert given.to_json_dict() == own.to_json_dict()
    with pytest.raises(ValueError, match="blocks are not this recording's"):
        calibrate_recording(rec.t[:-20], rec.raw[:-20], blocks=rec.blocks, temp=rec.temp[:-20], fs=rec.fs,
                            detection="blocks")
    with pytest.raises(ValueError, match="blocks are not this recording's"):
        calibrate_recording(rec.t, rec.raw, blocks=rec.blocks, temp=None, fs=rec.fs, detection="blocks")


@pytest.mark.parametrize("threads", [1, 2])
def test_the_pass_does_not_keep_the_mapped_file_resident(tmp_path, threads):
    """Every chunk's pages leave the resident set after it (the file stays in the page cache)."""
    path = _write_npy(tmp_path / "big.npy", _records(3, 1_500_000, gaps=False))  # 36 MB
    mm = np.load(path, mmap_mode="r")
    sc = scan_columns(mm["t"], _triad(mm), [mm["temp"]], None, chunk=1 << 16, repeats=True, blocks=True,
                      aux=mm["temp"], threads=threads)
    assert sc.finite and sc.blocks is not None
    assert mapped_kb(path) < 0.05 * path.stat().st_size / 1024


@pytest.mark.parametrize("layout", [">f4", "<i4", "<f8"])
def test_reading_pass_blocks_for_any_stored_type(tmp_path, layout):
    """Big-endian floats, integer counts (converted per chunk) and float64 channels: the reading pass's
    blocks equal block_stats' of the recording read."""
    from gravcal.io.recordings import read_recording

    sim = simulate("loetters", seed=2, duration=120.0).samples
    end = ">" if layout[0] == ">" else "<"
    rec = np.empty(len(sim), dtype=[("t", end + "f8"), ("ax", layout), ("ay", layout), ("az", layout),
                                    ("temp", end + "f4")])
    tri = raw_triad(sim)
    rec["t"], rec["temp"] = sim["t"], sim["temp"]
    rec["ax"], rec["ay"], rec["az"] = (np.round(tri * 1e6) if layout == "<i4" else tri).T
    r = read_recording(_write_npy(tmp_path / "x.npy", rec), blocks=True)
    ref = fastdetect.block_stats(r.t, lambda c, i, j: r.raw[i:j, c], r.n_samples, r.fs, aux=r.temp)
    assert r.blocks is not None
    for name in ("mean", "scatter", "aux", "usable"):
        np.testing.assert_array_equal(getattr(r.blocks, name), getattr(ref, name), err_msg=name)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_times_are_reported_without_numpy_warnings(bad):
    """The sampled steps before the pass meet the bad times first: no RuntimeWarning on the way to the
    pass's own finding."""
    import warnings

    rec = _records(4, 20_000, gaps=False)
    rec["t"][[5, 6]] = bad
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sc = scan_columns(rec["t"], _triad(rec), [], None, chunk=1000, blocks=True)
    assert not sc.finite and sc.blocks is None
