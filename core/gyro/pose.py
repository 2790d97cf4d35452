"""Gyro sensitivity from pose-to-pose rotations (in use: no turntable, no known angles).

Between two quasi-static windows i and j the body turned by C_T = prod exp([omega_k dt]x),
integrated from the gyro. Gravity is fixed in the world, so its direction in the body frame,
measured by the calibrated accelerometer in both windows, must satisfy

    g_j = C_T^T g_i                                   (g: unit vectors, body frame)

With omega = M u (u: gyro counts above the bias with the board's high-pass undone,
``conditioning``; M = sensitivity^-1 [rad/s per count]) this is a nonlinear measurement of M.
Two components of g_j are informative (its length is 1 by construction), so each pair gives a
2-vector residual r = E^T (g_j - C_T^T g_i), E (3x2) orthogonal to g_j.

Jacobian (first order, body-frame error at the end): a rate error d_omega_k rotates the end
attitude by d_phi = sum_k C_T^T C_k d_omega_k dt, and the predicted gravity changes by
[g_pred]x d_phi. d_omega = dM u (matrix) or axis * u * dm (single-axis ENC-03J: M = m a, a
scalar m along the known sensitive axis a).

The estimate is recursive: an iterated extended Kalman filter over pairs (state vec(M), its
covariance P), each pair re-linearised 3 times (pose changes are large rotations). A pair is
rejected, with its reason counted, when
- the gyro path angle sum |omega| dt is below ``min_angle_rad``: "no rotation between windows";
- the part of the rotation perpendicular to gravity is below ``min_angle_rad``: "rotation about
  the gravity axis only (unobservable from gravity)" (e.g. a turn on a turntable);
- any sample reaches the gyro's range or the ADC rails: "saturated". The range is compared with
  the rate at the current scale, lowered by the scale's uncertainty (3 sigma, at most
  SCALE_SPREAD): the ENC-03J clips at 300 °/s, which a board 20 % below the start scale reads
  as 240 °/s, and a clipped rotation that slipped in would pull the scale up;
- single-axis gyro: gravity's component along the sensitive axis changed by more than 4 sigma:
  "rotation not about the gyro's sensitive axis" (a rotation about the axis keeps it; the gyro
  cannot see the rest of the rotation, so the pair would pull the scale anywhere, even past 0);
  this test uses the accelerometer only, so it holds from the first pair, whatever the start;
- the normalised innovation exceeds the gate: "inconsistent with the gyro model" (translation
  during the windows, a turn out of the axis and back).
Observability at the end: the information from the data, whitened by the prior, must exceed
``MIN_INFORMATION_RATIO`` in every direction of the parameter space, otherwise no sensitivity
is claimed (``observable`` False and a message saying which directions are missing); nor with
fewer than ``min_pairs`` accepted pairs, less than ``min_total_angle_rad`` of rotation across
gravity in them, or a reduced chi2 of their residuals above ``max_reduced_chi2`` (the pairs
disagree with each other beyond their noise: model error). Below that limit the covariance is
inflated by the reduced chi2 when it exceeds 1.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from .rotation import attitude, orthonormal_complement, skew

NO_ROTATION = "no rotation between windows"
ABOUT_GRAVITY = "rotation about the gravity axis only (unobservable from gravity)"
SATURATED = "saturated (rate beyond the gyro's range or ADC at its rails)"
INCONSISTENT = "inconsistent with the gyro model (innovation beyond the gate)"
TOO_LONG = "too long between windows"
OFF_AXIS = "rotation not about the gyro's sensitive axis (gravity's component along it changed)"
OFF_AXIS_CHI2 = 16.0  # 1 degree of freedom: a 4-sigma change of gravity along the sensitive axis
# No sensitivity claimed from fewer accepted pairs: one pair cannot show its own model error, and 4-5
# pairs could not expose a rotation the gyro only partly sees (a six-position session's hand turns: a
# turn about the vertical combined with 90 deg about y; 2 of 10 seeds claimed 1.4 % low at z ~ 3.7
# with 4; none with 8: bench/bench_gyro.py, docs/gyro.md).
MIN_PAIRS = 8
MIN_TOTAL_ANGLE_RAD = np.deg2rad(90.0)  # summed rotation (across gravity) of the accepted pairs
MAX_REDUCED_CHI2 = 4.0  # pairs' residuals beyond 2x their modelled std: model error, no claim
MIN_INFORMATION_RATIO = 9.0  # data information >= 9x the prior's in every direction: posterior std <= prior/3
GATE_CHI2 = 25.0  # 2 degrees of freedom: P(chi2 > 25) = 4e-6 for a consistent pair
SCALE_SPREAD = 0.25  # largest scale error assumed by the saturation test (ENC-03J: +-20 % from nominal)


@dataclass
class Pair:
    """What one rotation between quasi-static windows i and j contributes.

    u (K, k): gyro counts above the bias, high-pass undone, detrended on the two windows, for
    the K samples from the start of window i to the end of window j (k = 1 for the ENC-03J,
    3 for a triaxial gyro); n_i, n_j: samples of window i (the first n_i) and j (the last n_j);
    dt [s]; g_i, g_j (3,) unit gravity directions (body frame) = the accelerometer's window
    means, calibrated; cov_i, cov_j (3, 3) their covariances; rest_rms (k,) rms of u in the
    windows [counts] (noise); saturated: a sample at the ADC rails.

    A window's mean is the average over its samples: if the board still moves a little inside
    it (the ends of a slow pose change that the detector let in), the mean direction is
    B gamma with B = mean_k C_k^T over the window, gamma the direction in a reference frame.
    The prediction uses these averages (g_j = B_j B_i^-1 g_i), so motion inside windows is
    integrated rather than ignored.
    """

    u: np.ndarray
    dt: float
    g_i: np.ndarray
    g_j: np.ndarray
    cov_i: np.ndarray
    cov_j: np.ndarray
    rest_rms: np.ndarray
    n_rest: int
    n_i: int = 1
    n_j: int = 1
    saturated: bool = False
    t_i: float = 0.0
    t_j: float = 0.0


@dataclass
class PairOutcome:
    accepted: bool
    reason: str = ""
    path_angle_rad: float = 0.0
    perp_angle_rad: float = 0.0
    residual_rad: float = float("nan")  # |g_j - C_T^T g_i| after the update (small-angle: an angle)
    nis: float = float("nan")  # normalised innovation squared before the update (2 dof)


@dataclass
class PoseToPose:
    """Recursive pose-to-pose gyro sensitivity (IEKF over pairs).

    kind "scalar": single-axis gyro along ``axis`` (board frame), state [m] [rad/s per count].
    kind "matrix": triaxial gyro, state vec(M) row-major (9), omega = M u.
    ``start``: M (k x k) or m [rad/s per count]; ``start_rel_std``: prior std relative to the
    start's scale (a weak prior: 0.5 = +-50 %). ``range_rad_s``: gyro range (per axis).
    ``floor_rad``: extra isotropic noise on each gravity direction [rad] (posture sway, linear
    acceleration in the windows, accelerometer calibration residuals); 0.5°: the held-out
    residual of simulated foot poses and of the measured Xsens poses is 0.5-0.9°.
    """

    kind: str
    start: np.ndarray
    axis: np.ndarray | None = None
    start_rel_std: float = 0.5
    range_rad_s: float = np.inf
    min_angle_rad: float = np.deg2rad(10.0)
    floor_rad: float = np.deg2rad(0.5)
    gate_chi2: float = GATE_CHI2
    iterations: int = 3
    gate_after: int = 3  # pairs accepted before the innovation gate applies (0: from the first)
    min_pairs: int = MIN_PAIRS
    min_total_angle_rad: float = MIN_TOTAL_ANGLE_RAD
    max_reduced_chi2: float = MAX_REDUCED_CHI2
    x: np.ndarray = field(init=False)
    P: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        if self.kind not in ("scalar", "matrix"):
            raise ValueError(f"kind must be 'scalar' (single-axis gyro) or 'matrix' (triaxial), not {self.kind!r}")
        s = np.asarray(self.start, dtype=float)
        if self.kind == "scalar":
            if self.axis is None:
                raise ValueError("a single-axis gyro needs its sensitive axis (board frame)")
            self.axis = np.asarray(self.axis, float) / np.linalg.norm(self.axis)
            self.x = s.reshape(1).copy()
            scale = abs(float(self.x[0]))
        else:
            self.x = s.reshape(9).copy() if s.size == 9 else (np.eye(3) * float(s)).reshape(9)
            scale = float(np.linalg.norm(self.x) / np.sqrt(3.0))  # rms singular value
        if not (np.all(np.isfinite(self.x)) and scale > 0):
            raise ValueError(f"start sensitivity must be finite and non-zero, got {self.start!r}")
        self.P0 = np.eye(self.x.size) * (self.start_rel_std * scale) ** 2
        self.P = self.P0.copy()
        self.rejected: Counter[str] = Counter()
        self.n_pairs = 0
        self.total_angle_rad = 0.0  # summed rotation across gravity of the accepted pairs [rad]
        self.chi2 = 0.0  # sum of post-update NIS over accepted pairs (consistency of the noise model)

    # -- model -------------------------------------------------------------------------
    @property
    def k(self) -> int:
        return 1 if self.kind == "scalar" else 3

    def rate_matrix(self, x: np.ndarray | None = None) -> np.ndarray:
        """(3, k): omega [rad/s] = rate_matrix @ u [counts]."""
        x = self.x if x is None else x
        return (self.axis * x[0]).reshape(3, 1) if self.kind == "scalar" else x.reshape(3, 3)

    def _predict(self, x: np.ndarray, pair: Pair):
        u = pair.u.reshape(-1, self.k)
        omega = u @ self.rate_matrix(x).T
        C = attitude(omega, pair.dt)
        if C.shape[0] == 0:
            C = np.eye(3)[None]
        Bi = C[: pair.n_i].mean(axis=0).T  # window means of C_k^T
        Bj = C[C.shape[0] - pair.n_j:].mean(axis=0).T
        g_pred = Bj @ np.linalg.solve(Bi, pair.g_i)
        g_pred /= np.linalg.norm(g_pred)
        # Jacobian of the rotation between the window centres (the windows hold little motion)
        ci, cj = pair.n_i // 2, C.shape[0] - 1 - pair.n_j // 2
        Cr = np.einsum("ji,kjl->kil", C[ci], C[ci:cj + 1])  # C_ci^T C_k: frames relative to centre i
        Cm = 0.5 * (Cr[1:] + Cr[:-1])  # mid-sample attitude: exact to O(dt^2)
        A = np.einsum("ji,kjl->kil", Cr[-1], Cm)  # A_k = C_T^T C_k
        uc = u[ci + 1:cj + 1]
        if self.kind == "scalar":
            J_phi = np.einsum("kil,l,k->i", A, self.axis, uc[:, 0])[:, None] * pair.dt
        else:
            J_phi = np.einsum("kir,kc->irc", A, uc).reshape(3, 9) * pair.dt
        J = skew(g_pred) @ J_phi
        return g_pred, J, C, omega

    def _angles(self, C: np.ndarray, omega: np.ndarray, g_i: np.ndarray, dt: float) -> tuple[float, float]:
        g_body = np.einsum("kji,j->ki", C, g_i)  # gravity in the body frame at each sample (approx.)
        along = np.einsum("ki,ki->k", omega, g_body)
        perp = np.sqrt(np.clip(np.einsum("ki,ki->k", omega, omega) - along**2, 0, None))
        return float(np.linalg.norm(omega, axis=1).sum() * dt), float(perp.sum() * dt)

    def _noise(self, pair: Pair, CT: np.ndarray, E: np.ndarray) -> np.ndarray:
        rm = self.rate_matrix()
        # gyro noise integrated over the gap + uncertainty of the detrend line over its length
        n_gap = max(pair.u.shape[0] - (pair.n_i + pair.n_j) // 2, 1)  # samples between the window centres
        T = n_gap * pair.dt
        var_u = np.asarray(pair.rest_rms, float).reshape(self.k) ** 2
        var_phi = (rm**2 @ var_u) * (n_gap * pair.dt**2 * 4.0 + T**2 / max(pair.n_rest, 1))
        R3 = pair.cov_j + CT.T @ pair.cov_i @ CT + (2 * self.floor_rad**2 + var_phi.sum()) * np.eye(3)
        return E.T @ R3 @ E

    # -- recursion ------------------------------------------------------------------------
    def update(self, pair: Pair) -> PairOutcome:
        """Fold one pair in (or reject it, counting the reason)."""
        if pair.saturated:
            return self._reject(SATURATED)
        if self.kind == "scalar":
            a = self.axis
            d = float(a @ (pair.g_j - pair.g_i))
            var = float(a @ (pair.cov_i + pair.cov_j) @ a) + 2 * self.floor_rad**2
            if d * d > OFF_AXIS_CHI2 * var:
                return self._reject(OFF_AXIS)
        g_pred, J, C, omega = self._predict(self.x, pair)
        path, perp = self._angles(C, omega, pair.g_i, pair.dt)
        if np.any(np.abs(omega) >= self.saturation_rad_s()):
            return self._reject(SATURATED, path, perp)
        if path < self.min_angle_rad:
            return self._reject(NO_ROTATION, path, perp)
        if perp < self.min_angle_rad:
            return self._reject(ABOUT_GRAVITY, path, perp)
        E = orthonormal_complement(pair.g_j)
        R = self._noise(pair, C[-1], E)
        H = E.T @ J
        r = E.T @ (pair.g_j - g_pred)
        S = H @ self.P @ H.T + R
        nis = float(r @ np.linalg.solve(S, r))
        if nis > self.gate_chi2 and self.n_pairs >= self.gate_after:  # the first pairs may be far from a weak start
            return self._reject(INCONSISTENT, path, perp, nis)
        xi = self.x.copy()
        for _ in range(self.iterations):  # iterated EKF: re-linearise at the updated state
            K = self.P @ H.T @ np.linalg.inv(H @ self.P @ H.T + R)
            x_new = self.x + K @ (r - H @ (self.x - xi))
            xi = x_new
            g_pred, J, C, omega = self._predict(xi, pair)
            H = E.T @ J
            r = E.T @ (pair.g_j - g_pred)
        K = self.P @ H.T @ np.linalg.inv(H @ self.P @ H.T + R)
        I_KH = np.eye(self.x.size) - K @ H
        self.P = I_KH @ self.P @ I_KH.T + K @ R @ K.T  # Joseph form
        self.x = xi
        post = float(r @ np.linalg.solve(R, r))
        self.chi2 += post
        self.n_pairs += 1
        self.total_angle_rad += perp
        return PairOutcome(True, "", path, perp, float(np.linalg.norm(pair.g_j - g_pred)), nis)

    def scale_rel_std(self) -> float:
        """Relative standard deviation of the rate scale (largest direction for a matrix)."""
        if self.kind == "scalar":
            return float(np.sqrt(self.P[0, 0]) / abs(self.x[0]))
        scale = float(np.linalg.norm(self.x) / np.sqrt(3.0))
        return float(np.sqrt(np.linalg.eigvalsh(self.P).max()) / scale)

    def saturation_rad_s(self) -> float:
        """|rate| [rad/s] at the current scale from which a pair counts as saturated: 98 % of the
        range, divided by 1 + the scale's uncertainty (3 sigma, at most SCALE_SPREAD)."""
        return 0.98 * self.range_rad_s / (1.0 + min(SCALE_SPREAD, 3.0 * self.scale_rel_std()))

    def _reject(self, reason: str, path: float = 0.0, perp: float = 0.0, nis: float = float("nan")) -> PairOutcome:
        self.rejected[reason] += 1
        return PairOutcome(False, reason, path, perp, float("nan"), nis)

    # -- results ----------------------------------------------------------------------------
    def information_ratio(self) -> np.ndarray:
        """Eigenvalues of the data information whitened by the prior (ascending): how many times
        the pairs outweigh the prior in each direction of the parameter space."""
        info = np.linalg.inv(self.P) - np.linalg.inv(self.P0)
        w = np.linalg.cholesky(self.P0)
        return np.linalg.eigvalsh(w.T @ info @ w)

    def why_not_determined(self) -> str:
        """Empty when the pairs determine the sensitivity; otherwise the reason."""
        if self.n_pairs == 0:
            return "no usable rotation between quasi-static windows"
        if self.n_pairs < self.min_pairs:
            return f"{self.n_pairs} pair(s) accepted, need {self.min_pairs} (a single pair cannot show its own model error)"
        if self.total_angle_rad < self.min_total_angle_rad:
            return (f"the accepted pairs turned {np.degrees(self.total_angle_rad):.0f}° in all across gravity, "
                    f"need {np.degrees(self.min_total_angle_rad):.0f}°")
        c = self.reduced_chi2()
        if np.isfinite(c) and c > self.max_reduced_chi2:
            return (f"the pairs disagree beyond their noise (reduced chi2 {c:.3g} > {self.max_reduced_chi2:g}: "
                    f"model error, e.g. rotations the gyro does not see)")
        lam = self.information_ratio()
        if float(lam[0]) < MIN_INFORMATION_RATIO:
            weak = int(np.sum(lam < MIN_INFORMATION_RATIO))
            what = ("the scale" if self.kind == "scalar" else
                    f"{weak} of the 9 matrix directions (rotations about too few axes across gravity)")
            return (f"{self.n_pairs} pair(s) do not determine {what} "
                    f"(information {lam[0]:.2g}x the prior's, need {MIN_INFORMATION_RATIO:g}x)")
        return ""

    @property
    def observable(self) -> bool:
        return self.n_pairs > 0 and not self.why_not_determined()

    def message(self) -> str:
        rej = "; ".join(f"{n} x {why}" for why, n in sorted(self.rejected.items(), key=lambda kv: -kv[1]))
        why = self.why_not_determined()
        if why:
            return f"no sensitivity: {why}" + (f"; rejected: {rej}" if rej else "")
        return f"{self.n_pairs} pair(s) used" + (f"; rejected: {rej}" if rej else "")

    def reduced_chi2(self) -> float:
        dof = 2 * self.n_pairs - self.x.size
        return self.chi2 / dof if dof > 0 else float("nan")

    def rate_matrix_and_cov(self, inflate: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """(M (k, k) [rad/s per count], covariance of vec(M)), inflated by the reduced chi2
        when above 1 (noise model too optimistic, as on measured data)."""
        c = self.reduced_chi2()
        f = max(1.0, c) if inflate and np.isfinite(c) else 1.0
        M = self.x.reshape(1, 1) if self.kind == "scalar" else self.x.reshape(3, 3)
        return M.copy(), self.P * f

    def sensitivity(self, inflate: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """(S = M^-1 (k, k) [counts per rad/s], covariance of vec(S) row-major) by the delta
        method: d vec(S) = -(S kron S^T) d vec(M)."""
        M, cov = self.rate_matrix_and_cov(inflate)
        S = np.linalg.inv(M)
        D = -np.kron(S, S.T)
        return S, D @ cov @ D.T
