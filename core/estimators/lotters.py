"""Lötters et al. (1998) estimator on quasi-static window means, batch and recursive.

Measurement model (eq. 5, 8): every quasi-static window mean m satisfies

    y = 1 [g] = h(m, p) + mu,       h(m, p) = |K(p)^-1 (m - o(p))|

linearised about the previous estimate (eq. 9-10): xi = 1 - h(m, p_hat) = B q + mu with
B = dh/dp (eq. 13a, generalised by the Parameterization) and q = p - p_hat (eq. 12).
The minimum-variance unbiased solution is (eq. 11a, 11b)

    q_hat = (B^T C_mu^-1 B)^-1 B^T C_mu^-1 xi,      C_e = (B^T C_mu^-1 B)^-1.

LottersBatch iterates eq. 11a (Gauss-Newton with step halving) to convergence;
LottersRecursive applies the same linearised model one window at a time (an iterated EKF /
recursive MVU update). Both work with any Parameterization (offsets, 6, and what H-twelve
registers in PARAMETERIZATIONS), in the recording's raw units.

Parameters a parameterization holds (offsets-only: the sensitivities) at uncertain values get a consider
(Schmidt) term in the reported covariance: see "consider covariance" below.

C_mu (the paper: "the variance of the collection of quasi-static moments") is per window:
the delta-method variance of h from the window's covariance of the mean (cov / n), plus a
quasi-static floor sigma_floor_g^2 for residual body motion that the window mean still
contains (see LottersBatch).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from gravcal.core.calibration import Calibration
from gravcal.core.estimators.extended import extended_class, extended_metadata
from gravcal.core.estimators.parameterization import PARAMETERIZATIONS, Parameterization
from gravcal.core.windows import Window, WindowSet

START_TOLERANCE = 0.05  # the paper's convergence assumption: start within 5 % of the truth
_RCOND = 1e-12  # relative eigenvalue below which a direction of the (normalised) Fisher information is void
ANCHOR_STD_G = 0.3  # weak prior on the start [fraction of 1 g] (see LottersBatch._solve)
STEP_TOL_STD = 1e-6  # Gauss-Newton stops when no parameter moves by more than this fraction of its std
MAX_PLAUSIBLE_RMS_G = 0.5  # a converged fit leaving more than this RMS |a| - 1 g is not a calibration
_TINY_VAR_G2 = 1e-14  # guard against zero-variance windows when no floor is given [g²]
OUTLIER_FLOOR_G = 0.002  # the per-window std floor of the outlier gate when no sigma_floor_g is given [g] (order.SIGMA_FLOOR_G)
OUTLIER_MAX_FRACTION = 0.1  # the gate leaves out at most this fraction of the windows (more is a model error, not outliers)


# --------------------------------------------------------------------------------------
# shared helpers
# --------------------------------------------------------------------------------------
def resolve_parameterization(model: str | type[Parameterization] | Parameterization, start: Calibration) -> Parameterization:
    """A Parameterization whose held values (K0, o0) come from ``start`` (unless an instance is given)."""
    if isinstance(model, Parameterization):
        return model
    if isinstance(model, type) and issubclass(model, Parameterization):
        return model(start.sensitivity, start.offset)
    if isinstance(model, str):
        if "+" in model and model not in PARAMETERIZATIONS:  # "<base>+<term>...": registered on first use
            extended_class(model)
        try:
            cls = PARAMETERIZATIONS[model]
        except KeyError:
            raise ValueError(f"unknown model {model!r}; known: {', '.join(sorted(PARAMETERIZATIONS))}") from None
        return cls(start.sensitivity, start.offset)
    raise ValueError(f"model must be a name, a Parameterization class or instance, not {type(model).__name__}")


def validate_windows(ws: WindowSet, n_params: int | None = None) -> None:
    """Raise ValueError naming the problem if ``ws`` cannot be used for a fit."""
    if not isinstance(ws, WindowSet):
        raise ValueError(f"expected a WindowSet, got {type(ws).__name__}")
    m = len(ws)
    if m == 0:
        raise ValueError("no quasi-static windows: nothing to calibrate from (is the recording all motion, or too short?)")
    bad = ~np.all(np.isfinite(ws.mean), axis=1)
    if bad.any():
        idx = np.flatnonzero(bad)
        raise ValueError(f"{idx.size} window mean(s) are NaN/inf (windows {idx[:5].tolist()}{'...' if idx.size > 5 else ''})")
    badc = ~np.all(np.isfinite(ws.cov.reshape(m, 9)), axis=1)
    if badc.any():
        idx = np.flatnonzero(badc)
        raise ValueError(f"{idx.size} window covariance(s) are NaN/inf (windows {idx[:5].tolist()})")
    if np.any(ws.n <= 0):
        raise ValueError("window sample counts must be positive")
    if n_params is not None and m < n_params:
        raise ValueError(
            f"{m} quasi-static window(s) for {n_params} parameters: need at least {n_params} "
            f"(more, spread over orientations, for a useful estimate)"
        )


def window_directions_spread_deg(mean: np.ndarray, cal: Calibration) -> float:
    """Largest angle [deg] between a window's acceleration direction and their mean direction."""
    a = cal.apply_reference(mean)
    u = a / np.linalg.norm(a, axis=1, keepdims=True)
    c = u.sum(axis=0)
    nc = np.linalg.norm(c)
    if nc < 1e-12:
        return 180.0
    cosang = np.clip(u @ (c / nc), -1.0, 1.0)
    return float(np.degrees(np.arccos(cosang.min())))


def _h_variance(a: np.ndarray, Kinv: np.ndarray, cov_mean: np.ndarray) -> np.ndarray:
    """Delta-method variance of h = |a| [g²] from the covariance of the window mean (raw units²).

    dh/dm = (a/|a|)^T K^-1, so var h = g cov g^T with g that row vector.
    """
    u = a / np.linalg.norm(a, axis=1, keepdims=True)
    g = u @ Kinv
    return np.einsum("mi,mij,mj->m", g, cov_mean, g)


def _ellipsoid_start(ws: WindowSet) -> Calibration:
    """Start point without pre-calibration: gravcal.core.estimators.start.ellipsoid_fit when present,
    else a private axis-aligned algebraic ellipsoid fit (fallback until H-detect's start.py exists)."""
    try:
        from gravcal.core.estimators.start import ellipsoid_fit  # noqa: PLC0415 (optional, written in parallel)
    except ImportError:
        ellipsoid_fit = None
    if ellipsoid_fit is not None:
        return ellipsoid_fit(ws)
    return _axis_aligned_ellipsoid_fit(ws.mean)


