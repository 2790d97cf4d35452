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
    assert rep.order["model"] == "6"
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
    # auto (the default) on six faces of an aligned sensor: 6, and why (six faces cannot show cross-axis terms)
    assert d["order"]["model"] == "6" and "6 observable" in d["order"]["reason"]
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


def test_single_posture_recording_never_gives_sensitivities():
    sim = simulate("static", seed=4, duration=720.0)  # 12 windows of <= 60 s, one posture
    t, raw = sim.samples["t"], raw_triad(sim.samples)
    truth = Calibration.from_dict(sim.truth["calibration"])
    for start in (Calibration("nominal", truth.offset + 0.001, truth.sensitivity * 1.01), None):
        # auto (the default): nothing is determined -> an error saying why, never a calibration
        with pytest.raises(pipeline.OrderNotDetermined, match=r"12 windows, 1 distinct postures.*not even the offsets"):
            calibrate_recording(t, raw, start=start)
        # an explicit order is refused with what is missing
        with pytest.raises(ValueError, match=r"model 6: the 12 windows do not determine the sensitivities: they cover "
                                             r"1 distinct posture"):
            calibrate_recording(t, raw, start=start, model="6")


def _misaligned(seed: int, misalignment: bool = True):
    from gravcal.core.model.defaults import default_model, triad_truth

    model = default_model(np.random.default_rng(seed), misalignment=misalignment)
    return model, triad_truth(model)


@pytest.fixture(scope="module")
def rich_misaligned():
    """Lötters orientation 2, theta up to 120 deg, 30 min, misaligned second chip."""
    model, truth = _misaligned(11)
    sim = simulate("loetters", model, seed=11, duration=1800.0, orientation=2, theta_max_deg=120.0)
    return sim.samples["t"], raw_triad(sim.samples), truth


def test_auto_rich_session_with_misalignment_chooses_the_full_set_and_says_why(rich_misaligned):
    from gravcal.core.estimators.inuse12 import frame_of, identifiable_part, rotation_angle_deg

    t, raw, truth = rich_misaligned
    assert rotation_angle_deg(frame_of(truth)) > 0.5  # the sensor is misaligned (its K is not symmetric)
    rep = calibrate_recording(t, raw)
    d = rep.to_json_dict()
    assert d["model"] == "9" and d["order"]["model"] == "9"
    assert "cross-axis terms chosen (BIC 9" in d["order"]["reason"] and "held-out" in d["order"]["reason"]
    cmp = d["order"]["evidence"]["comparison"]
    assert cmp["9"]["bic"] < cmp["6"]["bic"] and cmp["9"]["heldout_rms_mg"] < cmp["6"]["heldout_rms_mg"]
    json.dumps(d, allow_nan=False)  # the evidence is plain JSON
    # the identifiable part S = (K K^T)^1/2 and the offsets within 5 reported std (+0.05 % of 1 g unmodelled)
    S, o = identifiable_part(truth)
    cal = rep.calibration
    e = np.r_[[cal.sensitivity[i, j] - S[i, j] for i, j in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))],
              cal.offset - o]
    s_ref = float(np.mean(np.diag(S)))
    assert np.all(np.abs(e) < 5 * np.sqrt(np.diag(cal.covariance)) + 5e-4 * s_ref), e / np.sqrt(np.diag(cal.covariance))
    assert rep.heldout_rms_mg < 2.0 and rep.heldout_rms_mg >= rep.insample_rms_mg
    assert cal.metadata["frame_source"].startswith("R0 = I")


def test_model_12_holds_the_lab_frame_and_auto_with_a_stale_lab_chooses_12(rich_misaligned):
    from gravcal.core.estimators.inuse12 import frame_of, rotation_angle_deg

    t, raw, truth = rich_misaligned
    with pytest.raises(ValueError, match="model 12 holds the frame of a lab calibration"):
        calibrate_recording(t, raw, model="12")
    # the truth's frame, its gains 1 % off and offsets 10 mg off (the fit must improve on it to be returned)
    lab = Calibration("12", truth.offset + 0.01 * np.diag(truth.sensitivity), 1.01 * truth.sensitivity)
    rep = calibrate_recording(t, raw, model="12", lab=lab)
    cal = rep.calibration
    assert rep.verdict.status == "ok", rep.verdict.reason
    assert cal.model == "12" and rep.order["reason"].startswith("requested (--model 12)")
    assert rotation_angle_deg(frame_of(cal) @ frame_of(truth).T) < 1e-6  # the frame is held
    err = np.abs(cal.sensitivity - truth.sensitivity) / np.mean(np.diag(truth.sensitivity))
    assert err.max() < 2e-3, err  # the full K (with the lab's frame) to 0.2 % of 1 g
    # a lab calibration from before the chip moved: right frame, stale cross-axis terms -> auto updates them (12)
    stale = Calibration("12", truth.offset, np.diag(np.diag(truth.sensitivity)) @ frame_of(truth))
    rep = calibrate_recording(t, raw, lab=stale)
    assert rep.order["model"] == "12", rep.order["reason"]
    assert rotation_angle_deg(frame_of(rep.calibration) @ frame_of(stale).T) < 1e-6


def test_auto_rich_session_without_misalignment_chooses_6():
    model, truth = _misaligned(11, misalignment=False)
    sim = simulate("loetters", model, seed=11, duration=1800.0, orientation=1, theta_max_deg=180.0)
    rep = calibrate_recording(sim.samples["t"], raw_triad(sim.samples))
    assert rep.order["model"] == "6" and rep.calibration.model == "6"
    assert "cross-axis terms not warranted" in rep.order["reason"]


def test_auto_orientation1_theta30_gives_offsets_only_with_the_reason():
    model, truth = _misaligned(8)
    sim = simulate("loetters", model, seed=8, duration=1200.0, orientation=1, theta_max_deg=30.0)
    # a datasheet-like start (3 %): 30° of postures cannot give a scale-free bootstrap its scale
    start = Calibration("nominal", truth.offset + 0.003, np.diag(np.diag(truth.sensitivity)) * 1.03)
    rep = calibrate_recording(sim.samples["t"], raw_triad(sim.samples), start=start)
    cal = rep.calibration
    assert cal.model == "offsets" and cal.param_names == ["o_x", "o_y", "o_z"]
    reason = rep.to_json_dict()["order"]["reason"]
    assert "offsets observable" in reason and "not observable: 6: predicted error" in reason
    assert rep.order["evidence"]["orders"]["6"]["amplification"] > 100  # the geometry, not the window count
    # asked for 6 on the same data: refused, saying what is missing
    with pytest.raises(ValueError, match="do not determine the sensitivities"):
        calibrate_recording(sim.samples["t"], raw_triad(sim.samples), start=start, model="6")
