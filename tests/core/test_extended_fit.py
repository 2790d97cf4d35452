"""The batch path with extended terms: LottersBatch / calibrate_recording / `gravcal calibrate` for a model
such as "6+temperature_offset" store the terms (metadata "params" and "extended", what apply_extended
needs), the held-out error applies them at each window's temperature, and the CLI reports them.

Before this was fixed the batch fit's Calibration kept only K, o at the reference 25 °C, so
apply_extended and the held-out error silently used them at every temperature.

Sessions: as tests/core/test_online_extended.py. Window level: core.estimators.remount.session_windows (the
loetters scenario, window means from the sensor model's linear part) of default_model(seed,
temperature_offset=True) (~1-3 mg/°C planted) with a temperature ramp 22 -> 32 °C. Sample level (the CLI):
core.simulate of the same model, loetters motion at 50 Hz with its temperature replaced by a ramp
22 -> 34 °C, written as a CSV recording.

Statistics: the window-level coefficient check pools 3 seeds x 3 axes = 9 z-scores; |z| < 4 fails a
consistent estimator with probability 9 x 6.3e-5 < 1e-3, and the mean z² of 9 draws (chi²_9 / 9) exceeds
3.1 with probability 1e-3. The CLI check is the brief's 3σ on 3 axes (0.8 % for a consistent estimator).
"""
from __future__ import annotations

import contextlib
import dataclasses
import io
import json

import numpy as np
import pytest

from gravcal.core.calibration import Calibration
from gravcal.core.estimators.extended import apply_extended, apply_windows
from gravcal.core.estimators.lotters import LottersBatch
from gravcal.core.estimators.recursive import LottersRecursive
from gravcal.core.estimators.remount import session_windows
from gravcal.core.heldout import heldout_error, norm_error_mg
from gravcal.core.model.defaults import default_model, triad_truth

DURATION = 5400.0
EXT = "6+temperature_offset"
TERMS = ["oT_x", "oT_y", "oT_z"]


def ramp(t):
    return 22.0 + 10.0 * t / DURATION


_cache: dict = {}


def planted(seed: int):
    """(windows, info, batch fit of EXT) of a session with the term planted."""
    if seed not in _cache:
        ws, info = session_windows("loetters", seed=seed, duration=DURATION,
                                   model=default_model(seed, temperature_offset=True), temp_c=ramp)
        _cache[seed] = (ws, info, LottersBatch(EXT).fit(ws))
    return _cache[seed]


def true_coefficient(truth) -> np.ndarray:
    """c_T [raw/°C] of the planted term (exact: it is linear in T)."""
    return truth(26.0).offset - truth(25.0).offset


def rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def test_batch_fit_stores_the_terms_and_recovers_the_coefficient():
    z = []
    for seed in (0, 1, 2):
        ws, info, cal = planted(seed)
        assert cal.model == EXT and cal.converged and cal.observable, cal.message
        params, ext = cal.metadata["params"], cal.metadata["extended"]
        assert list(params) == cal.param_names and set(TERMS) <= set(params)
        assert ext["terms"] == ["temperature_offset"] and ext["t_ref_c"] == 25.0 and ext["temp_column"] == 0
        mag = ext["magnitudes"]["temperature_offset"]
        assert mag["unit"] == "mg_per_C" and set(mag["std"]) == {"x", "y", "z"}
        est = np.array([params[n] for n in TERMS])
        std = np.array([cal.std[n] for n in TERMS])
        z += ((est - true_coefficient(info["truth"])) / std).tolist()
        # the magnitude is the coefficient in mg/°C (per axis sensitivity)
        s = np.abs(np.diag(cal.sensitivity))
        np.testing.assert_allclose([mag["value"][a] for a in "xyz"], est / s * 1e3, rtol=1e-12)
    z = np.array(z)
    assert np.all(np.abs(z) < 4.0), z
    assert np.mean(z * z) < 3.1, z


def test_apply_extended_corrects_the_temperature_extremes():
    for seed in (0, 1):
        ws, info, cal = planted(seed)
        T = ws.aux[:, 0]
        noise_mg = cal.metadata["insample_rms_mg"]  # the fit's own residual level over the whole session
        c_mg = np.abs([cal.metadata["extended"]["magnitudes"]["temperature_offset"]["value"][a] for a in "xyz"])
        for sel in (T < np.quantile(T, 0.1), T > np.quantile(T, 0.9)):
            a = apply_extended(cal, ws.mean[sel], temp=T[sel])
            np.testing.assert_allclose(a, apply_windows(cal, ws.subset(np.flatnonzero(sel))), atol=1e-12)
            err = rms(np.linalg.norm(a, axis=1) - 1.0) * 1e3
            np.testing.assert_allclose(a, cal.apply(ws.mean[sel], temp=T[sel]), atol=0)  # apply applies every term
            with pytest.raises(ValueError, match="needs the temperature"):
                cal.apply(ws.mean[sel])  # never silently at the reference
            # K, o alone: off by c_T (T - 25)
            plain = rms(np.linalg.norm(cal.apply_reference(ws.mean[sel]), axis=1) - 1.0) * 1e3
            planted_mg = float(np.max(c_mg) * np.max(np.abs(T[sel] - 25.0)))
            assert err < 2.0 * noise_mg, (seed, err, noise_mg)
            assert plain > 5.0 * err and plain > 0.1 * planted_mg, (seed, plain, err, planted_mg)


