"""Sessions written from the physics, independent of gravcal's simulator, with their truth.

Nothing here calls ``gravcal.core.simulate``, ``core.scenarios`` or ``core.model``: the sensor, the wearer's
postures, the noise and the temperature are drawn from this module's own numpy streams
(``numpy.random.SeedSequence([TAG, kind, seed])``), so a coverage test over these sessions checks gravcal's
stated std against data gravcal did not shape. Only the container (``WindowSet``) is gravcal's.

Physics (a in g, raw in counts):

    raw(t) = K(T) a(t) + o(T) + n(t)
    K      = diag(1 + c_s (T - T_ref) + d_s t) diag(s) (I + L)    gains move with temperature and time [h]
    o      = o_ref + c_o (T - T_ref) + d_o t + c_v (V - V_ref)     zero-g levels: temperature, time, supply
    a_i   -> a_i + c2_i a_i²                                        each channel's quadratic bow [1/g]

``L`` holds the axes' leans (off-diagonal, L_ij: axis i tilted toward j), so the sensitive axis of channel i
is row i of ``diag(s) (I + L)``; the misalignment of axes i and j is 90° minus the angle between those rows.
A quasi-static moment of the wearer has |a| = 1 g along a posture's gravity direction (standing, sitting,
lying on back, front or either side, and the tilts between), turned by the sensor's mounting on the body, plus
the residual body motion a still window keeps (a small acceleration constant over the window, ``floor_g``
per axis) and white sample noise (``noise_g`` per axis and sample). Windows are 2-8 s at 50 Hz; each carries
its samples' mean, sample covariance, count, mid time, mean temperature and supply voltage (aux columns 0, 1), as
a detector's. The window statistics are drawn directly (the mean's noise and a Wishart sample covariance),
not from samples: the same distribution for Gaussian noise, at a fraction of the cost.
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import numpy as np
from gravcal.core.windows import WindowSet

TAG = 0x1DE9  # this module's stream: no other generator in the project draws from it
T_REF_C = 25.0  # reference temperature of K, o [°C] (gravcal's default T_ref; the truth is stated at it)
FS_HZ = 50.0

KINDS = ("six", "misaligned", "misaligned_lab", "misaligned_nine", "temperature_offset", "temperature_sensitivity", "offset_drift",
         "sensitivity_drift", "supply_offset", "nonlinearity", "offsets_held")
"""Session kinds: a plain sensor (fit: 6); leaned axes (6+misalignment), worn, or placed by hand in 40 poses
over the sphere with a quiet lab-grade sensor (the angles known to ~0.01°, where a small-angle conversion
is many std off), or worn and fitted with the in-use 9 (K symmetric); a temperature-driven offset (6+temperature_offset) or gain (6+temperature_sensitivity) over
a warm-up; an offset or a gain drifting in time (6+offset_drift, 6+sensitivity_drift); an offset following
the supply voltage as the battery discharges (6+supply_offset); a quadratic bow of each channel
(6+nonlinearity); a short session fitted for the offsets only with the sensitivities held from a previous
calibration of stated uncertainty (consider term)."""

MODEL = {"six": "6", "misaligned": "6+misalignment", "misaligned_lab": "6+misalignment", "misaligned_nine": "9",
         "offsets_held": "offsets", **{k: f"6+{k}" for k in KINDS[4:10]}}
"""The model each kind is made with, which the coverage fits."""
V_NOMINAL = 3.3  # supply reference [V] (gravcal's default V_ref)

# posture gravity directions in the body frame (x forward, y left, z up), before the per-window sway
_POSTURES = {
    "standing": (0.0, 0.0),  # (pitch, roll) [deg] of the trunk from upright
    "leaning": (25.0, 0.0),
    "sitting_back": (-30.0, 0.0),
    "slumped": (45.0, 10.0),
    "supine": (-90.0, 0.0),
    "prone": (90.0, 0.0),
    "left_side": (0.0, -90.0),
    "right_side": (0.0, 90.0),
    "reclined": (-60.0, 20.0),
}


@dataclass
class Truth:
    """What the session was made with: K, o at T_ref; per-axis temperature coefficients."""

    K: np.ndarray  # (3, 3) raw per g at T_ref: rows are the sensing axes times their gains
    o: np.ndarray  # (3,) raw at T_ref
    c_o: np.ndarray = field(default_factory=lambda: np.zeros(3))  # raw per °C
    c_s: np.ndarray = field(default_factory=lambda: np.zeros(3))  # relative gain change per °C
    d_o: np.ndarray = field(default_factory=lambda: np.zeros(3))  # raw per hour
    d_s: np.ndarray = field(default_factory=lambda: np.zeros(3))  # relative gain change per hour
    c_v: np.ndarray = field(default_factory=lambda: np.zeros(3))  # raw per V
    c2: np.ndarray = field(default_factory=lambda: np.zeros(3))  # quadratic bow [1/g]
    t_ref_c: float = T_REF_C

    @property
    def S(self) -> np.ndarray:
        """The symmetric factor of K = S R (what |K^-1 (raw - o)| = 1 g determines): (K K^T)^1/2."""
        w, V = np.linalg.eigh(self.K @ self.K.T)
        return (V * np.sqrt(w)) @ V.T

    @property
    def gains(self) -> np.ndarray:
        """Sensitivity of each channel along its own axis: the row norms of K [raw/g]."""
        return np.linalg.norm(self.K, axis=1)

    def misalignment_deg(self) -> dict[str, float]:
        """90° minus the angle between sensing axes i and j, per pair xy, xz, yz [deg]."""
        u = self.K / np.linalg.norm(self.K, axis=1, keepdims=True)
        return {f"{'xyz'[i]}{'xyz'[j]}": 90.0 - float(np.degrees(np.arccos(np.clip(u[i] @ u[j], -1, 1))))
                for i, j in ((0, 1), (0, 2), (1, 2))}

    def term_magnitudes(self) -> dict[str, np.ndarray]:
        """Each term per axis in the units gravcal reports it: an offset slope over the axis' gain [mg per °C,
        per h, per V], a gain slope in % [per °C, per h], the bow c2 [1/g]."""
        s = np.diag(self.K)
        return {"temperature_offset": self.c_o / s * 1e3, "temperature_sensitivity": self.c_s * 100.0,
                "offset_drift": self.d_o / s * 1e3, "sensitivity_drift": self.d_s * 100.0,
                "supply_offset": self.c_v / s * 1e3, "nonlinearity": self.c2.copy()}

    def term_parameters(self, term: str) -> np.ndarray:
        """The term's parameters as gravcal's extended model holds them [raw per covariate unit; c2 as is]."""
        s = np.diag(self.K)
        return {"temperature_offset": self.c_o, "temperature_sensitivity": self.c_s * s, "offset_drift": self.d_o,
                "sensitivity_drift": self.d_s * s, "supply_offset": self.c_v, "nonlinearity": self.c2}[term]


@dataclass
class Session:
    kind: str
    seed: int
    windows: WindowSet
    truth: Truth
    model: str  # the model whose parameters the truth states
    held_rel_std: float = 0.0  # offsets_held: stated relative std of the held sensitivities
    held_K: np.ndarray | None = None  # offsets_held: the held (previous) sensitivities, off the truth


def rng_for(kind: str, seed: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([TAG, zlib.crc32(kind.encode()), int(seed)]))


def _rotation(rng: np.random.Generator, max_deg: float) -> np.ndarray:
    """A rotation about a random axis by an angle uniform in [0, max_deg] (Rodrigues)."""
    k = rng.normal(size=3)
    k /= np.linalg.norm(k)
    th = np.radians(rng.uniform(0.0, max_deg))
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * Kx + (1 - np.cos(th)) * Kx @ Kx


def _posture_direction(pitch_deg: float, roll_deg: float) -> np.ndarray:
    """The specific force at rest (+1 g up) in the body frame of a trunk pitched and rolled from upright."""
    p, r = np.radians(pitch_deg), np.radians(roll_deg)
    return np.array([-np.sin(p) * np.cos(r), np.sin(r), np.cos(p) * np.cos(r)])


def _sensor(rng: np.random.Generator, leaned: bool, lean_deg: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """K (3, 3), o (3,) of a 12-bit triad around 2048 counts at 0 g, ~330 counts/g (ADXL-class spreads)."""
    s = 330.0 * (1 + rng.normal(0, 0.05, 3))
    o = 2048.0 + rng.normal(0, 0.1, 3) * s
    L = np.zeros((3, 3))
    if leaned:  # in-die axis errors and package placement: each axis toward both others, ``lean_deg`` std
        L = np.radians(rng.normal(0, lean_deg, (3, 3)))
        np.fill_diagonal(L, 0.0)
    return np.diag(s) @ (np.eye(3) + L), o


def _temperature(rng: np.random.Generator, t: np.ndarray, duration: float) -> np.ndarray:
    """Skin-side temperature [°C]: a warm-up from the room to the body with a slow wander (not a ramp)."""
    t_room, t_body = rng.uniform(18, 24), rng.uniform(30, 34)
    tau = rng.uniform(0.15, 0.4) * duration
    wander = rng.uniform(0.3, 1.0) * np.sin(2 * np.pi * t / rng.uniform(0.5, 1.0) / duration + rng.uniform(0, 6.3))
    return t_body + (t_room - t_body) * np.exp(-t / tau) + wander


def _sample_covariance(rng: np.random.Generator, L: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Sample covariances (ddof 1) of n[k] Gaussian samples of covariance L[k] L[k]^T, drawn directly (Bartlett:
    (n - 1) S = L A A^T L^T, A lower triangular, A_ii² ~ chi²(n - 1 - i), A_ij ~ N(0, 1) below), independent of
    the sample mean as for any Gaussian window."""
    m = len(n)
    A = np.zeros((m, 3, 3))
    A[:, [0, 1, 2], [0, 1, 2]] = np.sqrt(rng.chisquare((n - 1)[:, None] - np.arange(3)[None]))
    A[:, [1, 2, 2], [0, 0, 1]] = rng.normal(size=(m, 3))
    LA = L @ A
    return LA @ LA.transpose(0, 2, 1) / (n - 1)[:, None, None]


