"""The registry of sensor-model terms: one module per physical effect, listed here once.

Everything that needs to know which effects exist -- the default model and its ``gravcal
simulate`` flags, the extended parameterizations of the estimators, the order and evidence
rules, diagnose's catalogue, planting in tests, configuration validation, rebuilding a saved
model -- enumerates :data:`REGISTRY`. A term's module declares what the term is (name, stage,
calibration view and its parameter prefix); the three lists below declare where it goes, and
everything positional is derived from them and checked at import (:func:`checked_registry`):

- ``SPECS``: the order in which ``default_model`` seeds each term's random stream. Append new
  terms at the end so that existing seeds keep drawing the same sensors.
- ``CHAIN``: each stage's terms in the order the signal passes through them (``FORWARD_POSITION``).
- ``CALIBRATION_TERMS``: the terms with a calibration view in canonical order: the order of the
  terms in extended model names and of their parameters after the base model's.
"""
from __future__ import annotations

from typing import Any

from ..base import STAGES, Term
from ..enc03j import SPECS as GYRO_SPECS
from ..spec import AUX_COLUMNS, COVARIATES, CalibrationView, Covariate, LaggedView, TermSpec
from . import (analog_lowpass, axes, colored_noise, duty_cycle, misalignment, noise, nonlinearity, offset_drift,
               quantization, ratiometric_supply, saturation, sensitivity_drift, supply_offset, temperature_offset,
               temperature_sensitivity, thermal_lag)
from .analog_lowpass import AnalogLowpass
from .axes import Axes, projection_matrix
from .colored_noise import ColoredNoise
from .duty_cycle import DutyCycle
from .misalignment import Misalignment, misaligned_axes
from .noise import Noise
from .nonlinearity import Nonlinearity
from .offset_drift import OffsetDrift
from .quantization import Timer
from .ratiometric_supply import RatiometricSupply
from .saturation import Saturation
from .sensitivity_drift import SensitivityDrift
from .supply_offset import SupplyOffset
from .temperature_offset import TemperatureOffset
from .temperature_sensitivity import TemperatureSensitivity
from .thermal_lag import ThermalLag

SPECS: tuple[TermSpec, ...] = (
    axes.SPEC,
    misalignment.SPEC,
    nonlinearity.SPEC,
    temperature_sensitivity.SPEC,
    ratiometric_supply.SPEC,
    sensitivity_drift.SPEC,
    temperature_offset.SPEC,
    offset_drift.SPEC,
    noise.SPEC,
    colored_noise.SPEC,
    analog_lowpass.SPEC,
    saturation.SPEC,
    duty_cycle.SPEC,
    quantization.SPEC,
    *GYRO_SPECS,
    supply_offset.SPEC,
    thermal_lag.SPEC,
)

CHAIN: dict[str, tuple[str, ...]] = {
    # the projection on the channel axes, ideal or misaligned (a model holds one), is the stage change
    "board": ("axes", "misalignment"),
    "channel": ("nonlinearity", "temperature_sensitivity", "ratiometric_supply", "sensitivity_drift",
                "temperature_offset", "thermal_lag", "offset_drift", "supply_offset", "noise", "colored_noise",
                "analog_lowpass", "saturation"),
    "duty": ("duty_cycle",),
    "counts": ("timer",),
    "gyro": ("gyro_sensor", "gyro_conditioning", "gyro_adc"),
}

CALIBRATION_TERMS: tuple[str, ...] = ("misalignment", "nonlinearity", "temperature_offset", "temperature_sensitivity",
                                      "offset_drift", "sensitivity_drift", "supply_offset", "thermal_lag")
"""Terms with a calibration-level view, in canonical order (the order of extended model names)."""


