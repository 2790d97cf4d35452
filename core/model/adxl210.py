"""Terms of the ADXL210 pair: board -> channel -> duty -> timer counts.

Two biaxial ADXL210 chips form the triad (see ``core/samples.py``): chip A lies flat and
senses board x and y (channels ``ax``, ``ay``); chip B stands on its edge on a small carrier
and senses board z and x again (``az``, ``ax2``). Every term below is one named physical
effect with its own parameters; datasheet values and spreads live in ``defaults.py`` and
their sources in ``docs/sensor-model.md``.

Channel-stage and duty-stage terms also expose ``linear_part(ctx) -> (gain, offset)``: the
affine map x -> gain * x + offset they apply on average (noise and filters at DC are the
identity, nonlinearity contributes nothing to the linear part). ``defaults.triad_truth``
composes these into the calibration-level view raw = K a + o.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from scipy import signal
from scipy.spatial.transform import Rotation

from .base import Context, Term, register
from .stateful import StatefulTerm

N_CHANNELS = 4
N_CHIPS = 2

IDEAL_AXES = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 0, 0]])
"""Nominal sensitive axis of each channel (rows: ax, ay, az, ax2) in the board frame."""

# Chip frame -> board frame rotations of the nominal mounting (columns = chip axes in board).
CHIP_A_NOMINAL = np.eye(3)  # flat: chip x -> board x, chip y -> board y
CHIP_B_NOMINAL = np.array([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]])  # on edge: chip x -> board z, chip y -> board x
# (chip, chip axis) of each channel, in CHANNELS order.
CHANNEL_SOURCE = ((0, 0), (0, 1), (1, 0), (1, 1))

G_RANGE = 10.0  # ADXL210 full scale [g]
T2_PER_RSET = 1.0 / 125e6  # T2 [s] = RSET [ohm] / 125 Mohm (datasheet)


def _col(v: np.ndarray) -> np.ndarray:
    """Per-sample scalar (N,) -> (N, 1) for broadcasting against (N, 4)."""
    return np.asarray(v, dtype=float).reshape(-1, 1)


# ----------------------------------------------------------------------------------------
# board -> channel: the sensitive axes
# ----------------------------------------------------------------------------------------
@register
class Axes(Term):
    """Projection of the specific force (N, 3) [g, board] on the four channel axes (N, 4) [g].

    params: ``u`` (4, 3) sensitive-axis vectors of ax, ay, az, ax2 in the board frame. Any
    misalignment and cross-axis sensitivity is in ``u``; see :class:`Misalignment` for the
    same projection built from physical mounting angles.
    """

    name = "axes"
    stage = "board"
    order = 90  # the stage change: last in the board stage

    def __init__(self, u: Any = IDEAL_AXES, **params: Any):
        super().__init__(u=u, **params)
        if self.params["u"].shape != (N_CHANNELS, 3):
            raise ValueError(f"axes: u must have shape (4, 3), got {self.params['u'].shape}")

    @property
    def matrix(self) -> np.ndarray:
        """(4, 3) channel axes in the board frame."""
        return self.params["u"]

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        u = self.matrix
        # explicit per-row sums (not BLAS): identical results whatever the block length
        return x[:, 0:1] * u[:, 0] + x[:, 1:2] * u[:, 1] + x[:, 2:3] * u[:, 2]


def misaligned_axes(chip_a: Any = (0, 0, 0), chip_b: Any = (0, 0, 0), mount_b: Any = (0, 0, 0),
                    axis_err: Any = np.zeros((4, 2))) -> np.ndarray:
    """Channel axes (4, 3) from mounting angles [rad].

    chip_a, chip_b: rotation vectors of each package on its PCB, in the chip's own frame
    (placement/solder tilt). mount_b: rotation vector of chip B's edge carrier in the board
    frame. axis_err (4, 2): per-channel deviation of the sensitive axis inside the die toward
    the two chip axes perpendicular to it (datasheet "alignment error" / cross-axis sensitivity).
    """
    axis_err = np.asarray(axis_err, dtype=float).reshape(N_CHANNELS, 2)
    r_a = CHIP_A_NOMINAL @ Rotation.from_rotvec(np.asarray(chip_a, float)).as_matrix()
    r_b = (Rotation.from_rotvec(np.asarray(mount_b, float)).as_matrix() @ CHIP_B_NOMINAL
           @ Rotation.from_rotvec(np.asarray(chip_b, float)).as_matrix())
    chips = (r_a, r_b)
    u = np.zeros((N_CHANNELS, 3))
    for c, (chip, axis) in enumerate(CHANNEL_SOURCE):
        others = [i for i in range(3) if i != axis]
        v = np.zeros(3)
        v[axis] = 1.0
        v[others] = np.tan(axis_err[c])  # small tilts toward the other two chip axes
        u[c] = chips[chip] @ (v / np.linalg.norm(v))
    return u


@register
class Misalignment(Axes):
    """The axes projection built from mounting angles (catalogue name ``misalignment``).

    params [rad]: ``chip_a`` (3,), ``chip_b`` (3,) package rotation vectors in the chip frame,
    ``mount_b`` (3,) rotation vector of chip B's carrier in the board frame, ``axis_err`` (4, 2)
    in-die axis errors. A model holds either ``axes`` or ``misalignment``, not both; a model
    with neither uses the ideal axes.
    """

    name = "misalignment"

    def __init__(self, chip_a: Any = (0, 0, 0), chip_b: Any = (0, 0, 0), mount_b: Any = (0, 0, 0),
                 axis_err: Any = np.zeros((4, 2))):
        Term.__init__(self, chip_a=chip_a, chip_b=chip_b, mount_b=mount_b,
                      axis_err=np.asarray(axis_err, float).reshape(N_CHANNELS, 2))
        self._u = misaligned_axes(chip_a, chip_b, mount_b, axis_err)

    @property
    def matrix(self) -> np.ndarray:
        return self._u


def projection_matrix(model: Any) -> np.ndarray:
    """The (4, 3) channel axes of a model: its ``axes``/``misalignment`` term, else ideal."""
    proj = [t for t in model.stage_terms("board") if isinstance(t, Axes)]
    if len(proj) > 1:
        raise ValueError(f"sensor model has {len(proj)} axis projections ({[t.name for t in proj]}); "
                         "keep either 'axes' or 'misalignment'")
    return proj[0].matrix if proj else IDEAL_AXES


# ----------------------------------------------------------------------------------------
# channel stage [g]
# ----------------------------------------------------------------------------------------
@register
class Nonlinearity(Term):
    """x + c2 x^2 + c3 x^3 per channel (c2 [1/g], c3 [1/g^2]); contributes nothing linear."""

    name = "nonlinearity"
    stage = "channel"
    order = 10

    def __init__(self, c2: Any = np.zeros(4), c3: Any = np.zeros(4), **params: Any):
        super().__init__(c2=c2, c3=c3, **params)

    @classmethod
    def from_percent_fs(cls, pct: Any, full_scale_g: float = G_RANGE) -> "Nonlinearity":
        """Pure quadratic bow with max deviation ``pct`` % of full scale at +-full scale."""
        c2 = np.asarray(pct, float) / 100.0 * full_scale_g / full_scale_g**2
        return cls(c2=np.broadcast_to(c2, (4,)), c3=np.zeros(4))

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        p = self.params
        return x + p["c2"] * x**2 + p["c3"] * x**3

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        return np.ones(4), np.zeros(4)


@register
class TemperatureSensitivity(Term):
    """Gain (1 + coef_per_c (T - t0_c)) per channel [1/°C]."""

    name = "temperature_sensitivity"
    stage = "channel"
    order = 20

    def __init__(self, coef_per_c: Any = np.zeros(4), t0_c: Any = 25.0, **params: Any):
        super().__init__(coef_per_c=coef_per_c, t0_c=t0_c, **params)

    def _gain(self, ctx: Context) -> np.ndarray:
        return 1.0 + self.params["coef_per_c"] * (_col(ctx.temp) - self.params["t0_c"])

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        return x * self._gain(ctx)

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        return self._gain(ctx), np.zeros(4)


@register
class RatiometricSupply(Term):
    """Supply dependence: x (1 + gain_per_v dV) + offset_g_per_v dV, dV = vsupply - v0 [V]."""

    name = "ratiometric_supply"
    stage = "channel"
    order = 22

    def __init__(self, gain_per_v: Any = np.zeros(4), offset_g_per_v: Any = np.zeros(4), v0: Any = 3.3,
                 **params: Any):
        super().__init__(gain_per_v=gain_per_v, offset_g_per_v=offset_g_per_v, v0=v0, **params)

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        dv = _col(ctx.vsupply) - self.params["v0"]
        return 1.0 + self.params["gain_per_v"] * dv, self.params["offset_g_per_v"] * dv

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        g, o = self.linear_part(ctx)
        return x * g + o


class _RandomWalkTerm(StatefulTerm):
    """Shared machinery: deterministic rate * t plus a random walk W(t), state = W at block end."""

    rate_key: str
    walk_key: str

    def init_state(self, x: np.ndarray, ctx: Context) -> dict[str, Any]:
        return {"walk": np.zeros(4)}

    def _drift(self, ctx: Context, x: np.ndarray) -> np.ndarray:
        """rate t + W(t) for every sample, (N, 4); advances the walk state."""
        st = self.current_state(x, ctx)
        n = ctx.n
        dt_h = 1.0 / ctx.fs / 3600.0
        steps = st["rng"].standard_normal((n, 4)) * (self.params[self.walk_key] * np.sqrt(dt_h))
        # sequential recursion W[n] = W[n-1] + step: block-split invariant (unlike cumsum + offset)
        walk, zf = signal.lfilter([1.0], [1.0, -1.0], steps, axis=0, zi=st["walk"][None, :])
        st["walk"] = zf[0]
        return self.params[self.rate_key] * (_col(ctx.t) / 3600.0) + walk


@register
class SensitivityDrift(_RandomWalkTerm):
    """Gain 1 + rate_per_h t + random walk (walk_per_sqrt_h) per channel; t in hours."""

    name = "sensitivity_drift"
    stage = "channel"
    order = 24
    rate_key, walk_key = "rate_per_h", "walk_per_sqrt_h"

    def __init__(self, rate_per_h: Any = np.zeros(4), walk_per_sqrt_h: Any = np.zeros(4), **params: Any):
        super().__init__(rate_per_h=rate_per_h, walk_per_sqrt_h=walk_per_sqrt_h, **params)

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        return x * (1.0 + self._drift(ctx, x))

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        """Deterministic part only (the random walk has zero mean)."""
        return 1.0 + self.params["rate_per_h"] * (_col(ctx.t) / 3600.0), np.zeros(4)


@register
class TemperatureOffset(Term):
    """Offset coef_g_per_c (T - t0_c) per channel [g/°C]."""

    name = "temperature_offset"
    stage = "channel"
    order = 30

    def __init__(self, coef_g_per_c: Any = np.zeros(4), t0_c: Any = 25.0, **params: Any):
        super().__init__(coef_g_per_c=coef_g_per_c, t0_c=t0_c, **params)

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        return np.ones(4), self.params["coef_g_per_c"] * (_col(ctx.temp) - self.params["t0_c"])

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        return x + self.linear_part(ctx)[1]


@register
class OffsetDrift(_RandomWalkTerm):
    """Bias rate_g_per_h t + random walk (walk_g_per_sqrt_h) per channel [g]; t in hours."""

    name = "offset_drift"
    stage = "channel"
    order = 32
    rate_key, walk_key = "rate_g_per_h", "walk_g_per_sqrt_h"

    def __init__(self, rate_g_per_h: Any = np.zeros(4), walk_g_per_sqrt_h: Any = np.zeros(4), **params: Any):
        super().__init__(rate_g_per_h=rate_g_per_h, walk_g_per_sqrt_h=walk_g_per_sqrt_h, **params)

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        return x + self._drift(ctx, x)

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        """Deterministic part only (the random walk has zero mean)."""
        return np.ones(4), self.params["rate_g_per_h"] * (_col(ctx.t) / 3600.0)


@register
class Noise(StatefulTerm):
    """White noise of density density_ug [µg/√Hz] over bandwidth_hz (0 = fs/2, the sampled band).

    Added before the analog low-pass, which then shapes it like the Cx/Cy filter does. The
    only state is the term's own random stream.
    """

    name = "noise"
    stage = "channel"
    order = 40

    def __init__(self, density_ug: Any = np.full(4, 200.0), bandwidth_hz: Any = 0.0, **params: Any):
        super().__init__(density_ug=density_ug, bandwidth_hz=bandwidth_hz, **params)

    def sigma_g(self, fs: float) -> np.ndarray:
        """Per-sample standard deviation [g] at sample rate fs."""
        bw = float(self.params["bandwidth_hz"]) or fs / 2.0
        return self.params["density_ug"] * 1e-6 * np.sqrt(bw)

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        st = self.current_state(x, ctx)
        return x + st["rng"].standard_normal(x.shape) * self.sigma_g(ctx.fs)

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        return np.ones(4), np.zeros(4)


@register
class ColoredNoise(StatefulTerm):
    """Bias instability / flicker: sum of first-order Gauss-Markov processes per channel.

    params: ``sigma_g`` (4,) total stationary std [g], ``tau_s`` (k,) correlation times [s]
    (log-spaced times of equal variance approximate a 1/f spectrum between them).
    State: the filter states of the k processes (they start in their stationary distribution).
    """

    name = "colored_noise"
    stage = "channel"
    order = 42

    def __init__(self, sigma_g: Any = np.zeros(4), tau_s: Any = (1.0, 10.0, 100.0), **params: Any):
        super().__init__(sigma_g=sigma_g, tau_s=np.atleast_1d(np.asarray(tau_s, float)), **params)

    def _phi(self, fs: float) -> np.ndarray:
        return np.exp(-1.0 / (fs * self.params["tau_s"]))

    def init_state(self, x: np.ndarray, ctx: Context) -> dict[str, Any]:
        k = self.params["tau_s"].size
        s = self.params["sigma_g"] / np.sqrt(k)
        p0 = self.state["rng"].standard_normal((k, 4)) * s  # stationary start
        return {"zi": self._phi(ctx.fs)[:, None] * p0}

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        st = self.current_state(x, ctx)
        k = self.params["tau_s"].size
        s = self.params["sigma_g"] / np.sqrt(k)
        phi = self._phi(ctx.fs)
        w = st["rng"].standard_normal((x.shape[0], k, 4))  # sample-major: block-split invariant
        out = np.array(x, dtype=float, copy=True)
        for j in range(k):  # k is 2-4 processes, not samples
            y, zf = signal.lfilter([1.0], [1.0, -phi[j]], w[:, j] * (s * np.sqrt(1.0 - phi[j] ** 2)),
                                   axis=0, zi=st["zi"][j][None, :])
            st["zi"][j] = zf[0]
            out += y
        return out

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        return np.ones(4), np.zeros(4)


@register
class AnalogLowpass(StatefulTerm):
    """The Cx/Cy filter: one pole at f_3dB = 5 µF / C per channel (RFILT = 32 kohm on chip).

    params: ``c_uf`` (4,) filter capacitors [µF]. Discretised at the simulation rate with a
    matched pole exp(-2 pi f_3dB / fs). State: the lfilter state per channel; the first block
    starts settled on its first sample (the sensor was on before the session started).
    """

    name = "analog_lowpass"
    stage = "channel"
    order = 60

    def __init__(self, c_uf: Any = np.full(4, 0.47), **params: Any):
        super().__init__(c_uf=c_uf, **params)

    @property
    def f3db_hz(self) -> np.ndarray:
        return 5.0 / self.params["c_uf"]

    def _coeffs(self, fs: float) -> list[tuple[np.ndarray, np.ndarray]]:
        pole = np.exp(-2.0 * np.pi * self.f3db_hz / fs)
        return [(np.array([1.0 - p]), np.array([1.0, -p])) for p in pole]

    def init_state(self, x: np.ndarray, ctx: Context) -> dict[str, Any]:
        x0 = np.asarray(x, float)[0] if len(x) else np.zeros(4)
        coeffs = self._coeffs(ctx.fs)
        return {"coeffs": coeffs, "zi": [signal.lfilter_zi(b, a) * x0[c] for c, (b, a) in enumerate(coeffs)]}

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        st = self.current_state(x, ctx)
        out = np.empty_like(np.asarray(x, float))
        for c, (b, a) in enumerate(st["coeffs"]):  # 4 channels, each its own pole
            out[:, c], st["zi"][c] = signal.lfilter(b, a, x[:, c], zi=st["zi"][c])
        return out

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        return np.ones(4), np.zeros(4)  # unit DC gain


@register
class Saturation(Term):
    """Output range: clip each channel to +-limit_g [g]. Samples at the rail get FLAG_SATURATED."""

    name = "saturation"
    stage = "channel"
    order = 90

    def __init__(self, limit_g: Any = np.full(4, G_RANGE), **params: Any):
        super().__init__(limit_g=limit_g, **params)

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        lim = self.params["limit_g"]
        return np.clip(x, -lim, lim)

    def at_rail(self, x: np.ndarray) -> np.ndarray:
        """(N,) True where any channel of the (clipped) channel-stage output is at its limit."""
        return np.any(np.abs(x) >= self.params["limit_g"], axis=1)

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        return np.ones(4), np.zeros(4)  # identity inside the range


# ----------------------------------------------------------------------------------------
# duty stage and timer counts
# ----------------------------------------------------------------------------------------
@register
class DutyCycle(Term):
    """Duty-cycle modulator: d = d0 + k a per channel; inverse A = (T1/T2 - d0)/k.

    params: ``d0`` (4,) zero-g duty cycle (nominal 0.5), ``k`` (4,) sensitivity [duty/g]
    (nominal 0.04, i.e. 4 %/g).
    """

    name = "duty_cycle"
    stage = "duty"
    order = 10

    def __init__(self, d0: Any = np.full(4, 0.5), k: Any = np.full(4, 0.04), **params: Any):
        super().__init__(d0=d0, k=k, **params)

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        return self.params["d0"] + self.params["k"] * x

    def linear_part(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        return self.params["k"] * np.ones(4), self.params["d0"] * np.ones(4)


@register
class Timer(StatefulTerm):
    """Counter capture of T1 and T2 (catalogue name ``quantization``).

    T2 = RSET / 125 Mohm per chip (with a temperature coefficient of the oscillator), counted
    by a timer clocked at ``clock_hz``; T1 = d T2 per channel. Output (N, 6): T1 counts of the
    four channels, then T2 counts of chips A and B. With ``async_phase`` = 1 the clock phase
    relative to the PWM edges is random, so a count is floor(T f + U), U ~ U[0, 1): error within
    one count, unbiased; with 0 it is round(T f). Duty cycles are clipped to [0, 1] first.
    """

    name = "timer"
    stage = "counts"
    order = 10

    def __init__(self, rset_ohm: Any = np.full(2, 625e3), clock_hz: Any = 4e6, tempco_ppm: Any = np.zeros(2),
                 t0_c: Any = 25.0, async_phase: Any = 1.0, **params: Any):
        super().__init__(rset_ohm=rset_ohm, clock_hz=clock_hz, tempco_ppm=tempco_ppm, t0_c=t0_c,
                         async_phase=async_phase, **params)

    def t2_seconds(self, temp: Any) -> np.ndarray:
        """(N, 2) PWM period of each chip [s]."""
        p = self.params
        return p["rset_ohm"] * T2_PER_RSET * (1.0 + p["tempco_ppm"] * 1e-6 * (_col(temp) - p["t0_c"]))

    def forward(self, x: np.ndarray, ctx: Context) -> np.ndarray:
        st = self.current_state(x, ctx)
        t2 = self.t2_seconds(ctx.temp) * float(self.params["clock_hz"])  # (N, 2) exact counts
        t1 = np.clip(x, 0.0, 1.0) * t2[:, [0, 0, 1, 1]]
        exact = np.concatenate([t1, t2], axis=1)
        if float(self.params["async_phase"]):
            return np.floor(exact + st["rng"].random(exact.shape))
        return np.round(exact)


ADXL210_TERMS: tuple[str, ...] = (
    "axes", "misalignment", "nonlinearity", "temperature_sensitivity", "ratiometric_supply",
    "sensitivity_drift", "temperature_offset", "offset_drift", "noise", "colored_noise",
    "analog_lowpass", "saturation", "duty_cycle", "timer",
)
