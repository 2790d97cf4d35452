"""Model auto adds temperature terms on top of the chosen order by the online path's rule
(core/estimators/order_fit.py _auto_extended: order.term_testability, order.is_observable_extended,
order.compare_extended), and reports each term's status otherwise.

Sessions (sample level, as tests/core/test_extended_fit.py's CLI recording): core.simulate of
default_model(seed, temperature_offset=...) (~1-3 mg/°C planted when on), loetters motion at 50 Hz for
1 h with its temperature replaced by a ramp 22 -> 34 °C.

Statistics: the control (no planted term) over CONTROL_SEEDS = 5 seeds. Adding the term needs BIC
better by 3 ln m (m ~ 300 windows: Δχ² > 17) AND a better held-out error; for a term that is truly
absent Δχ² ~ χ²_3, P(χ²_3 > 17) = 7e-4 per seed, so a correct rule fails this test with probability
< 5 x 7e-4 = 0.4 %. What 0 adds in 5 seeds shows about the rule's false-add rate: < 45 % (one-sided 95 %,
1 - 0.05^(1/5)); the BIC margin above is the real bound.
"""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from gravcal.core.model.defaults import default_model
from gravcal.core.pipeline import AUTO_EXTENDED_TERMS, calibrate_recording

DURATION, FS = 3600.0, 50.0
PLANTED_SEEDS = (0, 1)
CONTROL_SEEDS = (10, 11, 12, 13, 14)

_cache: dict = {}


def session(seed: int, planted: bool):
    """(t, raw (N, 3), temp [°C]) of a 1 h session with a temperature ramp, the term planted or not."""
    key = (seed, planted)
    if key not in _cache:
        from gravcal.core.scenarios import make_motion
        from gravcal.core.simulate import simulate
        from gravcal.io.recordings import recording_columns

        motion = make_motion("loetters", duration=DURATION, fs=FS, rng=seed)
        motion = dataclasses.replace(motion, temp=22.0 + 12.0 * motion.t / DURATION)
        c = recording_columns(simulate(motion, default_model(seed, temperature_offset=planted), seed=seed).samples)
        _cache[key] = (c["t"], np.column_stack([c["ax"], c["ay"], c["az"]]), np.asarray(c["temp"], dtype=float))
    return _cache[key]


@pytest.mark.parametrize("seed", PLANTED_SEEDS)
def test_auto_adds_a_planted_temperature_offset_and_generalises_better(seed):
    t, raw, temp = session(seed, planted=True)
    auto = calibrate_recording(t, raw, temp=temp, fs=FS)
    model = auto.calibration.model
    assert "+temperature_offset" in model, (model, auto.extended_terms)
    base = model.split("+")[0]
    st = auto.extended_terms["temperature_offset"]
    assert st["status"] == "chosen" and "BIC" in st["reason"]
    assert auto.order["model"] == model and "temperature_offset added" in auto.order["reason"]
    # the same order without the term (what auto returned before): worse on windows it was not fitted on
    plain = calibrate_recording(t, raw, temp=temp, fs=FS, model=base)
    assert plain.calibration.model == base and plain.extended_terms is None
    assert auto.heldout_rms_mg < plain.heldout_rms_mg, (auto.heldout_rms_mg, plain.heldout_rms_mg)
    # the JSON carries the terms (extended) and every term's verdict (extended_terms)
    d = json.loads(json.dumps(auto.to_json_dict()))
    assert d["model"] == model and "temperature_offset" in d["extended"]["terms"]
    assert set(d["extended_terms"]) == set(AUTO_EXTENDED_TERMS)  # every registered term auto may add
    assert d["extended_terms"]["temperature_sensitivity"]["status"] in ("chosen", "not warranted", "not observable")


def test_auto_does_not_add_an_absent_term():
    added = []
    for seed in CONTROL_SEEDS:
        t, raw, temp = session(seed, planted=False)
        rep = calibrate_recording(t, raw, temp=temp, fs=FS)
        st = rep.extended_terms
        assert st["temperature_offset"]["status"] in ("not warranted", "not observable"), (seed, st)
        if "+" in rep.calibration.model:
            added.append((seed, rep.calibration.model))
        assert not [t for t, v in st.items() if v["status"] == "chosen"], (seed, st)
    assert not added, added


def test_without_a_temperature_column_the_terms_are_untestable_and_only_time_can_explain_the_ramp():
    t, raw, temp = session(PLANTED_SEEDS[0], planted=True)
    rep = calibrate_recording(t, raw, fs=FS)
    for term in ("temperature_offset", "temperature_sensitivity"):
        assert rep.extended_terms[term]["status"] == "untestable"
        assert "no temperature" in rep.extended_terms[term]["reason"]
    assert rep.extended_terms["supply_offset"]["status"] == "untestable"  # no supply column either
    # the temperature ramps linearly in time here: a drift term is the same column, the only one auto may add
    added = set(rep.calibration.model.split("+")[1:])
    assert added <= {"offset_drift", "sensitivity_drift"}, rep.calibration.model
    same = calibrate_recording(t, raw, fs=FS, model=rep.calibration.model)
    # the same model from another linearisation point: equal to the fit's convergence tolerance (1e-7 duty = 2.5 µg)
    np.testing.assert_allclose(rep.calibration.offset, same.calibration.offset, rtol=0, atol=1e-7)
    assert rep.heldout_rms_mg == pytest.approx(same.heldout_rms_mg, rel=1e-4)
    if added:
        base = calibrate_recording(t, raw, fs=FS, model=rep.calibration.model.split("+")[0])
        assert rep.heldout_rms_mg < base.heldout_rms_mg


def test_an_explicit_order_never_adds_terms():
    t, raw, temp = session(PLANTED_SEEDS[0], planted=True)
    rep = calibrate_recording(t, raw, temp=temp, fs=FS, model="6")
    assert rep.calibration.model == "6" and rep.extended_terms is None
    assert rep.to_json_dict()["extended_terms"] is None
