"""supply_offset end to end: the term added as one module + its registry line, used by every consumer.

Sessions: 1 h of the Lötters scenario at 50 Hz whose supply sags under load between 3.3 and 3.0 V
(a logger's radio bursts), constant temperature, with the planted supply offset (or without it:
the control). The planted coefficients are the datasheet-scale prior (0 g duty cycle vs supply,
docs/sensor-model.md), scaled to 40 mg/V so an hour of windows determines them.
"""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from gravcal.core.calibration import Calibration
from gravcal.core.model.defaults import default_model
from gravcal.core.model.terms import CALIBRATION_TERMS, REGISTRY
from gravcal.core.pipeline import calibrate_recording
from gravcal.cli.main import main as cli_main
from seed_pool import pmap

DURATION, FS = 3600.0, 50.0
COEF_G_PER_V = np.array([0.04, -0.03, 0.035, 0.04])  # per channel ax, ay, az, ax2 [g/V]

_cache: dict = {}


def session(seed: int, planted: bool):
    """(t, raw (N, 3), vsupply [V], model) of a 1 h session with a sagging supply."""
    key = (seed, planted)
    if key not in _cache:
        from gravcal.core.scenarios import make_motion
        from gravcal.core.simulate import simulate
        from gravcal.io.recordings import recording_columns

        motion = make_motion("loetters", duration=DURATION, fs=FS, rng=seed)
        sag = 0.15 * (1.0 - np.cos(2 * np.pi * motion.t / 1500.0))  # 0 to 0.3 V
        motion = dataclasses.replace(motion, vsupply=3.3 - sag, temp=np.full(len(motion.t), 25.0))
        term = {"coef_g_per_v": COEF_G_PER_V.tolist(), "v0": 3.3} if planted else False
        model = default_model(seed, supply_offset=term)
        c = recording_columns(simulate(motion, model, seed=seed).samples)
        _cache[key] = (c["t"], np.column_stack([c["ax"], c["ay"], c["az"]]), np.asarray(c["vsupply"], dtype=float),
                       model)
    return _cache[key]


def test_supply_offset_is_registered_with_its_view():
    spec = REGISTRY["supply_offset"]
    assert "supply_offset" in CALIBRATION_TERMS
    assert spec.view.covariate == "vsupply" and spec.view.unit == "mg_per_V"
    assert spec.view.param_names() == ["oV_x", "oV_y", "oV_z"]


@pytest.mark.parametrize("seed", (0, 1))
def test_calibrate_auto_chooses_it_with_its_magnitude(seed):
    t, raw, v, model = session(seed, planted=True)
    rep = calibrate_recording(t, raw, vsupply=v, fs=FS)
    assert "supply_offset" in rep.calibration.model.split("+"), (rep.calibration.model, rep.extended_terms)
    assert rep.extended_terms["supply_offset"]["status"] == "chosen"
    mag = rep.calibration.metadata["extended"]["magnitudes"]["supply_offset"]
    assert mag["unit"] == "mg_per_V"
    # the sensor's sensitivity scales the offset per axis: truth in g/V on the triad's channels x, y, z
    truth_mg = COEF_G_PER_V[:3] * 1e3
    for i, a in enumerate("xyz"):
        assert abs(mag["value"][a] - truth_mg[i]) <= 4 * mag["std"][a] + 0.05 * abs(truth_mg[i]), (a, mag, truth_mg)
    base = calibrate_recording(t, raw, vsupply=v, fs=FS, model=rep.calibration.model.split("+")[0])
    assert rep.heldout_rms_mg < 0.7 * base.heldout_rms_mg, (rep.heldout_rms_mg, base.heldout_rms_mg)
    # applied at each sample's supply: the saved calibration corrects the still samples of the deepest sag
    cal = Calibration.from_json(rep.calibration.to_json())
    with pytest.raises(ValueError, match="needs the supply voltage"):
        cal.apply(raw[:10])
    low = v < np.quantile(v, 0.1)
    a = cal.apply(raw[low], vsupply=v[low])
    plain = cal.apply_reference(raw[low])
    err = abs(float(np.median(np.linalg.norm(a, axis=1))) - 1.0)
    err_plain = abs(float(np.median(np.linalg.norm(plain, axis=1))) - 1.0)
    assert err < 0.3 * err_plain, (err, err_plain)


