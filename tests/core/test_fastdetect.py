"""core.fastdetect: offline detection on block statistics against the streaming detectors."""
from __future__ import annotations

import numpy as np
import pytest

import gravcal.core.fastdetect as fastdetect
from gravcal.core import detectors
from gravcal.core.calibration import Calibration
from gravcal.core.pipeline import calibrate_recording
from gravcal.core.samples import raw_triad
from gravcal.core.simulate import simulate
from tests.support.smaps import mapped_kb
from gravcal.core.accelerator import is_native

NATIVE = is_native(fastdetect._kernels)

FS = 100.0
# Boundary tolerance: the block detector decides per 0.1 s block on the same filter chain
# sampled at 10 Hz; nearly all its edges land within one block of the streaming detector's,
# and where the detection signal hovers at the threshold an edge may move by a few blocks.
EDGE_TYPICAL_S = 0.15  # 95 % of the edges: one block, plus the variance detector's 0.25 s guard rounded to blocks
EDGE_MAX_S = 1.0


@pytest.fixture(scope="module", params=["six_position", "loetters"])
def session(request):
    sim = simulate(request.param, seed=1, duration=600.0)
    return (sim.samples["t"], raw_triad(sim.samples), sim.samples["temp"],
            Calibration.from_dict(sim.truth["calibration"]))


def _match(a, b):
    """For each window of a, the window of b overlapping it most (index, overlap in samples)."""
    idx, ov = [], []
    for s, e in zip(a.start, a.end):
        o = np.minimum(e, b.end) - np.maximum(s, b.start)
        j = int(np.argmax(o))
        idx.append(j)
        ov.append(int(o[j]))
    return np.array(idx), np.array(ov)


