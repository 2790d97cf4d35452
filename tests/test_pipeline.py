"""calibrate_recording on simulated recordings (gravcal.core.simulate)."""
from __future__ import annotations

import json

import numpy as np
import pytest

import gravcal.core.pipeline as pipeline
from gravcal.core.calibration import Calibration
from gravcal.core.pipeline import calibrate_recording
from gravcal.core.samples import raw_triad
from gravcal.core.simulate import simulate


@pytest.fixture(scope="module")
def six_position():
    sim = simulate("six_position", seed=3, duration=600.0)
    return sim.samples["t"], raw_triad(sim.samples), sim.samples["temp"], Calibration.from_dict(sim.truth["calibration"])


def test_recovers_truth_with_heldout_report(six_position):
    t, raw, temp, truth = six_position
    rep = calibrate_recording(t, raw, temp=temp)
    cal = rep.calibration
    assert cal.converged and cal.observable, cal.message
    s = np.diag(truth.sensitivity)
    std = np.sqrt(np.diag(cal.covariance))
    err = np.r_[np.diag(cal.sensitivity) - s, cal.offset - truth.offset]
    # within 5 reported std, plus 0.02 % of 1 g for what C_e does not model (timer quantisation, ...)
    assert np.all(np.abs(err) < 5 * std + 2e-4 * np.r_[s, s]), err / std
    assert rep.n_windows == len(rep.windows) >= 20
    assert rep.heldout_rms_mg >= rep.insample_rms_mg > 0
    assert rep.heldout_rms_mg < 2.0  # mg: a correct calibration leaves |a| within noise of 1 g
    assert rep.windows.aux.shape == (rep.n_windows, 1)  # temperature kept per window
    d = rep.to_json_dict()
    for key in ("model", "offset", "sensitivity", "std", "n_windows", "heldout_rms_mg", "insample_rms_mg",
                "converged", "observable", "message", "heldout_scheme"):
        assert key in d
    assert d["heldout_scheme"] == "contiguous:5" and d["model"] == "6"
    back = json.loads(json.dumps(d))
    np.testing.assert_allclose(back["sensitivity"], cal.sensitivity)
    assert Calibration.from_dict(back["calibration"]).param_names == cal.param_names


def test_chunked_columns_give_the_same_result(six_position, monkeypatch):
    t, raw, _, _ = six_position
    ref = calibrate_recording(t, raw)
    monkeypatch.setattr(pipeline, "CHUNK", 4099)  # odd block size: the detector must stream
    cols = calibrate_recording(t, (raw[:, 0].copy(), raw[:, 1].copy(), raw[:, 2].copy()))
    assert cols.n_windows == ref.n_windows
    np.testing.assert_allclose(cols.calibration.offset, ref.calibration.offset, rtol=0, atol=1e-9)
    np.testing.assert_allclose(cols.calibration.sensitivity, ref.calibration.sensitivity, rtol=0, atol=1e-9)


def test_offsets_model_and_given_start(six_position):
    t, raw, _, truth = six_position
    start = Calibration("nominal", truth.offset + 0.002, truth.sensitivity)
    rep = calibrate_recording(t, raw, model="offsets", start=start)
    assert rep.calibration.param_names == ["o_x", "o_y", "o_z"]
    assert np.all(np.abs(rep.calibration.offset - truth.offset) < 5 * np.sqrt(np.diag(rep.calibration.covariance)) + 1e-5)


def test_bad_input_is_a_clear_error(six_position):
    t, raw, _, _ = six_position
    with pytest.raises(ValueError, match="one time per raw row"):
        calibrate_recording(t[:-1], raw)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        calibrate_recording(t, raw[:, :2])
    with pytest.raises(ValueError, match="folds"):
        calibrate_recording(t, raw, folds=1)
    rng = np.random.default_rng(0)
    moving = rng.normal(size=(6000, 3)) * 0.2 + 0.5  # all motion
    with pytest.raises(ValueError):
        calibrate_recording(np.arange(6000) / 100.0, moving)


def test_single_posture_recording_is_never_a_confident_calibration():
    sim = simulate("static", seed=4, duration=720.0)  # 12 windows of <= 60 s, one posture
    t, raw = sim.samples["t"], raw_triad(sim.samples)
    truth = Calibration.from_dict(sim.truth["calibration"])
    for start in (Calibration("nominal", truth.offset + 0.001, truth.sensitivity * 1.01), None):
        cal = calibrate_recording(t, raw, start=start).calibration
        assert not cal.observable
        assert "not observable: all 12 windows within" in cal.message
        s_ref = np.mean(np.diag(cal.sensitivity))
        assert max(cal.std[n] for n in ("s_x", "s_y", "s_z")) / s_ref > 0.03