def checked_registry(specs: tuple[TermSpec, ...], chain: dict[str, tuple[str, ...]],
                     calibration_terms: tuple[str, ...]) -> dict[str, TermSpec]:
    """name -> spec, in ``specs`` order, once every name, class, catalogue name and parameter prefix is
    unique and ``chain`` and ``calibration_terms`` place each term exactly once; ValueError naming the clash."""
    registry: dict[str, TermSpec] = {}
    classes: dict[type[Term], str] = {}
    for spec in specs:
        if spec.name in registry:
            raise ValueError(f"term {spec.name!r} is registered twice")
        if spec.forward.name != spec.name:
            raise ValueError(f"term {spec.name!r}: its class {spec.forward.__name__} is named {spec.forward.name!r}")
        if spec.forward.stage not in STAGES:
            raise ValueError(f"term {spec.name!r}: unknown stage {spec.forward.stage!r}; stages: {', '.join(STAGES)}")
        if spec.forward in classes:
            raise ValueError(f"terms {classes[spec.forward]!r} and {spec.name!r} share the class "
                             f"{spec.forward.__name__}")
        classes[spec.forward] = spec.name
        registry[spec.name] = spec
    names = [s.catalogue_name for s in specs] + [s.name for s in specs if s.catalogue]
    for name in set(names):
        owners = [s.name for s in specs if name in (s.name, s.catalogue_name)]
        if len(owners) > 1:
            raise ValueError(f"name {name!r} names more than one term: {', '.join(owners)}")
    placed = [(stage, n) for stage, members in chain.items() for n in members]
    for stage, name in placed:
        if stage not in STAGES:
            raise ValueError(f"the forward chain has an unknown stage {stage!r}; stages: {', '.join(STAGES)}")
        if name not in registry:
            raise ValueError(f"the forward chain places {name!r}, which is not registered")
        if registry[name].forward.stage != stage:
            raise ValueError(f"the forward chain places {name!r} in stage {stage!r}; the term's stage is "
                             f"{registry[name].forward.stage!r}")
        if [n for _, n in placed].count(name) > 1:
            raise ValueError(f"the forward chain places {name!r} more than once")
    unplaced = [n for n in registry if n not in {n for _, n in placed}]
    if unplaced:
        raise ValueError(f"the forward chain does not place {', '.join(unplaced)}")
    viewed = [n for n, s in registry.items() if s.view is not None]
    for name in calibration_terms:
        if calibration_terms.count(name) > 1:
            raise ValueError(f"calibration term {name!r} is listed twice: its parameters need one position")
        if name not in viewed:
            raise ValueError(f"calibration term {name!r} is not a registered term with a calibration view")
    missing = [n for n in viewed if n not in calibration_terms]
    if missing:
        raise ValueError(f"terms with a calibration view but no position among the calibration terms: "
                         f"{', '.join(missing)}")
    prefixes: dict[str, str] = {}
    for name in viewed:
        prefix = registry[name].view.prefix
        if prefix in prefixes:
            raise ValueError(f"terms {prefixes[prefix]!r} and {name!r} share the parameter prefix {prefix!r}")
        prefixes[prefix] = name
    return registry


REGISTRY: dict[str, TermSpec] = checked_registry(SPECS, CHAIN, CALIBRATION_TERMS)

FORWARD_POSITION: dict[str, tuple[int, int]] = {
    name: (STAGES.index(stage), i) for stage, members in CHAIN.items() for i, name in enumerate(members)}
"""name -> (stage, position in the stage's chain): the order in which a model runs its terms."""

BASE_TERMS: tuple[str, ...] = ("axes", "noise", "analog_lowpass", "saturation", "duty_cycle", "timer",
                               "gyro_sensor", "gyro_conditioning", "gyro_adc")
"""Terms of every default model (the others are switched on by their group's flag)."""

GROUPS: dict[str, tuple[str, ...]] = {}
for _spec in REGISTRY.values():
    if _spec.group is not None:
        GROUPS.setdefault(_spec.group, ())
        GROUPS[_spec.group] += (_spec.name,)

CATALOGUE: dict[str, str] = {s.catalogue_name: s.name for s in REGISTRY.values() if s.diagnosed_by is not None}
"""diagnose's catalogue: effect name -> term name."""


def term_spec(name: str) -> TermSpec:
    """The registered term ``name`` (a term or catalogue name); a clear error listing the registry."""
    spec = REGISTRY.get(CATALOGUE.get(name, name))
    if spec is None:
        raise ValueError(f"unknown sensor-model term {name!r}; registered terms: {', '.join(REGISTRY)}")
    return spec


def term_from_dict(d: dict[str, Any]) -> Term:
    """The term a ``Term.to_dict`` describes; a clear error for an unknown name."""
    spec = REGISTRY.get(d.get("name"))
    if spec is None:
        raise ValueError(f"unknown sensor-model term {d.get('name')!r}; registered terms: {', '.join(REGISTRY)}")
    return spec.forward(**d.get("params", {}))


def calibration_view(name: str) -> CalibrationView:
    """The calibration view of term ``name``; a clear error for an unknown or simulation-only term."""
    spec = REGISTRY.get(name)
    if spec is None or spec.view is None:
        raise ValueError(f"unknown calibration term {name!r}; terms with a calibration view: "
                         f"{', '.join(CALIBRATION_TERMS)}")
    return spec.view


__all__ = ["REGISTRY", "SPECS", "CHAIN", "FORWARD_POSITION", "BASE_TERMS", "GROUPS", "CALIBRATION_TERMS", "CATALOGUE",
           "AUX_COLUMNS", "COVARIATES", "CalibrationView", "Covariate", "LaggedView", "TermSpec", "checked_registry",
           "term_spec", "term_from_dict", "calibration_view",
           "AnalogLowpass", "Axes", "ColoredNoise", "DutyCycle", "Misalignment", "Noise", "Nonlinearity", "OffsetDrift",
           "RatiometricSupply", "Saturation", "SensitivityDrift", "SupplyOffset", "TemperatureOffset",
           "TemperatureSensitivity", "ThermalLag", "Timer", "misaligned_axes", "projection_matrix"]
