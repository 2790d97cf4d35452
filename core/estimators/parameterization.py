"""Parameterizations of the calibration-level sensor model raw = K a + o.

An estimator never hard-codes which parameters it estimates: it asks a parameterization
for (K, o) given the parameter vector p and for the Jacobian of the corrected acceleration
a = K^-1 (raw - o) with respect to p. The Lötters measurement is h = |a| (eq. 8), so

    dh/dp = (a / |a|)^T  da/dp,      da/dp_m = -K^-1 (dK/dp_m a + do/dp_m)

which for the 6-parameter model reduces to the paper's eq. 13a. Every parameterization here
is linear in p (dK/dp and do/dp are constant), which keeps the Jacobian exact and cheap.
Adding a model order (9, 12, temperature terms, ...) means adding a subclass.
"""
from __future__ import annotations

from abc import ABC
from typing import ClassVar

import numpy as np

from gravcal.core.accelerator import kernels

_fitsums = kernels("gravcal.core._fitsums")
_jacobians = kernels("gravcal.core.estimators._jacobians")
AXES = ("x", "y", "z")


class Parameterization(ABC):
    """p <-> (K, o) with constant derivatives dK (P, 3, 3) and do (P, 3).

    ``K0``, ``o0`` hold the values of whatever this parameterization does not estimate
    (e.g. the sensitivities in offsets-only mode, or the frame rotation in 12-in-use).
    """

    model: ClassVar[str]
    names: list[str]
    dK: np.ndarray
    do: np.ndarray

    def __init__(self, K0: np.ndarray, o0: np.ndarray):
        self.K0 = np.asarray(K0, dtype=float).reshape(3, 3).copy()
        self.o0 = np.asarray(o0, dtype=float).reshape(3).copy()

    @property
    def n_params(self) -> int:
        return len(self.names)

    covariates: ClassVar[tuple[str, ...]] = ()
    """Per-window covariates dK/do depend on (e.g. "temp_c", "t_s"; core/estimators/extended.py).
    Empty (every parameterization here): constant derivatives."""

    def at_windows(self, ws) -> "Parameterization":
        """This parameterization bound to the covariates of the windows ``ws`` (a WindowSet, same rows
        as the means it will be given); itself when it has no covariates."""
        return self

    def unusable_windows(self) -> str:
        """Why the windows this parameterization is bound to cannot be fitted ("" when they can)."""
        return ""

    def unpack(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K, o) for parameter vector p."""
        p = np.asarray(p, dtype=float)
        K = self.K_const + np.tensordot(p, self.dK, axes=1)
        o = self.o_const + p @ self.do
        return K, o

    def pack(self, K: np.ndarray, o: np.ndarray) -> np.ndarray:
        """The p whose (K, o) is closest (least squares in the entries) to the given (K, o)."""
        A = np.concatenate([self.dK.reshape(self.n_params, 9), self.do], axis=1).T  # (12, P)
        b = np.concatenate([(np.asarray(K) - self.K_const).ravel(), np.asarray(o) - self.o_const])
        return np.linalg.lstsq(A, b, rcond=None)[0]

    # Constant parts: the values of K and o at p = 0.
    K_const: np.ndarray
    o_const: np.ndarray

    def accel_and_jacobian(self, p: np.ndarray, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """a = K^-1 (raw - o) for rows raw (M, 3), and da/dp (M, 3, P)."""
        K, o = self.unpack(p)
        Kinv = np.linalg.inv(K)
        a = (np.asarray(raw, dtype=float) - o) @ Kinv.T  # (M, 3)
        # dK/dp_m a + do/dp_m  for every window and parameter: (M, 3, P)
        # J = -(G_p a + c_p) with G_p = Kinv dK_p, c_p = Kinv do_p: one (M, 3) @ (3, 3P) product
        # (~10x faster than contracting (M, 3, P) arrays with einsum)
        P = self.dK.shape[0]
        G = np.matmul(Kinv, self.dK)  # (P, 3, 3)
        J = (a @ G.transpose(2, 1, 0).reshape(3, 3 * P)).reshape(-1, 3, P)
        J += (self.do @ Kinv.T).T[None, :, :]
        np.negative(J, out=J)
        return a, J

    def norm_and_jacobian(self, p: np.ndarray, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """h = |a| (eq. 8), dh/dp (M, P) (eq. 13a generalised), and a itself."""
        h, B, a, _ = self.norm_jacobian_variance(p, raw)
        return h, B, a

    def norm_jacobian_variance(self, p: np.ndarray, raw: np.ndarray, cov_mean: np.ndarray | None = None
                               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """norm_and_jacobian's h, dh/dp, a and, given the windows' covariance of the mean (M, 3, 3), the
        delta-method variance of h with K^-1 of p (h_variance, Lötters' C_mu before any floor), else None.
        From 2 rows on in one compiled pass (core/estimators/_jacobians.c, equal bit for bit); one row, as the
        online estimator's, is a dgemv in numpy's products and keeps numpy's form."""
        raw = np.ascontiguousarray(raw, dtype=float)
        K, o = self.unpack(p)
        Kinv = np.linalg.inv(K)
        if raw.ndim != 2 or raw.shape[0] < 2:
            a, J = self.accel_and_jacobian(p, raw)
            h, B = norm_and_projection(a, J)
            if cov_mean is None:
                return h, B, a, None
            return h, B, a, h_variance(a, Kinv, cov_mean, h)
        M, P = raw.shape[0], self.dK.shape[0]
        G = np.matmul(Kinv, self.dK)  # (P, 3, 3), as accel_and_jacobian
        C = np.ascontiguousarray((self.do @ Kinv.T).T)
        h, B, a = np.empty(M), np.empty((M, P)), np.empty((M, 3))
        var = None if cov_mean is None else np.empty(M)
        cov = None if cov_mean is None else np.ascontiguousarray(cov_mean, dtype=float)
        _jacobians.linear_norm_jacobian(np.ascontiguousarray(Kinv), o, np.ascontiguousarray(G), C, raw, cov, h, B, a,
                                        var, M, P)
        return h, B, a, var


def norm_and_projection(a: np.ndarray, J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """h = |a| (M,) and the rows (a / h)^T J (M, P) for a (M, 3), J (M, 3, P): numpy's np.linalg.norm(a, axis=1)
    and einsum("mi,mip->mp", a / h[:, None], J), compiled."""
    M, P = J.shape[0], J.shape[2]
    h, B = np.empty(M), np.empty((M, P))
    _fitsums.norm_project(np.ascontiguousarray(a, dtype=float), np.ascontiguousarray(J, dtype=float), h, B, M, P)
    return h, B


def h_variance(a: np.ndarray, Kinv: np.ndarray, cov_mean: np.ndarray, h: np.ndarray | None = None) -> np.ndarray:
    """Delta-method variance [g²] of h = |a| from the covariance of the window mean (raw units²):
    dh/dm = (a/|a|)^T K^-1, so var h = g cov g^T with g that row vector (Lötters' C_mu, per window).
    ``h``: |a| when the caller has it (np.linalg.norm(a, axis=1) or the equal norm_and_projection)."""
    u = a / (np.linalg.norm(a, axis=1, keepdims=True) if h is None else h[:, None])
    g = u @ Kinv
    out = np.empty(g.shape[0])  # numpy's einsum("mi,mij,mj->m", g, cov_mean, g), compiled
    _fitsums.quadratic(np.ascontiguousarray(g, dtype=float), np.ascontiguousarray(cov_mean, dtype=float), out, g.shape[0])
    return out


class OffsetsOnly(Parameterization):
    """p = (o_x, o_y, o_z); K held at K0 (the paper's "offsets only")."""

    model = "offsets"

    def __init__(self, K0: np.ndarray, o0: np.ndarray):
        super().__init__(K0, o0)
        self.names = [f"o_{a}" for a in AXES]
        self.dK = np.zeros((3, 3, 3))
        self.do = np.eye(3)
        self.K_const = self.K0
        self.o_const = np.zeros(3)


class SixParameter(Parameterization):
    """p = (s_x, s_y, s_z, o_x, o_y, o_z), K = diag(s): the paper's eq. 6.

    Off-diagonal entries of K0 (a known cross-axis part, e.g. from a lab calibration) are held.
    """

    model = "6"

    def __init__(self, K0: np.ndarray, o0: np.ndarray):
        super().__init__(K0, o0)
        self.names = [f"s_{a}" for a in AXES] + [f"o_{a}" for a in AXES]
        self.dK = np.zeros((6, 3, 3))
        for i in range(3):
            self.dK[i, i, i] = 1.0
        self.do = np.zeros((6, 3))
        self.do[3:, :] = np.eye(3)
        self.K_const = self.K0 - np.diag(np.diag(self.K0))
        self.o_const = np.zeros(3)


# -- in-use 9 / 12 (the argument is in docs/twelve-parameters.md) -------------------------------
# From the gravity norm alone only K K^T and o are identifiable: |R K^-1 (r - o)| = |K^-1 (r - o)|
# for every rotation R, so K is known only up to K -> K R^T. Writing K = S R0 (left polar
# decomposition, S symmetric positive definite, R0 orthogonal), S (6) and o (3) are the 9
# identifiable parameters and R0 (3) is the frame, which the norm cannot see.
SYMMETRIC_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def polar_frame(K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(S, R) with K = S @ R, S symmetric positive definite, R orthogonal (left polar decomposition)."""
    # scipy.linalg.polar's construction from the SVD K = U diag(s) Vᵀ: R = U Vᵀ, S = U diag(s) Uᵀ
    # (numpy's SVD: the calibration path need not import scipy.linalg for one 3 x 3 matrix)
    U, s, Vt = np.linalg.svd(np.asarray(K, dtype=float).reshape(3, 3))
    S = (U * s) @ U.T
    return 0.5 * (S + S.T), U @ Vt


class _SymmetricInFrame(Parameterization):
    """p = (s_xx, s_yy, s_zz, s_xy, s_xz, s_yz, o_x, o_y, o_z); K = S R0 with S symmetric.

    ``pack`` maps any (K, o) to the S with the same gravity norm, S = (K K^T)^1/2, so a start
    from any convention (diagonal, triangular, full lab K) enters without changing |a|.
    """

    def _frame(self) -> np.ndarray:  # pragma: no cover - subclasses define it
        raise NotImplementedError

    def __init__(self, K0: np.ndarray, o0: np.ndarray):
        super().__init__(K0, o0)
        self.R0 = self._frame()
        self.names = [f"s_{AXES[i]}{AXES[j]}" for i, j in SYMMETRIC_PAIRS] + [f"o_{a}" for a in AXES]
        E = np.zeros((6, 3, 3))
        for m, (i, j) in enumerate(SYMMETRIC_PAIRS):
            E[m, i, j] = E[m, j, i] = 1.0
        self.dK = np.concatenate([E @ self.R0, np.zeros((3, 3, 3))])
        self.do = np.zeros((9, 3))
        self.do[6:, :] = np.eye(3)
        self.K_const = np.zeros((3, 3))
        self.o_const = np.zeros(3)

    def pack(self, K: np.ndarray, o: np.ndarray) -> np.ndarray:
        S, _ = polar_frame(K)
        return np.concatenate([[S[i, j] for i, j in SYMMETRIC_PAIRS], np.asarray(o, dtype=float).reshape(3)])


class NineParameter(_SymmetricInFrame):
    """In-use 9: K = S symmetric (R0 = I, the convention when there is no lab frame) + offsets."""

    model = "9"

    def _frame(self) -> np.ndarray:
        return np.eye(3)


class TwelveInUse(_SymmetricInFrame):
    """In-use 12: K = S R0 with the 9 of S, o updated and the frame R0 held: R0 is the orthogonal
    polar factor of K0 (the lab calibration's K, or the previous 12-in-use K, which carries it)."""

    model = "12"

    def _frame(self) -> np.ndarray:
        return polar_frame(self.K0)[1]


PARAMETERIZATIONS: dict[str, type[Parameterization]] = {
    OffsetsOnly.model: OffsetsOnly,
    SixParameter.model: SixParameter,
    NineParameter.model: NineParameter,
    TwelveInUse.model: TwelveInUse,
}
