"""Cramér–Rao bounds for the calibration parameters, per model order.

In use (Lötters): window i gives a mean r_i = K a_i + o + e_i with e_i ~ N(0, C_i),
C_i = cov_i / n_i, and an unknown direction a_i on the unit sphere (a nuisance). Eliminating
the two nuisance angles of every window (Schur complement of the Fisher information) leaves
exactly the information of the scalar norm measurement h_i = |K^-1 (r_i - o)| = 1 [g]:

    F = sum_i  B_i^T B_i / sigma_i^2,     B_i = dh/dp (eq. 13a generalised),
    sigma_i^2 = b_i^T C_i b_i (+ floor^2),  b_i = dh/dr = K^-T a_i / |a_i|

(the tangential part of e_i only moves the unknown direction). CRLB = F^-1. The Lötters
estimator (eq. 11a/b) is the weighted least squares of the same linearised model, so its
covariance eq. 11b equals this bound at the truth: efficiency is how close its MSE comes.

Lab (Bragge, eq. 2-4): the directions are known, the model is linear, F = H^T W H and the
bound equals the least-squares covariance.

Parameters are in the recording's raw units (sensitivities raw/g, offsets raw); dividing by
the sensitivity turns both into g at 1 g, which is how errors are reported (``accel_rms_g``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .calibration import Calibration
from .estimators.parameterization import PARAMETERIZATIONS, Parameterization, h_variance  # noqa: F401 (re-exported: crlb.h_variance)
from .windows import WindowSet, validate_windows

# Relative eigenvalue below which a direction of parameter space counts as not determined.
RANK_RTOL = 1e-9


def sphere_directions(n: int = 256) -> np.ndarray:
    """n roughly uniform unit vectors (Fibonacci lattice), for averages over all orientations."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (1.0 + 5.0**0.5) * k
    rho = np.sqrt(1.0 - z * z)
    return np.column_stack([rho * np.cos(phi), rho * np.sin(phi), z])


def make_parameterization(model: str | Parameterization, cal: Calibration) -> Parameterization:
    """The parameterization ``model`` (a name in PARAMETERIZATIONS) around ``cal``'s (K, o)."""
    if isinstance(model, Parameterization):
        return model
    try:
        cls = PARAMETERIZATIONS[str(model)]
    except KeyError:
        raise ValueError(f"unknown model {model!r}; expected one of {sorted(PARAMETERIZATIONS)}") from None
    return cls(cal.sensitivity, cal.offset)


