"""Datasheet defaults, the default model, and the calibration-level truth of a model.

Every constant names its source; ``docs/sensor-model.md`` lists them with the status of each
("verified" against a datasheet text, "as recalled" = not verified, or "assumed" = design choice).
Spreads: where the datasheet gives min/max, a part is drawn from a normal with the typical
value as mean and (max - min)/6 as standard deviation (min/max ~ +-3 sigma), clipped to min/max.
Effects given as "+-typ" with no sign are drawn zero-mean with sigma = typ.
"""
from __future__ import annotations

from typing import Any, Callable

import numpy as np

from ..calibration import Calibration
from ..samples import TRIAD
from .adxl210 import (
    AnalogLowpass, Axes, ColoredNoise, DutyCycle, Misalignment, Noise, Nonlinearity, OffsetDrift,
    RatiometricSupply, Saturation, SensitivityDrift, TemperatureOffset, TemperatureSensitivity, Timer,
    projection_matrix,
)
from .base import Context, SensorModel, Term
from .enc03j import GyroADC, GyroConditioning, GyroSensor

# --- ADXL210E (Analog Devices datasheet, rev. 0) -----------------------------------------
SENS_TYP = 0.04  # duty/g; verified: A(g) = (T1/T2 - 0.5)/4 %
SENS_LIMITS = (0.032, 0.048)  # duty/g min/max; as recalled (+-20 %)
D0_TYP = 0.50  # zero-g duty cycle; verified: "0 g = 50 % duty cycle"
D0_LIMITS = (0.42, 0.58)  # as recalled (+-2 g of offset at 4 %/g)
NOISE_DENSITY_UG = 200.0  # µg/√Hz; verified for ADXL210E (ADXL202/210 rev. B: 500)
RANGE_G = 10.0  # verified: full scale +-10 g
RSET_OHM = 625e3  # assumed: T2 = RSET/125 Mohm (verified formula) = 5 ms, inside 0.5-10 ms (verified)
RSET_TOL = 0.01  # assumed: 1 % resistor
CX_UF = 0.47  # assumed filter capacitor: f_3dB = 5 µF / C = 10.6 Hz (5 µF/C as recalled; = 1/(2 pi 32 kohm C))
CX_TOL = 0.10  # assumed: 10 % ceramic capacitor
ALIGN_DEG = 1.0  # +-1° in-die alignment error; as recalled (cross-axis sensitivity +-2 %)
CHIP_PLACEMENT_DEG = 0.5  # assumed: package placement on the PCB
MOUNT_B_DEG = 2.0  # assumed: chip B's hand-soldered edge carrier
TEMP_OFFSET_G_PER_C = 2e-3  # +-2 mg/°C zero-g drift; as recalled
TEMP_SENS_PER_C = 1e-4  # +-0.01 %/°C (+-0.5 % over 25..75 °C); as recalled
NONLIN_PCT_FS = 0.2  # +-0.2 % of full scale; as recalled
T2_TEMPCO_PPM = 100.0  # assumed oscillator tempco; cancels in T1/T2
# --- supply and drift: no datasheet figure; assumed magnitudes -----------------------------
V_NOMINAL = 3.3  # V, reference supply of the board
SUPPLY_GAIN_PER_V = 5e-3  # assumed: 0.5 %/V sensitivity change
SUPPLY_OFFSET_G_PER_V = 5e-3  # assumed: 5 mg/V zero-g change
OFFSET_RATE_G_PER_H = 1e-3  # assumed: 1 mg/h (Lötters 1998: offsets drift much more than sensitivities)
OFFSET_WALK_G_PER_SQRT_H = 2e-3  # assumed
SENS_RATE_PER_H = 2e-4  # assumed: 0.02 %/h
SENS_WALK_PER_SQRT_H = 5e-4  # assumed
BIAS_INSTABILITY_G = 0.5e-3  # assumed: colored-noise std
BIAS_TAU_S = (1.0, 10.0, 100.0)  # assumed: Gauss-Markov times spanning the 1/f region
TIMER_CLOCK_HZ = 4e6  # assumed microcontroller capture clock
# --- Murata ENC-03J ------------------------------------------------------------------------
GYRO_SCALE_MV_PER_DPS = 0.67  # as recalled; spread +-20 % as recalled
GYRO_SCALE_TOL = 0.20
GYRO_NULL_V = 1.35  # as recalled; spread assumed +-0.15 V
GYRO_NULL_TOL_V = 0.15
GYRO_RANGE_DPS = 300.0  # as recalled
GYRO_NOISE_DPS_RTHZ = 0.05  # assumed
GYRO_NULL_TEMPCO_MV_PER_C = 0.5  # assumed (removed by the high-pass anyway)
GYRO_HP_HZ = 0.3  # assumed conditioning stage (Scapellato 2005 gives no values)
GYRO_GAIN = 7.5  # assumed: +-300 °/s * 0.67 mV * 7.5 = +-1.5 V around Vsupply/2
GYRO_LP_HZ = 25.0  # assumed; below the sensor's own response (as recalled: 50 Hz)
GYRO_ADC_BITS = 12

