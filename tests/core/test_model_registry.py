"""The term registry derives every position from its declared lists and refuses a clash at import."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gravcal.core.model import SensorModel
from gravcal.core.model.defaults import default_model
from gravcal.core.model.spec import CalibrationView, LaggedView, per_sensitivity
from gravcal.core.model.terms import (CALIBRATION_TERMS, CHAIN, GROUPS, REGISTRY, SPECS, checked_registry,
                                      term_from_dict)


def spec_named(name):
    return next(s for s in SPECS if s.name == name)


def with_view(name, **changes):
    """SPECS with term ``name``'s calibration view changed."""
    spec = spec_named(name)
    changed = dataclasses.replace(spec, view=dataclasses.replace(spec.view, **changes))
    return tuple(changed if s is spec else s for s in SPECS)


def test_the_declared_lists_give_the_registry():
    assert list(checked_registry(SPECS, CHAIN, CALIBRATION_TERMS)) == [s.name for s in SPECS] == list(REGISTRY)


def test_a_term_registered_twice_is_refused():
    with pytest.raises(ValueError, match="term 'supply_offset' is registered twice"):
        checked_registry(SPECS + (spec_named("supply_offset"),), CHAIN, CALIBRATION_TERMS)


def test_a_shared_parameter_prefix_is_refused():
    prefix = REGISTRY["temperature_offset"].view.prefix
    with pytest.raises(ValueError, match=f"'temperature_offset' and 'supply_offset' share the parameter prefix "
                                         f"'{prefix}'"):
        checked_registry(with_view("supply_offset", prefix=prefix), CHAIN, CALIBRATION_TERMS)


def test_a_duplicate_parameter_position_is_refused():
    with pytest.raises(ValueError, match="'supply_offset' is listed twice"):
        checked_registry(SPECS, CHAIN, CALIBRATION_TERMS + ("supply_offset",))


def test_a_calibration_term_without_a_position_is_refused():
    with pytest.raises(ValueError, match="no position among the calibration terms: thermal_lag"):
        checked_registry(SPECS, CHAIN, tuple(t for t in CALIBRATION_TERMS if t != "thermal_lag"))
    with pytest.raises(ValueError, match="'noise' is not a registered term with a calibration view"):
        checked_registry(SPECS, CHAIN, CALIBRATION_TERMS + ("noise",))


def test_the_forward_chain_places_every_term_once_in_its_stage():
    channel = CHAIN["channel"]
    with pytest.raises(ValueError, match="does not place noise"):
        checked_registry(SPECS, {**CHAIN, "channel": tuple(t for t in channel if t != "noise")}, CALIBRATION_TERMS)
    with pytest.raises(ValueError, match="places 'noise' more than once"):
        checked_registry(SPECS, {**CHAIN, "channel": channel + ("noise",)}, CALIBRATION_TERMS)
    with pytest.raises(ValueError, match="places 'timer' in stage 'channel'; the term's stage is 'counts'"):
        checked_registry(SPECS, {**CHAIN, "channel": channel + ("timer",)}, CALIBRATION_TERMS)


def test_a_catalogue_name_naming_another_term_is_refused():
    spec = spec_named("colored_noise")
    clash = dataclasses.replace(spec, catalogue="noise")
    with pytest.raises(ValueError, match="name 'noise' names more than one term"):
        checked_registry(tuple(clash if s is spec else s for s in SPECS), CHAIN, CALIBRATION_TERMS)


def test_a_model_runs_its_terms_in_chain_order_whatever_order_they_come_in():
    model = default_model(3, **{g: True for g in GROUPS})
    chain = [n for stage in CHAIN.values() for n in stage]
    names = [t.name for t in model.terms]
    assert names == sorted(names, key=chain.index)
    assert [t.name for t in SensorModel(model.terms[::-1]).terms] == names


def test_a_saved_model_rebuilds_every_registered_term():
    for spec in SPECS:
        term = spec.prior(np.random.default_rng(1))
        back = term_from_dict(term.to_dict())
        assert type(back) is spec.forward
        assert back.to_dict() == term.to_dict()
    with pytest.raises(ValueError, match="unknown sensor-model term 'fog'"):
        term_from_dict({"name": "fog", "params": {}})


def test_a_lag_is_the_views_class_not_a_string():
    lagged = [t for t in CALIBRATION_TERMS if REGISTRY[t].view.lagged]
    assert lagged == ["thermal_lag"]
    view = REGISTRY["thermal_lag"].view
    assert isinstance(view, LaggedView) and view.on_offset and not view.per_window
    assert view.deviation_key == "temp_lagged" and view.profiled > 0
    assert all(REGISTRY[t].view.per_window for t in CALIBRATION_TERMS if t not in lagged)
    with pytest.raises(ValueError, match="acts_on must be one of"):
        CalibrationView(prefix="oX", acts_on="lagged_offset", covariate="temp", unit="mg_per_C",
                        report_factor=per_sensitivity(1e3))
    with pytest.raises(ValueError, match="a lag needs a recorded covariate"):
        LaggedView(prefix="oX", covariate="time", unit="mg_per_h", report_factor=per_sensitivity(1e3), profiled=60.0)