def _supply(rng: np.random.Generator, t: np.ndarray, duration: float) -> np.ndarray:
    """Supply voltage [V] of a discharging cell: a droop of 0.1-0.3 V over the session, steeper at the end,
    with load ripple."""
    droop = rng.uniform(0.1, 0.3)
    x = t / duration
    return V_NOMINAL + 0.15 - droop * (0.7 * x + 0.3 * x**4) + rng.normal(0, 0.003, t.size)


def _postures(rng: np.random.Generator, m: int, lying_share: float) -> np.ndarray:
    """m gravity directions [body frame] of a wearer's day: bouts of postures, each with its own sway."""
    names = list(_POSTURES)
    upright = [n for n in names if n in ("standing", "leaning", "sitting_back", "slumped", "reclined")]
    lying = [n for n in names if n not in upright]
    out = np.empty((m, 3))
    k = 0
    while k < m:
        name = rng.choice(lying if rng.random() < lying_share else upright)
        pitch, roll = _POSTURES[name]
        bout = min(m - k, int(rng.integers(2, 7)))
        base = np.array([pitch, roll]) + rng.normal(0, 8.0, 2)  # each bout its own way of sitting/lying
        for _ in range(bout):
            pr = base + rng.normal(0, 2.0, 2)  # sway between still moments of one bout
            out[k] = _posture_direction(*pr)
            k += 1
    return out