CATALOGUE: dict[str, str] = {
    # catalogue (issue 6) name -> term name in the model
    "temperature_offset": "temperature_offset",
    "temperature_sensitivity": "temperature_sensitivity",
    "nonlinearity": "nonlinearity",
    "offset_drift": "offset_drift",
    "sensitivity_drift": "sensitivity_drift",
    "colored_noise": "colored_noise",
    "misalignment": "misalignment",
    "quantization": "timer",
    "ratiometric_supply": "ratiometric_supply",
}


def _spread(rng: np.random.Generator, typ: float, limits: tuple[float, float], n: int) -> np.ndarray:
    lo, hi = limits
    return np.clip(rng.normal(typ, (hi - lo) / 6.0, n), lo, hi)


def _signed(rng: np.random.Generator | None, typ: float, n: int) -> np.ndarray:
    """Zero-mean draw with sigma typ; nominal (rng None): +typ, -typ alternating per channel."""
    if rng is None:
        return typ * np.array([1.0, -1.0] * ((n + 1) // 2))[:n]
    return rng.normal(0.0, typ, n)


# Builders: (rng or None for nominal) -> Term. One per term, in a fixed order for seeding.
def _axes(rng):
    return Axes()


def _misalignment(rng):
    if rng is None:
        return Misalignment()
    d = np.deg2rad
    return Misalignment(chip_a=rng.normal(0, d(CHIP_PLACEMENT_DEG), 3), chip_b=rng.normal(0, d(CHIP_PLACEMENT_DEG), 3),
                        mount_b=rng.normal(0, d(MOUNT_B_DEG), 3), axis_err=rng.normal(0, d(ALIGN_DEG), (4, 2)))


def _nonlinearity(rng):
    c2 = NONLIN_PCT_FS / 100.0 / RANGE_G  # max deviation 0.2 % FS at full scale
    return Nonlinearity(c2=_signed(rng, c2, 4), c3=_signed(rng, c2 / RANGE_G / 2, 4))


BUILDERS: dict[str, Callable[[np.random.Generator | None], Term]] = {
    "axes": _axes,
    "misalignment": _misalignment,
    "nonlinearity": _nonlinearity,
    "temperature_sensitivity": lambda r: TemperatureSensitivity(coef_per_c=_signed(r, TEMP_SENS_PER_C, 4)),
    "ratiometric_supply": lambda r: RatiometricSupply(gain_per_v=_signed(r, SUPPLY_GAIN_PER_V, 4),
                                                      offset_g_per_v=_signed(r, SUPPLY_OFFSET_G_PER_V, 4),
                                                      v0=V_NOMINAL),
    "sensitivity_drift": lambda r: SensitivityDrift(rate_per_h=_signed(r, SENS_RATE_PER_H, 4),
                                                    walk_per_sqrt_h=np.full(4, SENS_WALK_PER_SQRT_H)),
    "temperature_offset": lambda r: TemperatureOffset(coef_g_per_c=_signed(r, TEMP_OFFSET_G_PER_C, 4)),
    "offset_drift": lambda r: OffsetDrift(rate_g_per_h=_signed(r, OFFSET_RATE_G_PER_H, 4),
                                          walk_g_per_sqrt_h=np.full(4, OFFSET_WALK_G_PER_SQRT_H)),
    "noise": lambda r: Noise(density_ug=np.full(4, NOISE_DENSITY_UG)),
    "colored_noise": lambda r: ColoredNoise(sigma_g=np.full(4, BIAS_INSTABILITY_G), tau_s=BIAS_TAU_S),
    "analog_lowpass": lambda r: AnalogLowpass(
        c_uf=np.full(4, CX_UF) if r is None else CX_UF * (1 + r.uniform(-CX_TOL, CX_TOL, 4))),
    "saturation": lambda r: Saturation(limit_g=np.full(4, RANGE_G)),
    "duty_cycle": lambda r: DutyCycle(
        d0=np.full(4, D0_TYP) if r is None else _spread(r, D0_TYP, D0_LIMITS, 4),
        k=np.full(4, SENS_TYP) if r is None else _spread(r, SENS_TYP, SENS_LIMITS, 4)),
    "timer": lambda r: Timer(
        rset_ohm=np.full(2, RSET_OHM) if r is None else RSET_OHM * (1 + r.uniform(-RSET_TOL, RSET_TOL, 2)),
        clock_hz=TIMER_CLOCK_HZ, tempco_ppm=np.zeros(2)),
    "gyro_sensor": lambda r: GyroSensor(
        scale_mv_per_dps=GYRO_SCALE_MV_PER_DPS if r is None
        else _spread(r, GYRO_SCALE_MV_PER_DPS, (GYRO_SCALE_MV_PER_DPS * (1 - GYRO_SCALE_TOL),
                                                GYRO_SCALE_MV_PER_DPS * (1 + GYRO_SCALE_TOL)), 1)[0],
        null_v=GYRO_NULL_V if r is None
        else _spread(r, GYRO_NULL_V, (GYRO_NULL_V - GYRO_NULL_TOL_V, GYRO_NULL_V + GYRO_NULL_TOL_V), 1)[0],
        range_dps=GYRO_RANGE_DPS, noise_dps_rthz=GYRO_NOISE_DPS_RTHZ),
    "gyro_conditioning": lambda r: GyroConditioning(hp_hz=GYRO_HP_HZ, gain=GYRO_GAIN, lp_hz=GYRO_LP_HZ),
    "gyro_adc": lambda r: GyroADC(bits=GYRO_ADC_BITS),
}

BASE_TERMS = ("axes", "noise", "analog_lowpass", "saturation", "duty_cycle", "timer",
              "gyro_sensor", "gyro_conditioning", "gyro_adc")
FLAG_TERMS = {
    "misalignment": ("misalignment",),
    "temperature": ("temperature_offset", "temperature_sensitivity"),
    "nonlinearity": ("nonlinearity",),
    "drift": ("offset_drift", "sensitivity_drift", "colored_noise"),
    "supply": ("ratiometric_supply",),
}


def catalogue_term(name: str, rng: Any = None, *, nominal: bool = False) -> Term:
    """The term for a catalogue or term name, drawn from the datasheet spreads (or nominal)."""
    term_name = CATALOGUE.get(name, name)
    if term_name not in BUILDERS:
        raise ValueError(f"unknown sensor-model effect {name!r}; known: {sorted(set(BUILDERS) | set(CATALOGUE))}")
    r = None if nominal else np.random.default_rng(rng)
    return BUILDERS[term_name](r)


def default_model(rng: Any = None, *, nominal: bool = False, misalignment: bool = False, temperature: bool = False,
                  nonlinearity: bool = False, drift: bool = False, supply: bool = False,
                  **overrides: Any) -> SensorModel:
    """The ADXL210 pair + ENC-03J model with parameters drawn from datasheet spreads.

    rng: a Generator or seed (None: fresh entropy). nominal=True: datasheet typical values, no
    draws ("+-typ" effects get +typ/-typ alternating over channels so they still act).
    Flags switch on groups of terms (see FLAG_TERMS). ``overrides``: per term name (or
    catalogue name): False drops the term, True adds it, a dict replaces some of its params,
    a Term replaces it. Each term draws from its own seeded stream, so switching one term on
    or off does not change the draws of the others.
    """
    gen = np.random.default_rng(rng)
    seeds = dict(zip(BUILDERS, gen.integers(0, 2**63 - 1, len(BUILDERS))))

    def build(name: str) -> Term:
        return BUILDERS[name](None if nominal else np.random.default_rng(int(seeds[name])))

    flags = {"misalignment": misalignment, "temperature": temperature, "nonlinearity": nonlinearity,
             "drift": drift, "supply": supply}
    for flag in ("misalignment", "nonlinearity"):  # flag == term name: a Term/dict value is an override
        if isinstance(flags[flag], (Term, dict)):
            overrides = {flag: flags[flag], **overrides}
            flags[flag] = True
    misalignment = bool(flags["misalignment"])
    names = [n for n in BASE_TERMS]
    for flag, on in flags.items():
        if on:
            names += FLAG_TERMS[flag]
    if misalignment:
        names.remove("axes")
    terms: dict[str, Term] = {n: build(n) for n in names}
    if temperature:  # the oscillator and the gyro null drift too (both cancel downstream)
        r = None if nominal else np.random.default_rng(int(seeds["temperature_offset"]) + 1)
        timer, gyro = terms["timer"], terms["gyro_sensor"]
        terms["timer"] = Timer(**{**timer.params, "tempco_ppm": _signed(r, T2_TEMPCO_PPM, 2)})
        terms["gyro_sensor"] = GyroSensor(**{**gyro.params,
                                            "null_tempco_mv_per_c": _signed(r, GYRO_NULL_TEMPCO_MV_PER_C, 1)[0]})

    for key, value in overrides.items():
        name = CATALOGUE.get(key, key)
        if name not in BUILDERS:
            raise ValueError(f"default_model: unknown override {key!r}; terms: {sorted(BUILDERS)}")
        if value is False or value is None:
            terms.pop(name, None)
        elif value is True:
            terms[name] = terms.get(name) or build(name)
        elif isinstance(value, Term):
            if value.name != name:
                raise ValueError(f"default_model: override {key!r} is a {value.name!r} term")
            terms[name] = value
        elif isinstance(value, dict):
            base = terms.get(name) or build(name)
            params = {k: v.tolist() for k, v in base.params.items()}
            unknown = set(value) - set(params)
            if unknown:
                raise ValueError(f"default_model: term {name!r} has no parameter(s) {sorted(unknown)}; "
                                 f"it has {sorted(params)}")
            params.update(value)
            terms[name] = type(base)(**params)
        else:
            raise ValueError(f"default_model: override {key!r} must be True, False, a dict of params or a Term")
        if name == "misalignment" and name in terms:
            terms.pop("axes", None)
        if name == "axes" and name in terms:
            terms.pop("misalignment", None)
    return SensorModel(list(terms.values()))


def linear_channels(model: SensorModel, temp_c: float = 25.0, vsupply: float = V_NOMINAL,
                    t: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Effective duty = S a + d of all four channels: S (4, 3) [duty/g], d (4,) [duty].

    Composes ``linear_part`` of every channel- and duty-stage term (deterministic parts:
    random walks and noise have zero mean; nonlinearity has no linear part).
    """
    ctx = Context(t=np.array([float(t)]), temp=np.array([float(temp_c)]), vsupply=np.array([float(vsupply)]),
                  fs=100.0, rng=np.random.default_rng(0))
    gain = np.ones(4)
    offset = np.zeros(4)
    for term in model.stage_terms("channel") + model.stage_terms("duty"):
        if not hasattr(term, "linear_part"):
            raise ValueError(f"term {term.name!r} has no calibration-level view (linear_part); "
                             "triad_truth cannot include it")
        g, o = term.linear_part(ctx)
        g = np.broadcast_to(np.asarray(g, float).reshape(-1), (4,))
        o = np.broadcast_to(np.asarray(o, float).reshape(-1), (4,))
        gain, offset = g * gain, g * offset + o
    return gain[:, None] * projection_matrix(model), offset


def triad_truth(model: SensorModel, temp_c: float = 25.0, vsupply: float = V_NOMINAL, t: float = 0.0) -> Calibration:
    """The effective raw = K a + o of the triad (duty cycles of ax, ay, az) at given conditions.

    This is what an ideal estimator should find: K (3x3) [duty/g] includes misalignment
    (off-diagonal), temperature and supply at (temp_c [°C], vsupply [V]) and deterministic
    drift at time t [s]; o [duty]. Exact for the linear part of the model.
    """
    s, d = linear_channels(model, temp_c, vsupply, t)
    tri = list(TRIAD)
    return Calibration(
        model="truth", offset=d[tri], sensitivity=s[tri], n_windows=0,
        message="true effective linear model of the simulated sensor",
        metadata={"temp_c": float(temp_c), "vsupply": float(vsupply), "t": float(t),
                  "ax2_sensitivity": s[3].tolist(), "ax2_offset": float(d[3])},
    )