def _axis_aligned_ellipsoid_fit(m: np.ndarray) -> Calibration:
    """Least squares A x² + B y² + C z² + D x + E y + F z = 1 (normalised columns), then centre and radii."""
    m = np.asarray(m, dtype=float)
    if m.shape[0] < 6:
        raise ValueError(f"cannot derive a start from {m.shape[0]} windows (need >= 6); pass start=")
    c0 = m.mean(axis=0)
    sc = np.maximum(m.std(axis=0), 1e-12 * (np.abs(c0) + 1.0))
    z = (m - c0) / sc  # conditioning: work around the centroid in unit spreads
    D = np.column_stack([z**2, z, np.ones(len(z))])
    # minimise |D theta| subject to |theta| = 1 (homogeneous form, constant term included)
    _, sv, vt = np.linalg.svd(D, full_matrices=False)
    th = vt[-1]
    A, b, k = th[:3], th[3:6], th[6]
    if not (np.all(A > 0) or np.all(A < 0)) or sv[-1] > 0.5 * sv[0]:
        raise ValueError(
            "cannot derive a start: the windows do not outline an ellipsoid (too few orientations); "
            "pass start= (e.g. a datasheet nominal calibration)"
        )
    centre_z = -b / (2 * A)
    rhs = np.sum(A * centre_z**2) - k
    r2 = rhs / A
    if np.any(r2 <= 0):
        raise ValueError("cannot derive a start: degenerate ellipsoid fit; pass start=")
    offset = c0 + centre_z * sc
    sens = np.sqrt(r2) * sc
    return Calibration(model="ellipsoid", offset=offset, sensitivity=np.diag(sens), message="axis-aligned ellipsoid fit (start)")


def _relative_difference(a: Calibration, b: Calibration) -> float:
    """Largest difference of a vs b in fractions of 1 g (eq. 15-16 style, per axis)."""
    s = np.abs(np.diag(b.sensitivity))
    ds = np.max(np.abs(a.sensitivity - b.sensitivity) / s[:, None])
    do = np.max(np.abs(a.offset - b.offset) / s)
    return float(max(ds, do))


def start_far_note(off: float) -> str:
    """Message for an estimate that ended ``off`` (fraction of 1 g) away from the given start."""
    return (f"the given start was too far off ({off * 100:.1f} % of 1 g from the estimate; the paper's "
            f"linearisation assumes < 5 %): converged by iteration")


# --------------------------------------------------------------------------------------
# consider covariance (Schmidt): the uncertainty of the parameters a parameterization holds
# --------------------------------------------------------------------------------------
# A parameterization estimates p and holds the rest of (K, o) at the start's values (offsets-only
# holds the sensitivities). When those held values are themselves uncertain (a datasheet nominal
# start, a previous fit), their error propagates into p: linearised, eq. 10 becomes
#     xi = B_e q + B_h dtheta + mu       (B_h = dh/dtheta, theta the held parameters)
# and the MVU estimate (eq. 11a) picks up  q_hat = ... + G dtheta,  G = (B_e^T W B_e)^-1 B_e^T W B_h,
# W = C_mu^-1. The honest covariance is C_total = C_e + G C_h G^T (consider / uncertain-parameter
# analysis), C_h the held parameters' covariance. The estimate itself is unchanged.
#
# Where C_h comes from (one mechanism: the start Calibration says how uncertain it is):
#   1. the start's own covariance over its param_names (a previous fit: 6-param, lab, bootstrap);
#   2. start.metadata[HELD_KEY] = {"names": [...], "cov": [[...]]} [raw units²] for names not in 1
#      (set by with_held_uncertainty; every fit here carries its held parameters' entry forward);
#   Neither: the held values are taken as exact (no consider term, the previous behaviour). A datasheet
#   nominal start has no data behind it but a known spread: wherever one is made, state it with
#   datasheet_held_uncertainty(start) (the ADXL210 spreads of core/model/defaults.py).
# Parameter names map to directions in (K, o): "s_x" / "s_xx" -> K[0, 0], "s_xy" -> K[0, 1] + K[1, 0],
# "o_x" -> o[0]; directions the parameterization estimates are projected out (its own offsets'
# prior uncertainty is not held: the windows re-estimate them).
HELD_KEY = "held_covariance"
CONSIDER_KEY = "consider"


def _datasheet_rel_spreads() -> tuple[float, float]:
    """(sensitivity std as a fraction of it, zero-g offset std [g]) of an ADXL210 part, from the
    datasheet min/max in core/model/defaults.py (min/max = +-3 sigma, the model's own convention)."""
    from gravcal.core.model.datasheet import D0_LIMITS, SENS_LIMITS, SENS_TYP  # noqa: PLC0415

    return (SENS_LIMITS[1] - SENS_LIMITS[0]) / 6.0 / SENS_TYP, (D0_LIMITS[1] - D0_LIMITS[0]) / 6.0 / SENS_TYP


DATASHEET_SENSITIVITY_REL_STD, DATASHEET_OFFSET_STD_G = _datasheet_rel_spreads()  # 6.7 %, 0.67 g


def with_held_uncertainty(cal: Calibration, std: dict[str, float] | None = None, *,
                          names: list[str] | None = None, cov: np.ndarray | None = None,
                          source: str = "stated held uncertainty") -> Calibration:
    """A copy of ``cal`` stating how uncertain its values are, for the parameters a later fit may hold:
    ``std`` {name: std [raw units]} (independent) or ``names`` with a covariance ``cov`` [raw units²]."""
    if std is not None:
        names, cov = list(std), np.diag(np.asarray([float(v) for v in std.values()]) ** 2)
    if names is None or cov is None:
        raise ValueError("with_held_uncertainty needs std={name: std} or names= and cov=")
    cov = np.asarray(cov, dtype=float)
    if cov.shape != (len(names), len(names)) or not np.all(np.isfinite(cov)) or np.any(np.diag(cov) < 0):
        raise ValueError(f"held covariance must be a finite ({len(names)}, {len(names)}) matrix with a "
                         f"non-negative diagonal, got shape {cov.shape}")
    unknown = [n for n in names if _name_direction(n) is None]
    if unknown:
        raise ValueError(f"unknown held parameter name(s) {unknown}: use s_x, s_y, s_z, s_xy, s_xz, s_yz, o_x, o_y, o_z")
    meta = dict(cal.metadata)
    meta[HELD_KEY] = {"names": list(names), "cov": cov.tolist(), "source": source}
    return Calibration(cal.model, cal.offset, cal.sensitivity, covariance=cal.covariance.copy(),
                       param_names=list(cal.param_names), n_windows=cal.n_windows, converged=cal.converged,
                       observable=cal.observable, message=cal.message, metadata=meta)


def datasheet_held_uncertainty(cal: Calibration, *, sensitivity_rel_std: float | None = None,
                               offset_std_g: float | None = None) -> Calibration:
    """``cal`` (a datasheet nominal calibration) stating the datasheet spread of the part: each
    sensitivity +-``sensitivity_rel_std`` of itself, each offset +-``offset_std_g`` [g] (defaults: the
    ADXL210 spreads of core/model/defaults.py, 6.7 % and 0.67 g)."""
    rs = DATASHEET_SENSITIVITY_REL_STD if sensitivity_rel_std is None else float(sensitivity_rel_std)
    og = DATASHEET_OFFSET_STD_G if offset_std_g is None else float(offset_std_g)
    s = np.abs(np.diag(cal.sensitivity))
    std = {f"s_{a}": rs * s[i] for i, a in enumerate("xyz")}
    std.update({f"o_{a}": og * s[i] for i, a in enumerate("xyz")})
    return with_held_uncertainty(cal, std, source="datasheet spread of a nominal start")


_AXIS = {"x": 0, "y": 1, "z": 2}