def test_heldout_error_uses_the_terms():
    for seed in (0, 1):
        ws, _, cal = planted(seed)
        ext = heldout_error(ws, EXT, full_fit=cal)
        six = heldout_error(ws, "6")
        assert not ext.notes and not six.notes, (ext.notes, six.notes)
        # the term generalises to unseen (contiguous in time, hence in temperature) windows: held-out at the
        # noise level of the fit, far below order 6, which leaves c_T (T - T_mean) in every window
        assert ext.heldout_rms_mg < 2.0 * ext.insample_rms_mg, ext
        assert ext.heldout_rms_mg < 0.3 * six.heldout_rms_mg, (ext, six)
        # in-sample uses the terms too: equal to the fit's own residual RMS
        assert ext.insample_rms_mg == pytest.approx(cal.metadata["insample_rms_mg"], rel=1e-6)
        np.testing.assert_allclose(norm_error_mg(cal, ws), (np.linalg.norm(apply_windows(cal, ws), axis=1) - 1) * 1e3)


def test_recursive_calibration_carries_the_terms_and_resumes_from_them():
    ws, info, cal = planted(0)
    half = len(ws) // 2
    first = LottersBatch(EXT).fit(ws.subset(np.arange(half)))
    rec = LottersRecursive(first, EXT)
    # resumed from the batch fit's parameters, extra terms included (they are not in K, o)
    np.testing.assert_allclose(rec.p, [first.metadata["params"][n] for n in rec.names])
    out = rec.update(ws.subset(np.arange(half, len(ws))))
    assert out.metadata["extended"]["terms"] == ["temperature_offset"]
    assert set(out.metadata["extended"]["magnitudes"]["temperature_offset"]["std"]) == {"x", "y", "z"}
    later = ws.subset(np.arange(half, len(ws)))
    err = rms(np.linalg.norm(apply_windows(out, later), axis=1) - 1.0) * 1e3
    plain = rms(np.linalg.norm(out.apply_reference(later.mean), axis=1) - 1.0) * 1e3
    assert err < 2.0 * cal.metadata["insample_rms_mg"] and plain > 5.0 * err, (err, plain)


def test_an_extended_calibration_without_its_terms_is_refused():
    ws, _, cal = planted(0)
    stripped = Calibration(cal.model, cal.offset, cal.sensitivity, covariance=cal.covariance,
                           param_names=list(cal.param_names), metadata={"estimator": "old"})
    with pytest.raises(ValueError, match="carries no metadata"):
        apply_extended(stripped, cal.offset[None], temp=np.array([30.0]))
    with pytest.raises(ValueError, match="carries no metadata"):  # the window means too, not K, o alone
        apply_windows(stripped, ws)
    with pytest.raises(ValueError, match="needs the temperature"):
        apply_extended(cal, cal.offset[None])


# -- the command line ---------------------------------------------------------------------------------
CLI_DURATION, CLI_FS, CLI_SEED = 1800.0, 50.0, 3


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    from gravcal.core.scenarios import make_motion
    from gravcal.core.simulate import simulate
    from gravcal.io.recordings import write_recording

    model = default_model(CLI_SEED, temperature_offset=True)
    motion = make_motion("loetters", duration=CLI_DURATION, fs=CLI_FS, rng=CLI_SEED)
    motion = dataclasses.replace(motion, temp=22.0 + 12.0 * motion.t / CLI_DURATION)
    sim = simulate(motion, model, seed=CLI_SEED)
    path = tmp_path_factory.mktemp("ext") / "ramp.csv"
    write_recording(path, sim.samples)
    return path, model, sim


def calibrate_json(*argv) -> tuple[int, dict]:
    from gravcal.cli.main import main

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["calibrate", *map(str, argv), "--json"])
    return code, json.loads(buf.getvalue())


def test_cli_reports_the_coefficient_and_a_heldout_error_that_uses_it(recording, tmp_path):
    path, model, sim = recording
    saved = tmp_path / "cal.json"
    code, d = calibrate_json(path, "--model", EXT, "--save", saved)
    assert code == 0 and d["model"] == EXT, d["message"]
    truth = true_coefficient(lambda T: triad_truth(model, temp_c=T))
    ext = d["extended"]
    assert ext["terms"] == ["temperature_offset"] and ext["t_ref_c"] == 25.0
    est = np.array([ext["params"][n] for n in TERMS])
    std = np.array([ext["std"][n] for n in TERMS])
    assert np.all(std > 0) and [d["std"][n] for n in TERMS] == std.tolist()
    assert np.all(np.abs(est - truth) < 3.0 * std), ((est - truth) / std)
    assert set(ext["magnitudes"]["temperature_offset"]["std"]) == {"x", "y", "z"}
    code6, d6 = calibrate_json(path, "--model", "6")
    assert code6 == 0 and d6["extended"] is None
    # with the term applied the held-out error drops well below order 6's (which cannot follow the ramp)
    assert d["heldout_rms_mg"] < 0.3 * d6["heldout_rms_mg"], (d["heldout_rms_mg"], d6["heldout_rms_mg"])
    # the saved calibration corrects samples at their temperature: the still samples of the hottest tenth
    cal = Calibration.from_json(saved.read_text(encoding="utf-8"))
    from gravcal.core.samples import raw_triad

    still = sim.motion.still & (sim.motion.temp > 22.0 + 0.9 * 12.0)
    raw = raw_triad(sim.samples[still])
    a = apply_extended(cal, raw, temp=sim.samples["temp"][still].astype(float))
    plain = cal.apply_reference(raw)
    err = abs(float(np.median(np.linalg.norm(a, axis=1))) - 1.0)
    err_plain = abs(float(np.median(np.linalg.norm(plain, axis=1))) - 1.0)
    assert err < 0.2 * err_plain, (err, err_plain)


def test_cli_summary_prints_the_term(recording, capsys):
    from gravcal.cli.main import main

    path, _, _ = recording
    assert main(["calibrate", str(path), "--model", EXT]) == 0
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if ln.startswith("temperature_offset"))
    assert "mg/°C" in line and "±" in line and "25 °C" in line