def control_verdict(seed: int) -> tuple[dict, str]:
    """(extended-term verdicts, chosen model) of calibrate on a control session (computed in a worker process)."""
    t, raw, v, _ = session(seed, planted=False)
    rep = calibrate_recording(t, raw, vsupply=v, fs=FS)
    return rep.extended_terms, rep.calibration.model


def test_a_varying_supply_without_the_effect_does_not_get_it():
    chosen = []
    seeds = (10, 11, 12, 13)
    for seed, (terms, model) in zip(seeds, pmap(control_verdict, [(seed,) for seed in seeds])):
        assert terms["supply_offset"]["status"] in ("not warranted", "not observable"), terms
        chosen += [(seed, model)] if "supply_offset" in model else []
    assert not chosen, chosen


def test_without_a_supply_column_it_is_untestable_and_says_why():
    t, raw, v, _ = session(0, planted=True)
    rep = calibrate_recording(t, raw, fs=FS)
    st = rep.extended_terms["supply_offset"]
    assert st["status"] == "untestable" and "supply voltage" in st["reason"]
    flat = calibrate_recording(t, raw, vsupply=np.full_like(v, 3.3), fs=FS)
    assert "no supply voltage spread" in flat.extended_terms["supply_offset"]["reason"]


def test_explicit_model_needs_the_supply_column():
    t, raw, v, _ = session(0, planted=True)
    with pytest.raises(ValueError, match="need a supply voltage column"):
        calibrate_recording(t, raw, fs=FS, model="6+supply_offset")


def _write_csv(path, t, raw, v):
    with open(path, "w", encoding="utf-8") as f:
        f.write("t,ax,ay,az,vsupply\n")
        for row in zip(t, raw[:, 0], raw[:, 1], raw[:, 2], v):
            f.write(",".join(f"{x:.10g}" for x in row) + "\n")


def test_cli_calibrate_and_diagnose_name_it(tmp_path, capsys):
    t, raw, v, _ = session(0, planted=True)
    path = tmp_path / "sag.csv"
    _write_csv(path, t, raw, v)
    assert cli_main(["calibrate", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert "supply_offset" in out["model"]
    assert cli_main(["diagnose", str(path), "--json", "--replicas", "4"]) == 0
    d = json.loads(capsys.readouterr().out)
    found = {f["effect"]: f for f in d["findings"]}
    assert "supply_offset" in found, d["findings"]
    mag = found["supply_offset"]["magnitude"]
    assert mag["unit"] == "mg_per_V"
    for i, a in enumerate("xyz"):
        assert math.isclose(mag["value"][a], COEF_G_PER_V[i] * 1e3, rel_tol=0.25), mag


def test_a_vsupply_column_with_bad_values_is_handled_like_temp(tmp_path, capsys):
    t, raw, v, _ = session(0, planted=True)
    n = 20_000
    few = v[:n].copy()
    few[[100, 200]] = [np.nan, 99.0]  # one NaN, one out of range: both dropped with a warning
    path = tmp_path / "few.csv"
    _write_csv(path, t[:n], raw[:n], few)
    from gravcal.io.recordings import read_recording

    rec = read_recording(path)
    assert rec.n_samples == n - 2 and rec.vsupply is not None and np.all(np.isfinite(rec.vsupply))
    assert any("vsupply" in w for w in rec.warnings), rec.warnings
    most = np.full(n, np.nan)
    path2 = tmp_path / "most.csv"
    _write_csv(path2, t[:n], raw[:n], most)
    assert cli_main(["calibrate", str(path2)]) == 2
    err = capsys.readouterr().err
    assert "too many to drop" in err and "vsupply" in err and "line" in err


def test_an_unknown_term_lists_the_registry():
    from gravcal.core.estimators.extended import extended_class
    from gravcal.daemon.config import ConfigError, parse_config

    with pytest.raises(ValueError) as exc:
        extended_class("6+supply_ofset")
    assert all(t in str(exc.value) for t in CALIBRATION_TERMS)
    with pytest.raises(ConfigError) as cexc:
        parse_config({"estimator": {"extended_terms": "supply_ofset"}}, "test.toml")
    assert "supply_offset" in str(cexc.value) and "temperature_offset" in str(cexc.value)