def session(kind: str, seed: int, *, m: int = 60, duration_s: float = 7200.0, noise_g: float = 0.004,
            floor_g: float = 0.002, effect_scale: float = 1.0) -> Session:
    """One session of ``kind`` (KINDS) with ``m`` quasi-static windows over ``duration_s``; ``effect_scale``
    multiplies the kind's planted term (the same session otherwise: the streams draw the same numbers)."""
    if kind not in KINDS:
        raise ValueError(f"unknown session kind {kind!r}; known: {KINDS}")
    rng = rng_for(kind, seed)
    lab = kind == "misaligned_lab"
    if lab:
        m, duration_s, noise_g, floor_g = 40, 1200.0, 0.0005, 0.00005
    K, o = _sensor(rng, leaned=kind.startswith("misaligned"), lean_deg=2.0 if lab else 1.0)
    truth = Truth(K, o)
    sign = rng.choice([-1, 1], 3)
    s = np.diag(K)
    if kind == "temperature_offset":  # 0.5-3 mg/°C per axis
        truth.c_o = rng.uniform(0.5e-3, 3e-3, 3) * sign * s
    if kind == "temperature_sensitivity":  # 0.02-0.1 %/°C
        truth.c_s = rng.uniform(2e-4, 1e-3, 3) * sign
    if kind == "offset_drift":  # 1-5 mg/h
        truth.d_o = rng.uniform(1e-3, 5e-3, 3) * sign * s
    if kind == "sensitivity_drift":  # 0.1-0.5 %/h
        truth.d_s = rng.uniform(1e-3, 5e-3, 3) * sign
    if kind == "supply_offset":  # 20-80 mg/V
        truth.c_v = rng.uniform(0.02, 0.08, 3) * sign * s
    if kind == "nonlinearity":  # 0.3-1 % of 1 g at 1 g
        truth.c2 = rng.uniform(3e-3, 1e-2, 3) * sign
    for name in ("c_o", "c_s", "d_o", "d_s", "c_v", "c2"):
        setattr(truth, name, getattr(truth, name) * effect_scale)
    if kind == "offsets_held":
        m, duration_s = 25, 900.0  # a short session: the offsets only
    if lab:  # poses by hand: directions uniform over the sphere
        dirs = rng.normal(size=(m, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    else:
        mount = _rotation(rng, 25.0)  # the sensor on the body: a = mount^T (body direction)
        dirs = _postures(rng, m, lying_share=0.15 if kind == "offsets_held" else 0.35) @ mount
    n = rng.integers(int(2 * FS_HZ), int(8 * FS_HZ) + 1, m)
    t_start = np.sort(rng.uniform(0, duration_s - 8.0, m))
    t_mid = t_start + 0.5 * (n - 1) / FS_HZ
    temp = _temperature(rng, t_mid, duration_s)
    volts = _supply(rng, t_mid, duration_s)
    dT, h = temp - T_REF_C, t_mid / 3600.0
    gain = 1.0 + truth.c_s * dT[:, None] + truth.d_s * h[:, None]  # (m, 3)
    K_k = gain[:, :, None] * K[None]  # each window's K
    o_k = o + truth.c_o * dT[:, None] + truth.d_o * h[:, None] + truth.c_v * (volts - V_NOMINAL)[:, None]
    a = dirs + rng.normal(0, floor_g, (m, 3))  # residual motion, constant over the still window
    a = a + truth.c2 * (a * a + noise_g**2)  # the bow, averaged over the window's noise
    L = np.linalg.cholesky(K_k @ K_k.transpose(0, 2, 1)) * noise_g  # samples' noise in raw units: K noise_g² K^T
    mean = np.einsum("mij,mj->mi", K_k, a) + o_k + np.einsum("mij,mj->mi", L, rng.normal(size=(m, 3))) / np.sqrt(n)[:, None]
    cov = _sample_covariance(rng, L, n)
    start = np.round(t_start * FS_HZ).astype(np.int64)
    ws = WindowSet(mean=mean, cov=cov, n=n.astype(float), t=t_mid, aux=np.column_stack([temp, volts]), start=start,
                   end=start + n)
    out = Session(kind, seed, ws, truth, MODEL[kind])
    if kind == "offsets_held":  # a previous calibration's sensitivities, off by its stated std
        out.held_rel_std = 0.01
        out.held_K = np.diag(np.diag(K) * (1 + rng.normal(0, out.held_rel_std, 3)))
    return out