@pytest.mark.parametrize("method", ["lotters", "variance"])
def test_same_windows_as_the_streaming_detector(session, method):
    t, raw, _, truth = session
    ref = detectors.detect(t, raw, method=method, to_g=truth)
    got = fastdetect.detect(t, raw, method=method, to_g=truth)
    assert len(ref) >= 20
    assert abs(len(got) - len(ref)) <= max(1, len(ref) // 50)
    j, ov = _match(ref, got)
    assert np.all(ov > 0), "a streaming window has no block window overlapping it"
    edges = np.abs(np.r_[got.start[j] - ref.start, got.end[j] - ref.end]) / FS
    assert np.quantile(edges, 0.95) <= EDGE_TYPICAL_S, np.sort(edges)[-10:]
    assert edges.max() <= EDGE_MAX_S, np.sort(edges)[-10:]
    # windows are still in both: their means agree within a few noise std of the mean
    sd_mean = np.sqrt(np.diagonal(ref.cov_of_mean, axis1=1, axis2=2))
    assert np.all(np.abs(got.mean[j] - ref.mean) < 10 * sd_mean + 1e-5)


def test_window_statistics_are_those_of_the_samples(session):
    t, raw, temp, truth = session
    ws = fastdetect.detect(t, raw, to_g=truth, aux=temp)
    assert len(ws) > 10
    for w in range(len(ws)):
        x = raw[ws.start[w]:ws.end[w]]
        assert ws.n[w] == x.shape[0]
        # float64 sums of deviations from each block's first sample, then from the window's first
        # block: ~1e-15 here; 1e-9 of a duty cycle is 10 ng, the noise of a window mean ~1e-5
        np.testing.assert_allclose(ws.mean[w], x.mean(axis=0), rtol=0, atol=1e-9)
        np.testing.assert_allclose(ws.cov[w], np.cov(x.T), rtol=1e-4, atol=1e-12 * np.abs(ws.cov[w]).max())
        np.testing.assert_allclose(ws.aux[w, 0], temp[ws.start[w]:ws.end[w]].astype(float).mean(), rtol=1e-12)
        assert ws.t[w] == pytest.approx(0.5 * (t[ws.start[w]] + t[ws.end[w] - 1]))


def test_block_statistics_do_not_depend_on_chunks_or_threads(session, monkeypatch):
    t, raw, _, _ = session
    n = raw.shape[0]
    a = fastdetect.block_stats(t, lambda c, i, j: raw[i:j, c], n, FS, threads=1)
    monkeypatch.setattr(fastdetect, "CHUNK_BLOCKS", 37)
    b = fastdetect.block_stats(t, lambda c, i, j: raw[i:j, c], n, FS, threads=2)
    # each block's sums are computed from its own samples alone: equal bit for bit
    np.testing.assert_array_equal(a.usable, b.usable)
    np.testing.assert_array_equal(a.mean, b.mean)
    np.testing.assert_array_equal(a.scatter, b.scatter)
    wa = fastdetect.detect_blocks(a, t)
    wb = fastdetect.detect_blocks(b, t)
    np.testing.assert_array_equal(wa.start, wb.start)
    np.testing.assert_array_equal(wa.end, wb.end)


def test_nonfinite_samples_and_time_gaps_break_windows():
    sim = simulate("six_position", seed=2, duration=300.0)
    t, raw = sim.samples["t"].copy(), raw_triad(sim.samples).copy()
    truth = Calibration.from_dict(sim.truth["calibration"])
    clean = fastdetect.detect(t, raw, to_g=truth)
    w = int(np.argmax(clean.n))  # the longest window: poison its middle
    mid = int((clean.start[w] + clean.end[w]) // 2)
    raw[mid, 1] = np.nan
    gap_at = int(clean.start[w] + (clean.end[w] - clean.start[w]) // 4)
    t[gap_at:] += 5.0  # a 5 s dropout
    ws = fastdetect.detect(t, raw, to_g=truth)
    for s, e in zip(ws.start, ws.end):
        assert not (s <= mid < e), "a window holds a NaN sample"
        assert not (s < gap_at < e), "a window spans a time gap"
    assert np.all(np.isfinite(ws.mean)) and np.all(np.isfinite(ws.cov))


@pytest.mark.parametrize("seed", [3, 4])
def test_calibration_agrees_with_the_streaming_path(seed):
    sim = simulate("six_position", seed=seed, duration=600.0)
    t, raw = sim.samples["t"], raw_triad(sim.samples)
    stream = calibrate_recording(t, raw, detection="stream")
    blocks = calibrate_recording(t, raw, detection="blocks")
    a, b = stream.calibration, blocks.calibration
    assert b.model == a.model and b.converged and b.observable
    std = np.sqrt(np.diag(a.covariance))
    diff = np.r_[np.diag(b.sensitivity) - np.diag(a.sensitivity), b.offset - a.offset]
    # the two window sets share most samples: their fits differ by well under one std
    assert np.all(np.abs(diff) < std), diff / std
    # held-out error not worse (a 10 % margin: the folds hold slightly different windows)
    assert blocks.heldout_rms_mg <= 1.1 * stream.heldout_rms_mg + 0.05


def test_release_mapped_keeps_the_data(tmp_path):
    x = np.arange(1 << 20, dtype=np.float64)
    path = tmp_path / "x.npy"
    np.save(path, x)
    mm = np.load(path, mmap_mode="r")
    fastdetect.release_mapped(mm, 0, mm.shape[0])
    np.testing.assert_array_equal(mm, x)  # faulted back in from the page cache
    y = x.copy()
    fastdetect.release_mapped(y, 0, y.shape[0])  # private memory: must be a no-op
    np.testing.assert_array_equal(y, x)


@pytest.mark.parametrize("layout", ["records", "columns"])
def test_row_releaser_drops_every_field_once(tmp_path, layout):
    """Fields of the same records (a structured .npy) are released through one of them; separate
    columns of one mapping each through their own range."""
    n = 1 << 20
    path = tmp_path / "rec.npy"
    if layout == "records":
        rec = np.zeros(n, dtype=[("t", "<f8"), ("ax", "<f4"), ("ay", "<f4"), ("az", "<f4")])
        rec["t"], rec["az"] = np.arange(n), 1.0
        np.save(path, rec)
        mm = np.load(path, mmap_mode="r")
        arrays = [mm["t"], mm["ax"], mm["az"]]
    else:
        np.save(path, np.vstack([np.arange(n, dtype=np.float64), np.ones(n)]))
        mm = np.load(path, mmap_mode="r")
        arrays = [mm[0], mm[1]]
    total = sum(float(a.sum()) for a in arrays)  # every page resident
    before = mapped_kb(path)
    assert before > 0.9 * path.stat().st_size / 1024
    fastdetect.row_releaser(arrays)(0, n)
    assert mapped_kb(path) < 0.02 * before
    assert sum(float(a.sum()) for a in arrays) == total  # faulted back in from the page cache


def test_bad_arguments_are_named():
    t = np.arange(1000) / FS
    raw = np.ones((1000, 3))
    with pytest.raises(ValueError, match="method"):
        fastdetect.detect(t, raw, method="nope")
    with pytest.raises(ValueError, match="raw"):
        fastdetect.detect(t, raw[:, :2])
    with pytest.raises(TypeError, match="Calibration"):
        fastdetect.detect(t, raw, to_g=lambda r: r)
    with pytest.raises(ValueError, match="detection"):
        calibrate_recording(t, raw, detection="nope")


def test_auto_detection_uses_blocks_for_long_recordings(monkeypatch):
    import gravcal.core.pipeline as pipeline

    sim = simulate("six_position", seed=3, duration=600.0)
    t, raw = sim.samples["t"], raw_triad(sim.samples)
    blocks = calibrate_recording(t, raw, detection="blocks")
    stream = calibrate_recording(t, raw, detection="stream")
    assert not np.array_equal(blocks.windows.start, stream.windows.start)  # the two paths are distinguishable
    monkeypatch.setattr(pipeline, "BLOCKS_MIN_SAMPLES", raw.shape[0])
    np.testing.assert_array_equal(calibrate_recording(t, raw).windows.start, blocks.windows.start)
    monkeypatch.setattr(pipeline, "BLOCKS_MIN_SAMPLES", raw.shape[0] + 1)
    np.testing.assert_array_equal(calibrate_recording(t, raw).windows.start, stream.windows.start)


@pytest.mark.parametrize("kind", ["highpass", "lowpass"])
@pytest.mark.parametrize("fs, corner", [(10.0, 0.5), (10.0, 0.1), (100.0, 0.5), (2.0, 0.9), (10.0, 4.0)])
def test_closed_form_butterworth_is_scipys(kind, fs, corner):
    from scipy import signal

    ref = signal.butter(2, corner, kind, fs=fs, output="sos")
    np.testing.assert_allclose(fastdetect.butter_sos(2, corner, kind, fs), ref, rtol=0, atol=1e-14)
    # the rest state: filtering a constant from it gives that constant's steady-state output at once
    zi = fastdetect.sos_rest_state(ref)
    np.testing.assert_allclose(zi, signal.sosfilt_zi(ref), rtol=1e-9, atol=1e-12)
    y, _ = signal.sosfilt(ref, np.full(50, 3.0), zi=3.0 * zi)
    dc = np.prod([(s[0] + s[1] + s[2]) / (s[3] + s[4] + s[5]) for s in ref])
    np.testing.assert_allclose(y, 3.0 * dc, rtol=0, atol=1e-12)


def test_rest_state_of_a_cascade_is_scipys():
    from scipy import signal

    sos = signal.butter(4, 0.5, "highpass", fs=10.0, output="sos")
    np.testing.assert_allclose(fastdetect.sos_rest_state(sos), signal.sosfilt_zi(sos), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fastdetect.butter_sos(4, 0.5, "highpass", 10.0), sos, rtol=0, atol=0)


@pytest.mark.skipif(not NATIVE, reason="the numpy references filter with scipy.signal")
def test_block_calibration_does_not_import_scipy_signal(tmp_path):
    """scipy.signal's package import is most of `gravcal calibrate`'s start-up: the block path filters
    with its own compiled kernel and loads neither scipy.signal nor SciPy's sosfilt extension."""
    out = _in_a_child(tmp_path, (
        "from gravcal.core.fastdetect import detect\n"
        "ws = detect(t, raw)\n"
        "print(len(ws), *(m in sys.modules for m in ('scipy.signal', 'scipy.signal._sosfilt')),\n"
        "      any(m.split('.')[0] == 'scipy' for m in sys.modules))\n"
    ))
    assert int(out[0]) > 0
    assert out[1:] == ["False", "False", "False"], "the block detector loaded scipy (or scipy.signal, its sosfilt kernel)"


def test_calibration_runs_blas_single_threaded(monkeypatch):
    """Every BLAS product of a calibration is small: OpenBLAS threads only spin (the week's fit 2.6x slower)."""
    import threadpoolctl  # a dependency of gravcal (pyproject.toml)
    import gravcal.core.pipeline as pipeline

    seen = []
    fit = pipeline._fit_order

    def spy(*args, **kwargs):
        seen.extend(p["num_threads"] for p in threadpoolctl.threadpool_info() if p["user_api"] == "blas")
        return fit(*args, **kwargs)

    monkeypatch.setattr(pipeline, "_fit_order", spy)
    sim = simulate("six_position", seed=3, duration=600.0)
    before = [p["num_threads"] for p in threadpoolctl.threadpool_info() if p["user_api"] == "blas"]
    report = calibrate_recording(sim.samples["t"], raw_triad(sim.samples), detection="blocks")
    assert report.calibration.converged
    assert seen and all(n == 1 for n in seen), seen
    assert [p["num_threads"] for p in threadpoolctl.threadpool_info() if p["user_api"] == "blas"] == before


@pytest.mark.skipif(not NATIVE, reason="the numpy references filter with scipy.signal")
def test_block_calibration_imports_neither_scipy_optimize_nor_linalg(tmp_path):
    """Their imports cost ~0.6 CPU-s, a tenth of a week's calibration: the default path needs neither."""
    out = _in_a_child(tmp_path, (
        "from gravcal.core.pipeline import calibrate_recording\n"
        "rep = calibrate_recording(t, raw, detection='blocks')\n"
        "print(rep.n_windows, *(m in sys.modules for m in ('scipy.optimize', 'scipy.linalg')))\n"
    ))
    assert int(out[0]) > 0
    assert out[1:] == ["False", "False"], "calibration imported scipy.optimize / scipy.linalg"


@pytest.mark.parametrize("chunk_blocks", [7, 4096])
def test_blocks_with_a_bad_time_step_are_unusable_at_chunk_borders_too(monkeypatch, chunk_blocks):
    """A block is usable only if the step into each of its samples (the first one's from the previous
    block) is in (0, 1.5/fs]: checked against that rule written out over the whole recording."""
    monkeypatch.setattr(fastdetect, "CHUNK_BLOCKS", chunk_blocks)
    fs, B = 100.0, 10
    rng = np.random.default_rng(3)
    n = 20 * chunk_blocks * B + 13
    t = np.arange(n) / fs
    raw = rng.normal(size=(n, 3))
    chunk = chunk_blocks * B
    for at in (25, chunk, chunk + 1, 3 * chunk - 1, 5 * chunk + 4, n - 20):  # chunk borders and inside
        t[at:] += 0.02  # a gap: 0.03 s > 1.5 / fs
    t[7 * chunk:] -= 0.5  # time going backwards at a chunk border
    dt = np.concatenate([[1.0 / fs], np.diff(t)])
    good = (dt > 0) & (dt <= 1.5 / fs)
    nb = n // B
    want = good[:nb * B].reshape(nb, B).all(axis=1)
    for threads in (1, 2):
        bs = fastdetect.block_stats(t, lambda c, i, j: raw[i:j, c], n, fs, block_n=B, threads=threads)
        np.testing.assert_array_equal(bs.usable, want)
    assert want[0] and (~want).sum() >= 6


def _in_a_child(tmp_path, body: str) -> list[str]:
    """Run ``body`` in a fresh interpreter (its imports are the test's subject) with ``t`` and ``raw`` of a
    six-position session loaded (the simulator imports scipy.signal: it runs here, not in the child);
    returns the words it printed."""
    import subprocess
    import sys

    s = simulate("six_position", seed=2, duration=300.0).samples
    np.save(tmp_path / "t.npy", s["t"])
    np.save(tmp_path / "raw.npy", raw_triad(s))
    code = ("import sys, numpy as np\n"
            f"t, raw = np.load({str(tmp_path / 't.npy')!r}), np.load({str(tmp_path / 'raw.npy')!r})\n" + body)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()


def test_windows_are_the_still_runs_including_those_at_the_ends():
    """With no guard and no length limits, the windows are exactly the runs of still blocks, found
    by a plain loop here (runs touching the first and the last block too)."""
    rng = np.random.default_rng(11)
    n, B = 4000, 10
    t = np.arange(n) / FS
    raw = rng.normal(size=(n, 3))
    bs = fastdetect.block_stats(t, lambda c, i, j: raw[i:j, c], n, FS, block_n=B)
    masks = [np.ones(len(bs), bool), np.zeros(len(bs), bool), rng.random(len(bs)) < 0.7, rng.random(len(bs)) < 0.3]
    masks[2][:5] = masks[2][-5:] = True
    for still in masks:
        runs, start = [], None
        for b, s in enumerate(list(still) + [False]):
            if s and start is None:
                start = b
            elif not s and start is not None:
                runs.append((start, b))
                start = None
        ws = fastdetect.windows_from_still(bs, still, t, min_duration_s=0.0, max_duration_s=None, guard_s=0.0)
        assert list(zip(ws.start // B, ws.end // B)) == runs


@pytest.mark.parametrize("threaded", [False, True])
def test_window_times_gathered_beside_the_sums_are_the_samples_times(tmp_path, session, monkeypatch, threaded):
    # the window times come from a memory-mapped t whose pages were released (as after the reading
    # pass), on a second thread while the sums' kernel runs or on this one: the same WindowSet
    t, raw, temp, truth = session
    path = tmp_path / "t.npy"
    np.save(path, np.asarray(t, dtype=np.float64) + 1.7e9)  # unix times: the sum of two rounds
    tm = np.load(path, mmap_mode="r")
    fs = fastdetect.estimate_fs(t)
    bs = fastdetect.block_stats(tm, lambda c, i, j: raw[i:j, c], raw.shape[0], fs, aux=temp)
    still = fastdetect.lotters_still(bs, truth)
    monkeypatch.setattr(fastdetect, "GATHER_THREAD_MIN", 0 if threaded else 1 << 62)
    fastdetect.release_mapped(tm, 0, tm.shape[0])
    ws = fastdetect.windows_from_still(bs, still, tm)
    assert len(ws) > 10
    tt = np.load(path)
    np.testing.assert_array_equal(ws.t, 0.5 * (tt[ws.start] + tt[ws.end - 1]))
    monkeypatch.setattr(fastdetect, "GATHER_THREAD_MIN", 1 << 62 if threaded else 0)
    other = fastdetect.windows_from_still(bs, still, tm)
    for name in ("mean", "cov", "n", "t", "aux", "start", "end"):
        np.testing.assert_array_equal(getattr(ws, name), getattr(other, name))
    with pytest.raises(IndexError):  # an error in the gathering thread reaches the caller
        fastdetect.windows_from_still(bs, still, tm[: tm.shape[0] // 2])