def _name_direction(name: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(dK (3, 3), do (3,)) of a parameter name, or None when it is not a plain K or o entry."""
    kind, _, ax = name.partition("_")
    dK, do = np.zeros((3, 3)), np.zeros(3)
    if kind == "o" and len(ax) == 1 and ax in _AXIS:
        do[_AXIS[ax]] = 1.0
    elif kind == "s" and len(ax) == 1 and ax in _AXIS:
        dK[_AXIS[ax], _AXIS[ax]] = 1.0
    elif kind == "s" and len(ax) == 2 and ax[0] in _AXIS and ax[1] in _AXIS:
        i, j = _AXIS[ax[0]], _AXIS[ax[1]]
        dK[i, j] = dK[j, i] = 1.0  # symmetric (in-use 9) entry; s_xx is the diagonal
    else:
        return None
    return dK, do


@dataclass
class HeldUncertainty:
    """Parameters a parameterization holds, with their covariance: names, cov (H, H) [raw units²],
    their directions dK (H, 3, 3) and do (H, 3) with what the parameterization estimates projected
    out, and where the covariance came from."""

    names: list[str]
    cov: np.ndarray
    dK: np.ndarray
    do: np.ndarray
    source: str


def _stated_uncertainty(start: Calibration) -> tuple[list[str], np.ndarray, list[str]]:
    """Names, covariance and the source of each, as the start states them (see the section comment)."""
    names: list[str] = []
    cov = np.zeros((0, 0))
    n = len(start.param_names)
    if n and start.covariance.shape == (n, n) and np.all(np.isfinite(start.covariance)):
        names, cov = list(start.param_names), np.asarray(start.covariance, dtype=float)
    sources = ["the start's covariance"] * len(names)
    held = start.metadata.get(HELD_KEY) if isinstance(start.metadata, dict) else None
    if isinstance(held, dict) and held.get("names"):
        hn = list(held["names"])
        hc = np.asarray(held["cov"], dtype=float).reshape(len(hn), len(hn))
        extra = [k for k, nm in enumerate(hn) if nm not in names]
        if extra and np.all(np.isfinite(hc)):
            C = np.zeros((len(names) + len(extra),) * 2)
            C[:len(names), :len(names)] = cov
            C[len(names):, len(names):] = hc[np.ix_(extra, extra)]
            names, cov = names + [hn[k] for k in extra], C
            sources += [str(held.get("source") or "stated held uncertainty")] * len(extra)
    return names, cov, sources


def held_uncertainty(start: Calibration, par: Parameterization) -> HeldUncertainty | None:
    """The uncertain parameters ``par`` holds at ``start``'s values, or None when there are none
    (nothing stated, or everything stated is estimated by ``par``)."""
    names, cov, sources = _stated_uncertainty(start)
    dirs = [(k, _name_direction(nm)) for k, nm in enumerate(names)]
    dirs = [(k, d) for k, d in dirs if d is not None]
    if not dirs:
        return None
    idx = np.array([k for k, _ in dirs])
    D = np.stack([np.concatenate([d[0].ravel(), d[1]]) for _, d in dirs], axis=1)  # (12, H)
    E = np.concatenate([par.dK.reshape(par.n_params, 9), par.do], axis=1).T  # (12, P): what par estimates
    D_perp = D - E @ np.linalg.lstsq(E, D, rcond=None)[0]
    keep = np.linalg.norm(D_perp, axis=0) > 1e-9 * np.linalg.norm(D, axis=0)
    C = cov[np.ix_(idx, idx)][np.ix_(keep, keep)]
    if not keep.any() or not np.any(np.diag(C) > 0):
        return None
    D_perp = D_perp[:, keep]
    H = D_perp.shape[1]
    kept = idx[keep]
    source = " and ".join(dict.fromkeys(sources[k] for k in kept))
    return HeldUncertainty([names[k] for k in kept], 0.5 * (C + C.T), D_perp[:9].T.reshape(H, 3, 3).copy(),
                           D_perp[9:].T.copy(), source)


def held_jacobian(par: Parameterization, p: np.ndarray, mean: np.ndarray, held: HeldUncertainty) -> np.ndarray:
    """B_h = dh/dtheta (M, H) at p for window means (M, 3): -u^T K^-1 (dK_h a + do_h), as eq. 13a."""
    a, _ = par.accel_and_jacobian(p, mean)  # per-window a (covariates included)
    K, _ = par.unpack(p)
    g = (a / np.linalg.norm(a, axis=1, keepdims=True)) @ np.linalg.inv(K)  # dh/dm (M, 3)
    return -(np.einsum("mi,hij,mj->mh", g, held.dK, a) + g @ held.do.T)


def consider_gain(cov_e: np.ndarray, B_e: np.ndarray, var: np.ndarray, B_h: np.ndarray) -> np.ndarray:
    """G = (B_e^T W B_e)^-1 B_e^T W B_h (P, H), W = diag(1/var), with ``cov_e`` that inverse (eq. 11b):
    q_hat moves by G dtheta when the held values are off by dtheta (so dp_hat/dtheta_0 = -G)."""
    return cov_e @ ((B_e.T / var) @ B_h)


def _consider_metadata(held: HeldUncertainty, sens: np.ndarray, cov_noise: np.ndarray, names: list[str],
                       scale_ref: float) -> dict:
    """metadata[CONSIDER_KEY]: what the reported covariance is made of."""
    cons = sens @ held.cov @ sens.T
    return {
        "held": list(held.names),
        "held_source": held.source,
        "sensitivity": sens.tolist(),  # d p_hat / d theta_held (P, H)
        "covariance_noise_only": cov_noise.tolist(),
        "std_g_noise_only": {n: float(s) for n, s in zip(names, np.sqrt(np.clip(np.diag(cov_noise), 0, None)) / scale_ref)},
        "std_g_held": {n: float(s) for n, s in zip(names, np.sqrt(np.clip(np.diag(cons), 0, None)) / scale_ref)},
    }


def _held_note(par_names: list[str], held: HeldUncertainty, cov_noise: np.ndarray, cons: np.ndarray,
               scale_ref: float) -> str:
    """A note when the held parameters' uncertainty dominates some estimated parameter's std."""
    sn, sc = np.sqrt(np.clip(np.diag(cov_noise), 0, None)), np.sqrt(np.clip(np.diag(cons), 0, None))
    k = int(np.argmax(sc - sn))
    if sc[k] <= sn[k]:
        return ""
    return (f"std includes the uncertainty of the held {', '.join(held.names)} ({held.source}): "
            f"{par_names[k]} std {math.hypot(sn[k], sc[k]) / scale_ref * 1e3:.3g} mg, of which the held "
            f"parameters {sc[k] / scale_ref * 1e3:.3g} mg, the window noise {sn[k] / scale_ref * 1e3:.3g} mg")


# --------------------------------------------------------------------------------------
# batch
# --------------------------------------------------------------------------------------
@dataclass
class _Solve:
    p: np.ndarray
    cov: np.ndarray  # C_e (eq. 11b), eigenvalue-guarded
    chi2: float
    resid_g: np.ndarray  # 1 - h at p [g]
    var_g2: np.ndarray  # C_mu diagonal [g²]
    iterations: int
    converged: bool
    fisher_eig: np.ndarray  # eigenvalues of B^T C_mu^-1 B for parameters in fractions of 1 g
    B: np.ndarray


class LottersBatch:
    """Iterated eq. 11a on a WindowSet.

    Parameters
    ----------
    model: name in PARAMETERIZATIONS ("offsets", "6", ...), a Parameterization class, or an instance.
    sigma_floor_g: quasi-static floor [g] added (in quadrature) to each window's delta-method std of h.
        None (default): derived from the data. A window mean of a body-worn sensor still contains residual
        motion that cov/n does not describe (slow sway, posture drift inside the window, unmodelled
        cross-axis terms), so cov/n alone makes C_mu far too small and C_e over-confident. When the reduced
        chi² of the residuals exceeds 1 we solve for the floor that brings it to 1 and refit with it
        (re-weighting, not just scaling C_e). With an explicit floor, a reduced chi² > 1 inflates C_e by
        that factor (Birge ratio) and is reported in metadata and the message.
    max_iter, tol: Gauss-Newton limits; tol is the largest step in fractions of 1 g (eq. 15-16 units).
    max_std_g: a parameter whose std exceeds this fraction of 1 g is "not determined" -> observable=False.
        Default 0.03: the paper's 3 % criterion.
    retry_from_ellipsoid: when a given start ends > 5 % away or does not converge, also try the
        ellipsoid-fit start and keep the better converged fit (False: the paper's setting, start trusted).
    tol_g: the observability rule's tolerance [g] (``order.is_observable``: predicted RMS acceleration error
        of the order over all orientations, including the geometry's amplification of per-window model
        error). Default ``order.TOL_G`` (10 mg, what ``--model auto`` uses), or inf (no rule) when
        max_std_g is inf (reproducing the paper's tables, which report every estimate).
    outlier_gate_sigma: None (default: every window counts, the paper's estimator) or k: after the fit,
        windows whose norm residual exceeds k robust sigmas are left out and the rest refitted (at most
        OUTLIER_MAX_FRACTION of them; metadata ``outlier_windows``, ``outlier_t``). The robust
        sigma is 1.4826 x the median |residual| in units of each window's own std (noise of its mean plus
        ``sigma_floor_g``, else OUTLIER_FLOOR_G), never below 1, of a robust (Cauchy-loss) fit. It is the batch counterpart of
        LottersRecursive's gate: a detector on |a| passes a window that straddles a bump or a smooth
        acceleration plateau (its mean is off the sphere by tens of mg), and with a data-derived floor
        such a window keeps the weight of a good one, so a single one moves a 20-window fit by ~10 mg.
    """

    def __init__(
        self,
        model: str | type[Parameterization] | Parameterization = "6",
        *,
        sigma_floor_g: float | None = None,
        max_iter: int = 50,
        tol: float = 1e-10,
        max_std_g: float = 0.03,
        retry_from_ellipsoid: bool = True,
        tol_g: float | None = None,
        outlier_gate_sigma: float | None = None,
    ):
        if outlier_gate_sigma is not None and not (outlier_gate_sigma > 0 and math.isfinite(outlier_gate_sigma)):
            raise ValueError(f"outlier_gate_sigma must be a finite number > 0 or None, got {outlier_gate_sigma!r}")
        self.outlier_gate_sigma = outlier_gate_sigma
        if sigma_floor_g is not None and not (sigma_floor_g >= 0 and math.isfinite(sigma_floor_g)):
            raise ValueError(f"sigma_floor_g must be a finite number >= 0, got {sigma_floor_g!r}")
        self.model = model
        self.sigma_floor_g = sigma_floor_g
        self.max_iter = int(max_iter)
        self.tol = float(tol)
        self.max_std_g = float(max_std_g)
        self.retry_from_ellipsoid = bool(retry_from_ellipsoid)
        if tol_g is None:
            from gravcal.core.estimators.order import TOL_G  # noqa: PLC0415 (order imports this module)

            tol_g = TOL_G if math.isfinite(self.max_std_g) else math.inf
        self.tol_g = float(tol_g)

    # -- core iteration --------------------------------------------------------------
    def _solve(self, par: Parameterization, p0: np.ndarray, anchor: np.ndarray, mean: np.ndarray,
               cov_mean: np.ndarray, floor2: float) -> _Solve:
        """Iterate eq. 11a from p0. ``anchor`` (the start) enters as a weak prior of ANCHOR_STD_G
        (0.3 g as a std, in fractions of 1 g): negligible for any determined parameter (a std of 1e-3 g
        is changed by ~1e-5 relative, the 3 % observability limit by 1 %), but it keeps combinations the windows cannot determine at the start instead
        of letting them wander to wherever the noise leads."""
        scale = float(np.mean(np.abs(np.diag(par.unpack(anchor)[0])))) or 1.0
        w_prior = 1.0 / (ANCHOR_STD_G * scale) ** 2

        def evaluate(p):
            K, _ = par.unpack(p)
            Kinv = np.linalg.inv(K)
            h, B, a = par.norm_and_jacobian(p, mean)
            var = np.maximum(_h_variance(a, Kinv, cov_mean) + floor2, _TINY_VAR_G2)  # C_mu diagonal
            xi = 1.0 - h  # eq. 14
            cost = float(np.sum(xi**2 / var) + w_prior * np.sum((p - anchor) ** 2))
            return xi, B, var, cost

        p = np.array(p0, dtype=float)
        xi, B, var, cost = evaluate(p)
        converged = False
        it = 0
        for it in range(1, self.max_iter + 1):
            step, std = _mvu_solve(B, var, xi, w_prior, p - anchor)  # eq. 11a (+ weak prior)
            if not np.all(np.isfinite(step)):
                break
            # converged when the step is negligible in absolute terms or against the parameter's own std
            # (along a direction the windows barely determine, Gauss-Newton crawls; that crawl is noise)
            if np.max(np.abs(step)) / scale < self.tol or np.max(np.abs(step) / std) < STEP_TOL_STD:
                p = p + step  # at the optimum: the cost no longer resolves such steps
                xi, B, var, cost = evaluate(p)
                converged = True
                break
            # step halving: the linearisation (eq. 9) only holds near p; never accept a worse fit
            lam = 1.0
            for _ in range(30):
                try:
                    trial = evaluate(p + lam * step)
                except np.linalg.LinAlgError:
                    lam *= 0.5
                    continue
                # compare at the current weights C_mu(p): eq. 11a is a descent direction for that cost
                # (an IRLS step); its fixed point is the MVU estimate, the paper's solution
                cost_fixed = float(np.sum(trial[0] ** 2 / var) + w_prior * np.sum((p + lam * step - anchor) ** 2))
                if np.isfinite(cost_fixed) and cost_fixed <= cost * (1 + 1e-12):
                    break
                lam *= 0.5
            else:
                break
            p = p + lam * step
            xi, B, var, cost = trial
            cost = float(np.sum(xi**2 / var) + w_prior * np.sum((p - anchor) ** 2))
            if np.max(np.abs(lam * step)) / scale < self.tol:
                converged = True
                break
        cov, eig = _mvu_covariance(B, var, scale)  # eq. 11b (data only: no prior in the reported C_e)
        return _Solve(p, cov, float(np.sum(xi**2 / var)), xi, var, it, converged, eig, B)

    # -- public ------------------------------------------------------------------------
    def fit(self, ws: WindowSet, start: Calibration | None = None) -> Calibration:
        """Calibration (raw = K a + o) from quasi-static windows; raises ValueError on unusable input."""
        return self._fit(ws, start, gate=self.outlier_gate_sigma is not None)

    def _outliers(self, par: Parameterization, sol: _Solve, mean: np.ndarray, floor2: float) -> np.ndarray:
        """Windows more than outlier_gate_sigma robust sigmas off a robust fit (bool (m,)), the largest first,
        at most OUTLIER_MAX_FRACTION of them. The robust fit (Cauchy loss on the residuals in units of each
        window's std, scipy.optimize.least_squares from the least-squares solution) keeps two outliers from
        masking each other: least squares spreads them over the other windows, so its residuals would not
        single them out."""
        from scipy.optimize import least_squares  # noqa: PLC0415

        floor_g2 = floor2 if self.sigma_floor_g is not None else OUTLIER_FLOOR_G**2
        sd = np.sqrt(np.maximum(sol.var_g2 - floor2 + floor_g2, _TINY_VAR_G2))

        def resid(p: np.ndarray) -> np.ndarray:
            return (1.0 - par.norm_and_jacobian(p, mean)[0]) / sd

        def jac(p: np.ndarray) -> np.ndarray:
            return -par.norm_and_jacobian(p, mean)[1] / sd[:, None]

        try:
            rob = least_squares(resid, sol.p, jac=jac, loss="cauchy", f_scale=1.0, x_scale="jac", max_nfev=200)
            r = np.abs(resid(rob.x))
        except (ValueError, np.linalg.LinAlgError):
            r = np.abs(sol.resid_g) / sd
        sigma = max(1.4826 * float(np.median(r)), 1.0)
        over = np.flatnonzero(r > self.outlier_gate_sigma * sigma)
        over = over[np.argsort(-r[over])][: int(OUTLIER_MAX_FRACTION * len(r))]
        mask = np.zeros(len(r), dtype=bool)
        mask[over] = True
        return mask

    def _fit(self, ws: WindowSet, start: Calibration | None, *, gate: bool = False) -> Calibration:
        if not isinstance(ws, WindowSet):
            raise ValueError(f"expected a WindowSet, got {type(ws).__name__}")
        validate_windows(ws)
        notes: list[str] = []
        start_source = "given"
        if start is None:
            start = _ellipsoid_start(ws)
            start_source = "ellipsoid_fit"
        if not (np.all(np.isfinite(start.offset)) and np.all(np.isfinite(start.sensitivity))):
            raise ValueError("start calibration has non-finite offset or sensitivity")
        if abs(np.linalg.det(start.sensitivity)) < 1e-300:
            raise ValueError("start calibration has a singular sensitivity matrix")
        par = resolve_parameterization(self.model, start).at_windows(ws)  # per-window covariates, if any
        validate_windows(ws, par.n_params)

        mean = ws.mean
        cov_mean = ws.cov_of_mean
        p0 = par.pack(start.sensitivity, start.offset)
        floor2 = 0.0 if self.sigma_floor_g is None else float(self.sigma_floor_g) ** 2
        anchor = p0
        sol = self._solve(par, p0, p0, mean, cov_mean, floor2)

        # A start far from the truth may converge elsewhere (the paper assumes < 5 %): when the estimate
        # ends > 5 % from the given start or did not converge, also fit from the ellipsoid start and keep
        # the converged fit with the lower chi²; flag non-convergence if neither converged.
        K1, o1 = par.unpack(sol.p)
        far = _relative_difference(Calibration(par.model, o1, K1), start) > START_TOLERANCE
        if start_source == "given" and self.retry_from_ellipsoid and (not sol.converged or far):
            try:
                alt_start = _ellipsoid_start(ws)
                pa = par.pack(alt_start.sensitivity, alt_start.offset)
                alt = self._solve(par, pa, pa, mean, cov_mean, floor2)
                if alt.converged and (alt.chi2 < sol.chi2 * (1 - 1e-9) or not sol.converged):
                    sol, anchor = alt, pa
                    start_source = "ellipsoid_fit (retry: the given start led to a worse or no solution)"
                    notes.append("the given start was too far off (did not converge or a worse fit); "
                                 "used the ellipsoid-fit start")
            except ValueError as exc:
                notes.append(f"ellipsoid-fit retry impossible: {exc}")

        m, P = len(ws), par.n_params
        if gate and sol.converged:
            out = self._outliers(par, sol, mean, floor2)
            if out.any() and m - int(out.sum()) >= P + 3:
                cal = self._fit(ws.subset(np.flatnonzero(~out)), start)
                cal.metadata["outlier_windows"] = int(out.sum())
                cal.metadata["outlier_t"] = [float(t) for t in ws.t[out]]
                note = (f"left out {int(out.sum())} of {m} windows whose |a| is more than {self.outlier_gate_sigma:g} "
                        f"robust sigmas off the fit (not quasi-static: a bump or an acceleration plateau)")
                cal.message = "; ".join(x for x in (cal.message, note) if x)
                return cal
        dof = m - P
        chi2_red_stat = sol.chi2 / dof if dof > 0 else float("nan")
        floor_used = math.sqrt(floor2)
        inflation = 1.0
        if self.sigma_floor_g is None and dof > 0 and chi2_red_stat > 1.0:
            # data-derived floor: solve sum xi²/(v + f²) = dof for f², then re-weight and refit
            v0 = sol.var_g2 - floor2
            r2 = sol.resid_g**2

            def excess(f2: float) -> float:
                return float(np.sum(r2 / np.maximum(v0 + f2, _TINY_VAR_G2)) - dof)

            hi = max(float(np.max(r2)), 1e-12) * 10
            floor2 = brentq(excess, 0.0, hi, xtol=1e-18, rtol=1e-10) if excess(hi) < 0 else hi
            floor_used = math.sqrt(floor2)
            sol2 = self._solve(par, sol.p, anchor, mean, cov_mean, floor2)
            sol = _Solve(sol2.p, sol2.cov, sol2.chi2, sol2.resid_g, sol2.var_g2, sol.iterations + sol2.iterations,
                         sol.converged and sol2.converged, sol2.fisher_eig, sol2.B)
            notes.append(f"reduced chi² {chi2_red_stat:.3g} from window noise alone: added a quasi-static floor "
                         f"of {floor_used * 1e3:.3g} mg to C_mu")
        rms_g = float(np.sqrt(np.mean(sol.resid_g**2)))
        if rms_g > MAX_PLAUSIBLE_RMS_G:
            sol.converged = False
            notes.append(f"the fit leaves an RMS |a| - 1 g of {rms_g * 1e3:.0f} mg: the windows do not lie on the "
                         f"fitted ellipsoid (wrong start, wrong units, or not quasi-static)")
        chi2_red = sol.chi2 / dof if dof > 0 else float("nan")
        if self.sigma_floor_g is not None and dof > 0 and chi2_red > 1.0:
            inflation = chi2_red  # Birge ratio: the given C_mu is too small by this factor
            notes.append(f"reduced chi² {chi2_red:.3g} > 1 with sigma_floor_g={self.sigma_floor_g}: C_e inflated by it")
        cov_noise = sol.cov * inflation

        K, o = par.unpack(sol.p)
        scale = np.abs(np.diag(K))
        scale_ref = float(np.mean(scale))
        # consider term: the held parameters' uncertainty (see "consider covariance" above)
        held = held_uncertainty(start, par)
        cov, consider_meta, held_meta = cov_noise, None, {}
        if held is not None:
            G = consider_gain(sol.cov, sol.B, sol.var_g2, held_jacobian(par, sol.p, mean, held))
            cons = G @ held.cov @ G.T
            cov = cov_noise + cons
            consider_meta = _consider_metadata(held, -G, cov_noise, list(par.names), scale_ref)
            held_meta = {HELD_KEY: {"names": list(held.names), "cov": held.cov.tolist(), "source": held.source}}
            note = _held_note(list(par.names), held, cov_noise, cons, scale_ref)
            if note:
                notes.append(note)
        std = np.sqrt(np.clip(np.diag(cov), 0, None))
        std_g = std / scale_ref  # fractions of 1 g (eq. 15-16)
        # window spread judged with the estimate when it converged (a far-off start distorts angles)
        view = Calibration(par.model, o, K) if sol.converged else start
        here = Calibration(par.model, o, K, metadata=dict(held_meta))  # the estimate, with its held uncertainty
        # the offsets-only alternative ("use --model offsets") holds the start's K with the start's uncertainty
        offsets_alt = Calibration(start.model, o, start.sensitivity, covariance=start.covariance,
                                  param_names=list(start.param_names), metadata=dict(start.metadata))
        observable, obs_msg = self._observability(par, sol, cov, std_g, ws, here, view, offsets_alt)
        converged = bool(sol.converged and np.all(np.isfinite(sol.p)))
        if not converged:
            notes.insert(0, f"did not converge in {sol.iterations} iterations (start {start_source}); "
                            f"the estimate is not trustworthy")
        if obs_msg:
            notes.insert(0, obs_msg)
        off = _relative_difference(Calibration(par.model, o, K), start)
        if off > START_TOLERANCE and start_source == "given":
            notes.append(start_far_note(off))
        metadata = {
            "estimator": "lotters_batch",
            "iterations": int(sol.iterations),
            "chi2": float(sol.chi2),
            "dof": int(dof),
            "reduced_chi2": float(chi2_red),
            "reduced_chi2_window_noise_only": float(chi2_red_stat),
            "sigma_floor_g": float(floor_used),
            "cov_inflation": float(inflation),
            "start": start_source,
            "start_offset_from_estimate": off,
            "std_g": {n: float(s) for n, s in zip(par.names, std_g)},
            "direction_std_g": (1.0 / np.sqrt(np.maximum(sol.fisher_eig, 1e-300))).tolist(),
            "spread_deg": window_directions_spread_deg(mean, view),
            "insample_rms_mg": float(np.sqrt(np.mean(sol.resid_g**2)) * 1e3),
            **held_meta,
            # params (+ extended terms): K, o above hold at T_ref / t0 only; apply_extended needs these
            **extended_metadata(par, sol.p, std),
        }
        if consider_meta is not None:
            metadata[CONSIDER_KEY] = consider_meta
        return Calibration(
            model=par.model, offset=o, sensitivity=K, covariance=cov, param_names=list(par.names),
            n_windows=m, converged=converged, observable=observable, message="; ".join(notes), metadata=metadata,
        )

    def _observability(self, par, sol: _Solve, cov, std_g, ws: WindowSet, cal, start,
                       offsets_alt: Calibration | None = None) -> tuple[bool, str]:
        """Is every requested parameter determined? gravcal's one rule (``order.is_observable``: predicted
        RMS acceleration error of this order <= ``tol_g``, the rule ``select_order`` uses, so an order auto
        would not choose is never flagged observable here), plus a numerically singular Fisher information
        B^T C_mu^-1 B and, as before, every parameter's std <= ``max_std_g`` (fractions of 1 g)."""
        from gravcal.core.estimators.order import N_PARAMS, held_note, is_observable  # noqa: PLC0415 (order imports this module)

        mean = ws.mean
        eig = sol.fisher_eig  # information in (fraction of 1 g)^-2
        singular = eig.size == 0 or eig.min() <= max(_RCOND * eig.max(), 1.0 / self.max_std_g**2)
        bad = [n for n, s in zip(par.names, std_g) if not (s <= self.max_std_g)]
        # the order rule: on this parameterization, or on the base order of an extended one (extra terms: std rule)
        base = par.model if par.model in N_PARAMS else getattr(par, "base_model", None)
        rule_ok, obs = True, None
        if base in N_PARAMS and math.isfinite(self.tol_g):
            try:
                rule_ok, obs = is_observable(ws, cal, par if base == par.model else base, tol_g=self.tol_g)
            except (ValueError, np.linalg.LinAlgError):
                rule_ok = False
        if not singular and not bad and rule_ok:
            return True, ""
        offsets_ok = False  # worth saying "use --model offsets"? (only computed for a negative verdict)
        if par.model != "offsets" and math.isfinite(self.tol_g):
            try:
                offsets_ok = is_observable(ws, offsets_alt if offsets_alt is not None else cal, "offsets",
                                           tol_g=self.tol_g)[0]
            except (ValueError, np.linalg.LinAlgError):
                pass
        if (singular or not rule_ok) and not bad:
            if base == "offsets":
                bad = [n for n in par.names if n.startswith("o_")]
            elif offsets_ok:
                bad = [n for n in par.names if n.startswith("s_")]
            else:
                bad = list(par.names)
        spread = window_directions_spread_deg(mean, start)
        kinds = {n.split("_")[0] for n in bad}
        what = {"s": "sensitivities", "o": "offsets"}.get(next(iter(kinds)), "") if len(kinds) == 1 else ""
        if what == "sensitivities" and base in ("9", "12"):
            what = "sensitivities and cross-axis terms"
        what = what or ", ".join(bad)
        worst = max((s for s in std_g if np.isfinite(s)), default=float("inf"))
        msg = (f"{what} not observable: all {len(mean)} windows within {spread:.0f}° of one direction "
               f"(std up to {worst * 100:.3g} % of 1 g")
        if obs is not None and not rule_ok:
            pred = "unbounded" if obs["predicted_mg"] is None else f"{obs['predicted_mg']:.3g} mg"
            msg += f"; predicted error {pred} > {self.tol_g * 1e3:.3g} mg)"
            note = held_note(obs)
            if note:
                msg += f"; {note}"
        else:
            msg += f" > {self.max_std_g * 100:.3g} %)"
        if offsets_ok:
            msg += "; use --model offsets"
        return False, msg


def _mvu_solve(B: np.ndarray, var: np.ndarray, xi: np.ndarray, w_prior: float, dev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """q_hat of eq. 11a with C_mu = diag(var), plus the weak prior w_prior |p - anchor|² (dev = p - anchor);
    also the std of each parameter under that regularised information."""
    W = 1.0 / var
    F = (B.T * W) @ B
    F[np.diag_indices_from(F)] += w_prior
    b = (B.T * W) @ xi - w_prior * dev
    Finv = np.linalg.inv(F)
    return Finv @ b, np.sqrt(np.diag(Finv))


def _mvu_covariance(B: np.ndarray, var: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """C_e of eq. 11b and the eigenvalues of the information B^T C_mu^-1 B for parameters in units
    of ``scale`` (the mean sensitivity), i.e. in fractions of 1 g as eq. 15-16: 1/sqrt(eigenvalue) is
    the std [fraction of 1 g] of that parameter combination. A (numerically) singular direction gets
    a huge, finite variance, so an unobservable parameter never looks confident."""
    W = 1.0 / var
    F = (B.T * W) @ B * (scale * scale)
    lam, V = np.linalg.eigh(F)
    lam_c = np.maximum(lam, _RCOND * max(float(lam[-1]), 1e-300))
    cov = (V / lam_c) @ V.T * (scale * scale)
    return cov, lam


# --------------------------------------------------------------------------------------
# recursive
# --------------------------------------------------------------------------------------
class LottersRecursive:
    """One linearised MVU (iterated-EKF) update per quasi-static window.

    State (filterpy style): ``p`` (P,) parameters in raw units, ``P`` (P, P) their covariance (C_e),
    ``Q`` (P, P) process noise per second of elapsed time [param units² / s] (random walk of the
    parameters, so drifting offsets are tracked), ``R_floor`` = sigma_floor_g² [g²].

    Per window (mean m, covariance of the mean C_m, mid time t):
        P  <- P + Q (t - t_prev)                                   (prediction: random-walk drift)
        h, B = |K^-1 (m - o)|, dh/dp at p                          (eq. 8, 13a)
        R   = (a/|a|)^T K^-1 C_m K^-T (a/|a|) + sigma_floor²       (C_mu of this window)
        S   = B P B^T + R;  xi = 1 - h                             (innovation, eq. 14)
        gate: xi² / S > gate_sigma²  -> reject, count
        K_g = P B^T / S;  p <- p + K_g xi;  P <- (I - K_g B) P (I - K_g B)^T + K_g R K_g^T   (Joseph form)
    With ``iterations`` > 1 the update is relinearised at the new estimate (IEKF):
        p_i+1 = p_prior + K_g,i (xi_i - B_i (p_prior - p_i)).
    Eq. 11a over all windows at once is the batch limit of this recursion (no prior, no Q).

    Held parameters (consider covariance, Schmidt): when ``start`` states an uncertainty C_h for
    parameters this parameterization holds (``held_uncertainty``: offsets-only from a datasheet start
    holds uncertain sensitivities), the sensitivity ``S`` = dp/dtheta_held (P, H) is propagated with
    the filter, S <- (I - K_g B) S - K_g B_h (B_h = dh/dtheta_held), from the start's (a batch fit's
    metadata["consider"]["sensitivity"], else 0). The reported covariance is P + S C_h S^T; the state
    update (gain, P) is the plain filter's, unchanged.
    """

    def __init__(
        self,
        start: Calibration,
        model: str | type[Parameterization] | Parameterization = "6",
        *,
        process_noise: float | np.ndarray | None = None,
        sigma_floor_g: float = 0.002,
        gate_sigma: float = 5.0,
        prior_std_rel: float = START_TOLERANCE,
        iterations: int = 1,
        max_consecutive_rejections: int = 20,
        max_std_g: float = 0.03,
    ):
        if not isinstance(start, Calibration):
            raise ValueError("LottersRecursive needs a start Calibration (e.g. LottersBatch().fit(first_windows))")
        self.par = resolve_parameterization(model, start)
        par = self.par
        n = par.n_params
        self.names = list(par.names)
        self.p = par.pack(start.sensitivity, start.offset)
        stated = start.metadata.get("params") if isinstance(start.metadata, dict) else None
        if start.model == par.model and "+" in par.model and isinstance(stated, dict) and all(n in stated for n in self.names):
            # an extended start (a batch fit): its extra terms are not in (K, o); resume from its parameters
            self.p = np.array([float(stated[n]) for n in self.names])
        self.scale_ref = float(np.mean(np.abs(np.diag(start.sensitivity))))
        # held parameters' uncertainty (consider term of the reported covariance only)
        self.held = held_uncertainty(start, par)
        cons = start.metadata.get(CONSIDER_KEY) if isinstance(start.metadata, dict) else None
        same = (self.held is not None and isinstance(cons, dict) and cons.get("held") == self.held.names
                and list(start.param_names) == self.names)
        h = 0 if self.held is None else len(self.held.names)
        self.S = np.asarray(cons["sensitivity"], dtype=float).reshape(n, h) if same else np.zeros((n, h))
        start_cov = np.asarray(cons["covariance_noise_only"], dtype=float) if same else start.covariance
        if start_cov.shape == (n, n) and list(start.param_names) == self.names and np.all(np.isfinite(start_cov)) \
                and np.all(np.diag(start_cov) > 0):
            self.P = start_cov.copy()  # the filter's own covariance (noise only: the consider part is reported)
        else:
            # the paper's assumption: start within 5 % (of 1 g) of the truth
            self.P = np.eye(n) * (prior_std_rel * self.scale_ref) ** 2
        if process_noise is None:
            self.Q = np.zeros((n, n))
        else:
            q = np.asarray(process_noise, dtype=float)
            self.Q = np.diag(np.broadcast_to(q, (n,))).astype(float) if q.ndim <= 1 else q.reshape(n, n).copy()
            if not np.all(np.isfinite(self.Q)) or np.any(np.diag(self.Q) < 0):
                raise ValueError("process_noise must be finite and non-negative")
        self.R_floor = float(sigma_floor_g) ** 2
        self.gate2 = float(gate_sigma) ** 2
        self.iterations = max(1, int(iterations))
        self.max_consecutive_rejections = int(max_consecutive_rejections)
        self.max_std_g = float(max_std_g)
        # constant derivatives, flattened for small explicit products
        self._dK9 = np.ascontiguousarray(par.dK.reshape(n, 9))  # (P, 9): K = K_const + p @ dK9
        # dh/dp_k = -sum_ij g_i dK_k[i, j] a_j: contract dK_k with the outer product g a^T (row-major i, j)
        self._dKg = self._dK9
        self._do = np.ascontiguousarray(par.do)  # (P, 3)
        if self.held is not None:
            self._dKh9 = np.ascontiguousarray(self.held.dK.reshape(h, 9))
            self._doh = np.ascontiguousarray(self.held.do)
        self._ag = self._g = None  # the last linearisation's a g^T (9,) and g (3,) (for B_h)
        self._dK9_ref, self._do_ref = self._dK9, self._do  # at the reference covariates (what .calibration reports)
        self._has_Q = bool(np.any(self.Q != 0))
        self._n = n
        self.t_last: float | None = None
        self.n_updates = 0
        self.n_rejected = 0
        self.consecutive_rejected = 0
        self.nis_sum = 0.0  # sum of normalised innovations squared of accepted windows (should average ~1)
        self._eye = np.eye(n)

    # -- the update ----------------------------------------------------------------------
    def _h_B_R(self, p: np.ndarray, m: tuple, Cm: list) -> tuple[float, np.ndarray, float]:
        """h (eq. 8), dh/dp (eq. 13a generalised) and the window's C_mu at p; 3-vectors in plain floats
        (numpy call overhead dominates 3x3 work)."""
        par = self.par
        K = (par.K_const.ravel() + p @ self._dK9).tolist()
        o = (par.o_const + p @ self._do).tolist()
        k00, k01, k02, k10, k11, k12, k20, k21, k22 = K
        c00 = k11 * k22 - k12 * k21
        c01 = k02 * k21 - k01 * k22
        c02 = k01 * k12 - k02 * k11
        det = k00 * c00 + k10 * c01 + k20 * c02
        if det == 0.0:
            raise ValueError("sensitivity matrix became singular")
        inv = 1.0 / det
        i00, i01, i02 = c00 * inv, c01 * inv, c02 * inv
        i10, i11, i12 = (k12 * k20 - k10 * k22) * inv, (k00 * k22 - k02 * k20) * inv, (k02 * k10 - k00 * k12) * inv
        i20, i21, i22 = (k10 * k21 - k11 * k20) * inv, (k01 * k20 - k00 * k21) * inv, (k00 * k11 - k01 * k10) * inv
        d0, d1, d2 = m[0] - o[0], m[1] - o[1], m[2] - o[2]
        a0 = i00 * d0 + i01 * d1 + i02 * d2  # a = K^-1 (m - o)
        a1 = i10 * d0 + i11 * d1 + i12 * d2
        a2 = i20 * d0 + i21 * d1 + i22 * d2
        h = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        u0, u1, u2 = a0 / h, a1 / h, a2 / h
        g0 = u0 * i00 + u1 * i10 + u2 * i20  # g = dh/dm = u^T K^-1
        g1 = u0 * i01 + u1 * i11 + u2 * i21
        g2 = u0 * i02 + u1 * i12 + u2 * i22
        # dh/dp_k = -g (dK_k a + do_k)
        self._ag = np.array((a0 * g0, a1 * g0, a2 * g0, a0 * g1, a1 * g1, a2 * g1, a0 * g2, a1 * g2, a2 * g2))
        self._g = np.array((g0, g1, g2))
        B = -(self._dKg @ self._ag + self._do @ self._g)
        R = (g0 * (Cm[0] * g0 + Cm[1] * g1 + Cm[2] * g2) + g1 * (Cm[3] * g0 + Cm[4] * g1 + Cm[5] * g2)
             + g2 * (Cm[6] * g0 + Cm[7] * g1 + Cm[8] * g2)) + self.R_floor
        return h, B, R

    def step(self, mean: np.ndarray, cov_of_mean: np.ndarray, t: float | None = None, aux: np.ndarray | None = None) -> bool:
        """Process one window (mean and covariance of the mean in raw units, mid time t [s], aux means
        e.g. temperature [°C]). Returns True if accepted, False if gated out as an outlier."""
        m = tuple(float(x) for x in np.ravel(mean))
        if len(m) != 3 or not all(math.isfinite(x) for x in m):
            raise ValueError(f"window mean must be 3 finite values, got {mean!r}")
        if self.par.covariates:  # derivatives depend on this window's covariates (extended.py)
            one = WindowSet(np.reshape(np.asarray(mean, dtype=float), (1, 3)), np.zeros((1, 3, 3)), np.ones(1),
                            np.array([0.0 if t is None else float(t)]),
                            np.reshape(np.zeros(0) if aux is None else np.asarray(aux, dtype=float), (1, -1)),
                            np.zeros(1, dtype=np.int64), np.ones(1, dtype=np.int64))
            pw = self.par.at_windows(one)
            self._dK9 = self._dKg = np.ascontiguousarray(pw.dK.reshape(self._n, 9))
            self._do = np.ascontiguousarray(pw.do)
        Cm = np.ravel(cov_of_mean).tolist()
        if t is not None:
            if self.t_last is not None and t > self.t_last and self._has_Q:
                self.P = self.P + self.Q * (t - self.t_last)  # random-walk prediction
            self.t_last = float(t) if self.t_last is None else max(self.t_last, float(t))
        p_prior, P = self.p, self.P
        p = p_prior
        for i in range(self.iterations):
            h, B, R = self._h_B_R(p, m, Cm)
            PB = P @ B
            S = float(B @ PB) + R
            if i == 0:
                xi0 = 1.0 - h  # eq. 14
                if xi0 * xi0 > self.gate2 * S:
                    self.n_rejected += 1
                    self.consecutive_rejected += 1
                    return False
                xi = xi0
            else:
                xi = 1.0 - h - float(B @ (p_prior - p))  # IEKF: relinearised at p, referred to the prior
            p = p_prior + PB * (xi / S)  # K_g = P B^T / S
        if self.held is not None:  # consider sensitivity: S <- (I - K_g B) S - K_g B_h (K_g = PB / S)
            B_h = -(self._dKh9 @ self._ag + self._doh @ self._g)
            self.S = self.S - np.outer(PB * (1.0 / S), B @ self.S + B_h)
        # P - K_g S K_g^T = P - PB PB^T / S: equal to the Joseph form for the optimal gain, and exactly symmetric
        self.P = P - np.outer(PB, PB * (1.0 / S))
        self.p = p
        self.nis_sum += xi0 * xi0 / S
        self.n_updates += 1
        self.consecutive_rejected = 0
        return True

    def update(self, window: Window | WindowSet) -> Calibration:
        """Update with one Window (or every row of a WindowSet, in order) and return the calibration."""
        if isinstance(window, Window):
            self.step(window.mean, window.cov / max(window.n, 1), window.t_mid, window.aux_mean)
        elif isinstance(window, WindowSet):
            if len(window):
                validate_windows(window)
            cm = window.cov_of_mean
            for i in range(len(window)):
                self.step(window.mean[i], cm[i], float(window.t[i]), window.aux[i])
        else:
            raise ValueError(f"expected a Window or WindowSet, got {type(window).__name__}")
        return self.calibration

    @property
    def calibration(self) -> Calibration:
        """The current estimate as a Calibration (covariance = P); cheap enough to build per window."""
        par = self.par
        K = (par.K_const.ravel() + self.p @ self._dK9_ref).reshape(3, 3)
        o = par.o_const + self.p @ self._do_ref
        scale_ref = (abs(K[0, 0]) + abs(K[1, 1]) + abs(K[2, 2])) / 3.0
        cov, extra = self.P, {}
        notes = []
        if self.held is not None:
            cons = self.S @ self.held.cov @ self.S.T
            cov = self.P + cons
            extra = {HELD_KEY: {"names": list(self.held.names), "cov": self.held.cov.tolist(), "source": self.held.source},
                     CONSIDER_KEY: _consider_metadata(self.held, self.S, self.P, self.names, scale_ref)}
            note = _held_note(self.names, self.held, self.P, cons, scale_ref)
            if note:
                notes.append(note)
        std_g = np.sqrt(np.maximum(np.diagonal(cov), 0.0)) / scale_ref
        observable = bool((std_g <= self.max_std_g).all())
        if not observable:
            bad = [n for n, s in zip(self.names, std_g) if s > self.max_std_g]
            notes.append(f"not yet determined: {', '.join(bad)} (std > {self.max_std_g * 100:.3g} % of 1 g)")
        converged = self.consecutive_rejected < self.max_consecutive_rejections
        if not converged:
            notes.append(f"last {self.consecutive_rejected} windows rejected by the {math.sqrt(self.gate2):.3g}σ gate: "
                         f"the estimate has probably diverged or the sensor changed; re-run a batch fit")
        return Calibration(
            model=self.par.model, offset=o, sensitivity=K, covariance=cov.copy(), param_names=list(self.names),
            n_windows=self.n_updates, converged=converged, observable=observable, message="; ".join(notes),
            metadata={"estimator": "lotters_recursive", "n_rejected": self.n_rejected,
                      "mean_nis": self.nis_sum / self.n_updates if self.n_updates else float("nan"),
                      "std_g": dict(zip(self.names, std_g.tolist())),
                      **extended_metadata(par, self.p, np.sqrt(np.maximum(np.diagonal(cov), 0.0))), **extra},
        )


__all__ = ["LottersBatch", "LottersRecursive", "resolve_parameterization", "validate_windows",
           "window_directions_spread_deg", "START_TOLERANCE", "HeldUncertainty", "held_uncertainty",
           "held_jacobian", "consider_gain", "with_held_uncertainty", "datasheet_held_uncertainty",
           "HELD_KEY", "CONSIDER_KEY", "DATASHEET_SENSITIVITY_REL_STD", "DATASHEET_OFFSET_STD_G"]