def on_ellipsoid(ws: WindowSet, cal: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """(directions a_i (M, 3) unit [g], noise-free means r_i* = K a_i + o (M, 3) raw)."""
    if len(ws):
        validate_windows(ws)  # every information built from them goes to LAPACK (eigh may loop forever on a NaN)
    a = cal.apply_reference(ws.mean)
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    return a, a @ cal.sensitivity.T + cal.offset


def norm_noise_var(ws: WindowSet, cal: Calibration, *, sigma_floor_g: float = 0.0) -> np.ndarray:
    """Variance [g^2] of each window's norm measurement h_i: h_variance + floor^2."""
    a, _ = on_ellipsoid(ws, cal)
    return h_variance(a, np.linalg.inv(cal.sensitivity), ws.cov_of_mean) + float(sigma_floor_g) ** 2


def sphere_metric(param: Parameterization, cal: Calibration, n_dirs: int = 256) -> np.ndarray:
    """G = mean over the sphere of J(a)^T J(a), J = da/dp: |dp|_G is the RMS calibrated-acceleration
    error [g] over all orientations that a parameter error dp produces."""
    p = param.pack(cal.sensitivity, cal.offset)
    u = sphere_directions(n_dirs)
    _, J = param.accel_and_jacobian(p, u @ cal.sensitivity.T + cal.offset)
    return np.einsum("mip,miq->pq", J, J) / len(u)


@dataclass
class Bound:
    """A Cramér–Rao bound: covariance over ``names`` (raw units) and what it means in g."""

    model: str
    names: list[str]
    fisher: np.ndarray  # (P, P) [1/raw^2]
    cov: np.ndarray  # (P, P) [raw^2]; inf on the diagonal for undetermined parameters
    eigvals: np.ndarray  # eigenvalues of the Fisher information, ascending
    identifiable: bool  # every parameter determined (Fisher information full rank)
    accel_rms_g: float  # predicted RMS calibrated-acceleration error over all orientations [g]
    n_windows: int
    undetermined: list[str] = field(default_factory=list)  # parameters in the null space

    @property
    def trace(self) -> float:
        return float(np.trace(self.cov))

    @property
    def std(self) -> dict[str, float]:
        return {n: float(np.sqrt(v)) for n, v in zip(self.names, np.diag(self.cov))}


def bound_from_fisher(model: str, names: list[str], F: np.ndarray, G: np.ndarray, n_windows: int) -> Bound:
    F = 0.5 * (F + F.T)
    w, V = np.linalg.eigh(F)
    null = w <= RANK_RTOL * max(w.max(), 1e-300)
    keep = ~null
    cov = (V[:, keep] / w[keep]) @ V[:, keep].T
    undetermined: list[str] = []
    if null.any():
        load = np.abs(V[:, null]).max(axis=1) > 1e-6
        undetermined = [n for n, bad in zip(names, load) if bad]
        cov[load, load] = np.inf  # the pseudo-inverse elsewhere; these have no bound
        accel = float("inf")
    else:
        accel = float(np.sqrt(max(np.trace(G @ cov), 0.0)))
    return Bound(model, list(names), F, cov, w, not null.any(), accel, int(n_windows), undetermined)


def fisher_inuse(ws: WindowSet, cal: Calibration, model: str | Parameterization = "9", *,
                 sigma_floor_g: float = 0.0, unit_floor_g: float | None = None):
    """Fisher information of the in-use (norm) problem at calibration ``cal`` (the truth for a bound,
    the current estimate for a decision). Returns (F (P, P) [1/raw^2], the parameterization); with
    ``unit_floor_g`` also a third item, the information with that floor instead of ``sigma_floor_g``
    (same Jacobian, computed once: order.observability's per-window geometry)."""
    param = make_parameterization(model, cal)
    if len(ws) == 0:
        Z = np.zeros((param.n_params, param.n_params))
        return (Z, param) if unit_floor_g is None else (Z, param, Z.copy())
    _, r_star = on_ellipsoid(ws, cal)
    p = param.pack(cal.sensitivity, cal.offset)
    _, B, _ = param.norm_and_jacobian(p, r_star)
    var0 = norm_noise_var(ws, cal)
    var = var0 + float(sigma_floor_g) ** 2
    if np.any(var <= 0):
        raise ValueError("window noise is zero: give window covariances (cov, n) or a sigma_floor_g > 0")
    F = (B / var[:, None]).T @ B
    if unit_floor_g is None:
        return F, param
    return F, param, (B / (var0 + float(unit_floor_g) ** 2)[:, None]).T @ B


def crlb(ws: WindowSet, cal: Calibration, model: str = "9", *, sigma_floor_g: float = 0.0) -> Bound:
    """Cramér–Rao bound of the in-use model order ``model`` ("offsets", "6", "9", "12") for these
    windows, evaluated at ``cal`` (the truth). "9" and "12" have the same bound: the held frame
    does not enter the norm."""
    F, param = fisher_inuse(ws, cal, model, sigma_floor_g=sigma_floor_g)
    return bound_from_fisher(param.model, param.names, F, sphere_metric(param, cal), len(ws))


# -- lab (Bragge) -----------------------------------------------------------------------------
BRAGGE_NAMES = [f"k_{i + 1}{j + 1}" for j in range(3) for i in range(3)] + ["o_x", "o_y", "o_z"]  # theta of eq. 2


def bragge_H(directions: np.ndarray) -> np.ndarray:
    """Stacked observation matrix (eq. 2-3) for known accelerations a (N, 3) [g]: (3N, 12)."""
    a = np.asarray(directions, dtype=float).reshape(-1, 3)
    n = a.shape[0]
    H = np.zeros((n, 3, 12))
    for j in range(3):  # theta = (k11, k21, k31, k12, ..., k33, ox, oy, oz): column-major K
        H[:, :, 3 * j:3 * j + 3] = a[:, j, None, None] * np.eye(3)[None]
    H[:, :, 9:] = np.eye(3)[None]
    return H.reshape(3 * n, 12)


def crlb_lab(directions: np.ndarray, cov_of_mean: np.ndarray, cal: Calibration | None = None) -> Bound:
    """Bound of Bragge's linear model for known directions (N, 3) and window-mean covariances
    (N, 3, 3) [raw^2]: F = H^T W H (eq. 4 is efficient here, so this is also its covariance)."""
    H = bragge_H(directions)
    C = np.asarray(cov_of_mean, dtype=float).reshape(-1, 3, 3)
    W = np.zeros((H.shape[0], H.shape[0]))
    for i, Ci in enumerate(C):
        W[3 * i:3 * i + 3, 3 * i:3 * i + 3] = np.linalg.inv(Ci)
    F = H.T @ W @ H
    if cal is None:
        G = np.eye(12)
    else:  # a = K^-1 (raw - o): da/dtheta for every direction on the sphere
        u = sphere_directions()
        Kinv = np.linalg.inv(cal.sensitivity)
        J = -np.einsum("ij,mjp->mip", Kinv, bragge_H(u).reshape(len(u), 3, 12))
        G = np.einsum("mip,miq->pq", J, J) / len(u)
    return bound_from_fisher("12-lab", BRAGGE_NAMES, F, G, len(C))


# -- window-level experiments (tests, benches, docs) ----------------------------------------------
def cap_directions(center: np.ndarray, theta_max_deg: float, m: int, rng: np.random.Generator) -> np.ndarray:
    """m unit vectors uniform on the spherical cap of half-angle theta_max around ``center``
    (Lötters' Fig. 6: postures spread up to theta from the most frequent one)."""
    c = np.asarray(center, dtype=float)
    c = c / np.linalg.norm(c)
    cos_min = np.cos(np.radians(theta_max_deg))
    z = rng.uniform(cos_min, 1.0, m)
    phi = rng.uniform(0.0, 2 * np.pi, m)
    rho = np.sqrt(np.clip(1 - z * z, 0, None))
    local = np.column_stack([rho * np.cos(phi), rho * np.sin(phi), z])
    # rotation taking e_z to c (Householder-free: Rodrigues about e_z x c)
    ez = np.array([0.0, 0.0, 1.0])
    v = np.cross(ez, c)
    s, cth = np.linalg.norm(v), float(ez @ c)
    if s < 1e-12:
        R = np.eye(3) if cth > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
        R = np.eye(3) + vx + vx @ vx * ((1 - cth) / s**2)
    return local @ R.T


def windows_on_ellipsoid(cal: Calibration, directions: np.ndarray, *, noise_g: float, n: int,
                         rng: np.random.Generator) -> WindowSet:
    """Windows of n samples each at the given directions [g] through raw = K a + o, with white
    isotropic sample noise ``noise_g`` [g rms per axis] (so cov of the mean = K K^T noise^2 / n)."""
    a = np.asarray(directions, dtype=float).reshape(-1, 3)
    m = a.shape[0]
    C = cal.sensitivity @ cal.sensitivity.T * noise_g**2  # sample covariance [raw^2]
    L = np.linalg.cholesky(C / n)
    mean = a @ cal.sensitivity.T + cal.offset + rng.standard_normal((m, 3)) @ L.T
    return WindowSet(mean, np.broadcast_to(C, (m, 3, 3)).copy(), np.full(m, float(n)), np.arange(m, dtype=float),
                     np.zeros((m, 0)), np.arange(m, dtype=np.int64) * n, np.arange(1, m + 1, dtype=np.int64) * n)


DAILY_POSTURES = {  # body-frame direction of the reading at rest (x forward, y left, z up) [g], share, spread [deg]
    "upright": ((0.0, 0.0, 1.0), 0.55, 12.0),
    "reclined": ((-0.5, 0.0, 0.87), 0.15, 12.0),
    "bent": ((0.6, 0.0, 0.8), 0.06, 20.0),
    "lie_back": ((-1.0, 0.0, 0.0), 0.07, 10.0),
    "lie_front": ((1.0, 0.0, 0.0), 0.05, 10.0),
    "lie_left": ((0.0, 1.0, 0.0), 0.06, 10.0),
    "lie_right": ((0.0, -1.0, 0.0), 0.06, 10.0),
}


def daily_living_directions(m: int, rng: np.random.Generator, mount: np.ndarray | None = None) -> np.ndarray:
    """m window directions [g, sensor frame] of a waist-worn sensor over a day with a night: mostly
    upright and sitting, some bending, lying on back/front/sides (shares in DAILY_POSTURES). ``mount``:
    body -> sensor rotation (default identity: Lötters' orientation 1)."""
    names = list(DAILY_POSTURES)
    share = np.array([DAILY_POSTURES[n][1] for n in names])
    pick = rng.choice(len(names), size=m, p=share / share.sum())
    out = np.empty((m, 3))
    for k, n in enumerate(names):
        idx = np.flatnonzero(pick == k)
        if idx.size:
            c, _, spread = DAILY_POSTURES[n]
            out[idx] = cap_directions(np.asarray(c), spread, idx.size, rng)
    R = np.eye(3) if mount is None else np.asarray(mount, dtype=float)
    return out @ R.T
