"""The registry of sensor-model terms: one module per physical effect, listed here once.

Everything that needs to know which effects exist -- the default model and its ``gravcal
simulate`` flags, the extended parameterizations of the estimators, the order and evidence
rules, diagnose's catalogue, planting in tests, configuration validation -- enumerates
:data:`REGISTRY`. Adding an effect is adding its module and its line below.

The order of the lines is the order in which ``default_model`` seeds each term's random stream:
append new terms at the end so that existing seeds keep drawing the same sensors.
"""
from __future__ import annotations

from ..enc03j import SPECS as GYRO_SPECS
from ..spec import AUX_COLUMNS, COVARIATES, CalibrationView, Covariate, TermSpec
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

REGISTRY: dict[str, TermSpec] = {spec.name: spec for spec in (
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
)}

BASE_TERMS: tuple[str, ...] = ("axes", "noise", "analog_lowpass", "saturation", "duty_cycle", "timer",
                               "gyro_sensor", "gyro_conditioning", "gyro_adc")
"""Terms of every default model (the others are switched on by their group's flag)."""

GROUPS: dict[str, tuple[str, ...]] = {}
for _spec in REGISTRY.values():
    if _spec.group is not None:
        GROUPS.setdefault(_spec.group, ())
        GROUPS[_spec.group] += (_spec.name,)

CALIBRATION_TERMS: tuple[str, ...] = tuple(sorted((s.name for s in REGISTRY.values() if s.view is not None),
                                                 key=lambda n: REGISTRY[n].view.rank))
"""Terms with a calibration-level view, in canonical order (the order of extended model names)."""

CATALOGUE: dict[str, str] = {s.catalogue_name: s.name for s in REGISTRY.values() if s.diagnosed_by is not None}
"""diagnose's catalogue: effect name -> term name."""


def term_spec(name: str) -> TermSpec:
    """The registered term ``name`` (a term or catalogue name); a clear error listing the registry."""
    spec = REGISTRY.get(CATALOGUE.get(name, name))
    if spec is None:
        raise ValueError(f"unknown sensor-model term {name!r}; registered terms: {', '.join(REGISTRY)}")
    return spec


def calibration_view(name: str) -> CalibrationView:
    """The calibration view of term ``name``; a clear error for an unknown or simulation-only term."""
    spec = REGISTRY.get(name)
    if spec is None or spec.view is None:
        raise ValueError(f"unknown calibration term {name!r}; terms with a calibration view: "
                         f"{', '.join(CALIBRATION_TERMS)}")
    return spec.view


__all__ = ["REGISTRY", "BASE_TERMS", "GROUPS", "CALIBRATION_TERMS", "CATALOGUE", "AUX_COLUMNS", "COVARIATES",
           "CalibrationView", "Covariate", "TermSpec", "term_spec", "calibration_view",
           "AnalogLowpass", "Axes", "ColoredNoise", "DutyCycle", "Misalignment", "Noise", "Nonlinearity", "OffsetDrift",
           "RatiometricSupply", "Saturation", "SensitivityDrift", "SupplyOffset", "TemperatureOffset",
           "TemperatureSensitivity", "ThermalLag", "Timer", "misaligned_axes", "projection_matrix"]
