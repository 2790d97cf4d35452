"""The Murata ENC-03J rate-gyro path: angular rate [rad/s] -> volts -> conditioning -> ADC counts.

Stage ``gyro`` in the model. The sensor output is V = V0 + Sv * rate (Murata's datasheet
convention: null voltage V0 ~ 1.35 V, scale factor Sv ~ 0.67 mV/(°/s)). On the IMU board the
signal goes through an analog stage (Scapellato et al. 2005, sec. 2: "sent to an analog
filtering stage"): a first-order high-pass that removes the null voltage and its drift, a
non-inverting amplifier around Vref = Vsupply/2, and a first-order low-pass; then a 12-bit
ADC ratiometric to the supply fills the ``gyro`` field. Every
parameter is a term parameter: extending the path adds terms rather than editing these.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from .base import Context, Term
from .datasheet import (GYRO_ADC_BITS, GYRO_GAIN, GYRO_HP_HZ, GYRO_LP_HZ, GYRO_NOISE_DPS_RTHZ, GYRO_NULL_TEMPCO_MV_PER_C,
                        GYRO_NULL_TOL_V, GYRO_NULL_V, GYRO_RANGE_DPS, GYRO_SCALE_MV_PER_DPS, GYRO_SCALE_TOL)
from .filters import butterworth_first_order, filter_sections, frequency_response, state_at
from .spec import TermSpec, signed, spread
from .stateful import StatefulTerm

DEG = np.pi / 180.0


class GyroSensor(StatefulTerm):
    """The ENC-03J element: rate along its sensitive axis -> output voltage [V].

    params: ``axis`` (3,) sensitive axis in the board frame (board y: medio-lateral when worn on
    the foot instep), ``scale_mv_per_dps`` [mV/(°/s)], ``null_v`` [V] at t0_c,
    ``null_tempco_mv_per_c`` [mV/°C], ``range_dps`` (rate clipped beyond it), ``noise_dps_rthz``
    white rate-noise density [(°/s)/√Hz] over the sampled band fs/2. State: own random stream.
    """

    name = "gyro_sensor"
    stage = "gyro"

    def __init__(self, axis: Any = (0.0, 1.0, 0.0), scale_mv_per_dps: Any = 0.67, null_v: Any = 1.35,
                 null_tempco_mv_per_c: Any = 0.0, t0_c: Any = 25.0, range_dps: Any = 300.0,
                 noise_dps_rthz: Any = 0.05, **params: Any):
        super().__init__(axis=axis, scale_mv_per_dps=scale_mv_per_dps, null_v=null_v,
                         null_tempco_mv_per_c=null_tempco_mv_per_c, t0_c=t0_c, range_dps=range_dps,
                         noise_dps_rthz=noise_dps_rthz, **params)

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        st = self.current_state(x, ctx)
        p = self.params
        omega = np.asarray(x, dtype=float).reshape(-1, 3)
        a = p["axis"]
        rate_dps = (omega[:, 0] * a[0] + omega[:, 1] * a[1] + omega[:, 2] * a[2]) / DEG
        rate_dps = rate_dps + st["rng"].standard_normal(rate_dps.shape) * p["noise_dps_rthz"] * np.sqrt(ctx.fs / 2)
        rate_dps = np.clip(rate_dps, -p["range_dps"], p["range_dps"])
        null = p["null_v"] + p["null_tempco_mv_per_c"] * 1e-3 * (np.asarray(ctx.temp, float) - p["t0_c"])
        return null + p["scale_mv_per_dps"] * 1e-3 * rate_dps


class GyroConditioning(StatefulTerm):
    """High-pass (hp_hz) -> amplifier (gain) around vref_ratio * Vsupply -> low-pass (lp_hz) [V -> V].

    First-order Butterworth sections (bilinear) as one SOS cascade with carried state; the
    first block starts settled on its first sample. Output clipped to the op-amp rails [0, Vsupply].
    """

    name = "gyro_conditioning"
    stage = "gyro"

    def __init__(self, hp_hz: Any = 0.3, gain: Any = 7.5, lp_hz: Any = 25.0, vref_ratio: Any = 0.5,
                 **params: Any):
        super().__init__(hp_hz=hp_hz, gain=gain, lp_hz=lp_hz, vref_ratio=vref_ratio, **params)

    def sos(self, fs: float) -> np.ndarray:
        """The two sections at sample rate fs. An analog low-pass at or above Nyquist cannot be
        represented in the sampled signal; it is then placed at 0.45 fs (the samples alias anyway)."""
        hp = butterworth_first_order(float(self.params["hp_hz"]), "highpass", fs)
        lp = butterworth_first_order(min(float(self.params["lp_hz"]), 0.45 * fs), "lowpass", fs)
        return np.vstack([hp, lp])

    def init_state(self, x: np.ndarray, ctx: Context) -> dict[str, Any]:
        x0 = float(np.asarray(x, float)[0]) if len(x) else 0.0
        sos = self.sos(ctx.fs)  # designed once per session: small blocks stay cheap
        return {"sos": sos, "zi": state_at(sos, x0)}

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        st = self.current_state(x, ctx)
        y = filter_sections(st["sos"], x, st["zi"])
        vs = np.asarray(ctx.vsupply, float)
        return np.clip(self.params["vref_ratio"] * vs + self.params["gain"] * y, 0.0, vs)


class GyroADC(Term):
    """bits-bit ADC ratiometric to the supply: counts = floor(V / Vsupply * 2^bits), clipped."""

    name = "gyro_adc"
    stage = "gyro"

    def __init__(self, bits: Any = 12, **params: Any):
        super().__init__(bits=bits, **params)

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        full = 2 ** int(self.params["bits"])
        counts = np.floor(np.asarray(x, float) / np.asarray(ctx.vsupply, float) * full)
        return np.clip(counts, 0, full - 1)


def gyro_scale_counts_per_rad_s(model: Any, vsupply: float = 3.3) -> float:
    """Small-signal gain of the whole gyro path in the pass band [ADC counts per rad/s]."""
    sensor, cond, adc = model["gyro_sensor"], model["gyro_conditioning"], model["gyro_adc"]
    volts_per_rad_s = float(sensor.params["scale_mv_per_dps"]) * 1e-3 / DEG
    return volts_per_rad_s * float(cond.params["gain"]) * 2 ** int(adc.params["bits"]) / vsupply


def gyro_null_counts(model: Any) -> float:
    """ADC reading at zero rate once the high-pass has settled (vref_ratio of full scale)."""
    return float(model["gyro_conditioning"].params["vref_ratio"]) * 2 ** int(model["gyro_adc"].params["bits"])


ENC03J_TERMS: tuple[str, ...] = ("gyro_sensor", "gyro_conditioning", "gyro_adc")


# -- what the conditioning does to the signal, and the gyro's calibration-level truth ----
def conditioning_response(model: Any, f_hz: Any, fs: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    """Gain (relative to the pass band, unitless) and phase [deg] of the conditioning stage
    (high-pass + low-pass as simulated, bilinear at ``fs``) at frequencies ``f_hz`` [Hz].

    With the defaults (HP 0.3 Hz, LP 25 Hz, fs 100 Hz) the gait band is not flat: 0.5 Hz is
    passed at 0.86 with +30° phase lead, 1 Hz at 0.96 / +15°, 2 Hz at 0.99 / +5°, 5 Hz at
    0.99 / -6° (the low-pass). A pose change
    (a rate pulse of ~1 s) therefore integrates to a wrong angle unless the high-pass is
    undone (``gravcal.core.gyro.conditioning.HighPassInverse``)."""
    f = np.atleast_1d(np.asarray(f_hz, dtype=float))
    h = frequency_response(model["gyro_conditioning"].sos(fs), f, fs)
    return np.abs(h), np.degrees(np.angle(h))


def gyro_truth(model: Any, vsupply: float = 3.3) -> dict[str, float]:
    """What an ideal in-use gyro calibration should find for the simulated ENC-03J path.

    ``bias_counts``: the ADC reading at zero rate. The high-pass removes the sensor's null
    voltage (and its temperature drift), so the DC level at the ADC is the conditioning stage's
    reference vref_ratio * Vsupply, ratiometric to the ADC: vref_ratio * 2^bits counts, minus
    half a count for the ADC's floor (the noise dithers it). A drifting null is not entirely
    removed: a first-order high-pass passes a ramp as the offset gain * tau * dV0/dt (0.02 counts
    for 0.5 mV/°C and a 10 °C warm-up over 20 min; not included here). ``sensitivity_counts_per_rad_s``:
    the pass-band gain of the whole path at ``vsupply`` [V] (the ENC-03J itself is not
    ratiometric, so the count scale goes as 1/Vsupply). ``axis``: the sensitive axis (board).
    """
    return {"bias_counts": gyro_null_counts(model) - 0.5,
            "sensitivity_counts_per_rad_s": gyro_scale_counts_per_rad_s(model, vsupply),
            "hp_hz": float(model["gyro_conditioning"].params["hp_hz"]),
            "axis": np.asarray(model["gyro_sensor"].params["axis"], float).tolist(),
            "range_rad_s": float(model["gyro_sensor"].params["range_dps"]) * DEG}


SPECS = (
    TermSpec(name="gyro_sensor", forward=GyroSensor, prior=lambda rng: GyroSensor(
        scale_mv_per_dps=GYRO_SCALE_MV_PER_DPS if rng is None
        else spread(rng, GYRO_SCALE_MV_PER_DPS, (GYRO_SCALE_MV_PER_DPS * (1 - GYRO_SCALE_TOL),
                                                 GYRO_SCALE_MV_PER_DPS * (1 + GYRO_SCALE_TOL)), 1)[0],
        null_v=GYRO_NULL_V if rng is None
        else spread(rng, GYRO_NULL_V, (GYRO_NULL_V - GYRO_NULL_TOL_V, GYRO_NULL_V + GYRO_NULL_TOL_V), 1)[0],
        range_dps=GYRO_RANGE_DPS, noise_dps_rthz=GYRO_NOISE_DPS_RTHZ),
        # the null drifts with temperature (removed by the conditioning's high-pass)
        variants={"temperature": lambda term, rng: GyroSensor(**{
            **term.params, "null_tempco_mv_per_c": signed(rng, GYRO_NULL_TEMPCO_MV_PER_C, 1)[0]})}),
    TermSpec(name="gyro_conditioning", forward=GyroConditioning,
             prior=lambda rng: GyroConditioning(hp_hz=GYRO_HP_HZ, gain=GYRO_GAIN, lp_hz=GYRO_LP_HZ)),
    TermSpec(name="gyro_adc", forward=GyroADC, prior=lambda rng: GyroADC(bits=GYRO_ADC_BITS)),
)
