"""What one pose determines: each channel's reading against the temperature, and nothing the norm needs.

A recording held in one pose (a temperature chamber, a logger on a desk) gives the norm fit nothing to
work with: |K^-1 (raw - o)| = 1 g along one direction cannot separate the offsets from the gains, and an
offset across gravity does not change the norm to first order. What the pose does determine needs no
norm: the sensor does not move, so each raw channel's window mean is a constant plus whatever the
temperature adds, and a per-channel least-squares line (``channel_slopes``) gives its slope [raw/°C]
with a statistical std. Converted to g through the held sensitivities (the device's own calibration, or
the start) the slope also carries their stated relative std. Along gravity an offset change and a gain
change read alike; across gravity the absolute offsets, and every sensitivity, are not determined: they
are named with the reason, not printed as results.

The slopes are kept only when they predict windows they were not fitted on better than a constant does
(contiguous folds in time, per channel): otherwise the pose determines nothing and the verdict says so.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..blas import single_threaded_blas
from ..calibration import Calibration
from ..heldout import HeldoutResult
from ..model.terms import CALIBRATION_TERMS, COVARIATES, calibration_view
from ..windows import WindowSet

POSE_TOL_DEG = 10.0  # first cut: 2 mg/°C across gravity over 45 °C turns the apparent direction by 5°
POSE_HOLD_DEG = 0.5  # the pose once each channel's temperature line is out (9 mg across gravity; the chamber: < 0.6°)
MIN_POSE_WINDOWS = 6  # a line and its scatter need a few windows; fewer determine nothing
MIN_POSE_SHARE = 0.5  # the pose holds most windows (a chamber's handling is brief): else it is a wearer's day
FOLDS = 5  # contiguous folds of the held-out check
REML_TAUS = 10  # wander time constants tried, log-spaced from the windows' spacing to the session
REML_SHARES = np.linspace(0.0, 0.99, 34)  # the wander's share of the windows' variance tried
REML_MAX_WINDOWS = 250  # the covariance fit's windows (evenly thinned beyond: its cost grows as m^3)
WANDER_LR = 2.71  # -2 log REML gain for a wander: the 5 % point of one variance component on its boundary
MIN_DOF = 3.0  # a variance with fewer Satterthwaite dof is taken as 3 (the t's variance is infinite at 2)
SLOPES_CHI2 = 16.27  # chi²(3) at 0.999: the slopes applied only when they are not noise (and hold out better)
# the registered term a channel's slope on the temperature is held as: the zero-g level's, unlagged
TERM = next(t for t in CALIBRATION_TERMS if calibration_view(t).acts_on == "offset"
            and calibration_view(t).covariate == "temp" and not calibration_view(t).lagged)
HELD_KEY = "held_covariance"  # consider.HELD_KEY: the start's stated uncertainty of what a fit holds


def _wander_grid(t: np.ndarray, X: np.ndarray, y: np.ndarray):
    """Restricted maximum likelihood of white-plus-wander covariances V = s2 ((1 - lam) I + lam exp(-|dt| / tau))
    on a grid (the share profiled through one eigendecomposition per tau). Per column: -2 log REML of the best
    grid point and of white errors (lam 0), and the best point's (tau, lam, s2)."""
    (m, k), c = X.shape, y.shape[1]
    span, step = float(np.ptp(t)), float(np.median(np.diff(t)))
    lags = np.abs(t[:, None] - t[None])
    best_ll, best = np.full(c, np.inf), np.zeros((c, 3))
    white_ll = np.full(c, np.nan)
    for tau in np.geomspace(step, span, REML_TAUS):
        e, U = np.linalg.eigh(np.exp(-lags / tau))
        e = np.clip(e, 0.0, None)
        Xt, Yt = U.T @ X, U.T @ y
        for lam in REML_SHARES:
            d = (1.0 - lam) + lam * e
            A = (Xt / d[:, None]).T @ Xt
            B = np.linalg.solve(A, (Xt / d[:, None]).T @ Yt)
            s2 = np.sum((Yt - Xt @ B) ** 2 / d[:, None], axis=0) / (m - k)
            ll = (m - k) * np.log(np.maximum(s2, 1e-300)) + np.sum(np.log(d)) + np.linalg.slogdet(A)[1]
            if lam == 0.0:
                white_ll = ll
            better = ll < best_ll
            best_ll = np.where(better, ll, best_ll)
            best[better] = np.column_stack([np.full(c, tau), np.full(c, lam), s2])[better]
    return lags, white_ll, best_ll, best


def _satterthwaite_dof(lags: np.ndarray, X: np.ndarray, h: np.ndarray, tau: float, a: float, b: float) -> float:
    """Degrees of freedom of the slope variance v = h' V h estimated through V = a I + b exp(-|dt| / tau):
    2 v² / Var(v), Var(v) by the delta method with the REML information of (a, b, tau) (Kenward & Roger's
    Satterthwaite step)."""
    C = np.exp(-lags / tau)
    e, U = np.linalg.eigh(C)
    d = a + b * np.clip(e, 0.0, None)
    Xt = U.T @ X
    XdX = (Xt / d[:, None]).T @ Xt
    DiX = Xt / d[:, None]
    P = np.diag(1.0 / d) - DiX @ np.linalg.solve(XdX, DiX.T)  # the REML projection, in C's eigenbasis
    dV = [np.ones_like(d), np.clip(e, 0.0, None), U.T @ (b * C * lags / tau ** 2) @ U]
    PdV = [P * D[None, :] if D.ndim == 1 else P @ D for D in dV]
    info = np.array([[0.5 * np.sum(Pi * Pj.T) for Pj in PdV] for Pi in PdV])
    ht = U.T @ h
    grad = np.array([ht @ ht, ht @ (dV[1] * ht), ht @ dV[2] @ ht])
    v = a * (ht @ ht) + b * (ht @ (dV[1] * ht))
    var_v = float(grad @ np.linalg.pinv(info) @ grad)
    return 2.0 * v * v / var_v if var_v > 0 else np.inf


def correlated_slope_std(t: np.ndarray, x: np.ndarray | None, y: np.ndarray, coef: int = 1) -> np.ndarray:
    """(c,) std of each column's least-squares slope (``coef`` 1; 0: the line's value at the mean of ``x``, or
    the mean where ``x`` is None) of ``y`` (m, c) on ``x`` (``t`` ascending): its variance h' V h under the
    windows' covariance V, which is white unless a slow wander (exp(-|dt| / tau): a chamber's drift, a
    warm-up's lag) improves the restricted likelihood by more than WANDER_LR. The wander's share and tau are
    estimated from this one session, so the variance has few degrees of freedom (nu, Satterthwaite): an error
    over such a std is t-distributed with variance nu / (nu - 2), and the std is widened by that factor so
    that it is the error's std, not its typical scale."""
    m = len(t)
    X = np.ones((m, 1)) if x is None else np.column_stack([np.ones(m), x - x.mean()])
    k = X.shape[1]
    h = X @ np.linalg.inv(X.T @ X)[:, coef]  # the least-squares estimate's weights on the windows
    if m < 8 or not np.ptp(t) > 0 or not np.median(np.diff(t)) > 0:
        return np.full(y.shape[1], np.nan)
    lags, white_ll, best_ll, best = _wander_grid(t, X, y)
    out = np.empty(y.shape[1])
    for j, (tau, lam, s2) in enumerate(best):
        white_s2 = float(np.sum((y[:, j] - X @ np.linalg.lstsq(X, y[:, j], rcond=None)[0]) ** 2) / (m - k))
        if lam == 0.0 or white_ll[j] - best_ll[j] <= WANDER_LR:
            out[j] = np.sqrt(white_s2 * (h @ h) * (m - k) / (m - k - 2))  # white: t with m - k dof
            continue
        a, b = s2 * (1.0 - lam), s2 * lam
        v = a * (h @ h) + b * (h @ np.exp(-lags / tau) @ h)
        nu = max(_satterthwaite_dof(lags, X, h, tau, a, b), MIN_DOF)
        out[j] = np.sqrt(v * nu / (nu - 2.0))
    return out


def channel_slopes(ws: WindowSet, covariate: str) -> dict[str, Any] | None:
    """Each raw channel's mean regressed on a covariate over the windows: slope [raw per unit] and its std.
    Needs no offsets, sensitivities or direction: what an independent least-squares fit sees. The std is the
    least-squares slope's under the windows' covariance (``correlated_slope_std``): white, or white plus a slow
    wander where the windows show one (windows close in time then share errors that a white std would take for
    independent), widened for the few degrees of freedom a wander's estimate has."""
    x = ws.covariate(covariate) if covariate != "time" else ws.t / 3600.0
    if x is None or np.ptp(x) == 0 or len(ws) < 3:
        return None
    order = np.argsort(ws.t, kind="stable")
    A = np.column_stack([np.ones(len(ws)), x - x.mean()])
    slope = np.linalg.lstsq(A, ws.mean, rcond=None)[0][1]
    sub = order if len(order) <= REML_MAX_WINDOWS else order[np.linspace(0, len(order) - 1, REML_MAX_WINDOWS).astype(int)]
    # thinned: not scaled down (a wander does not average out over more windows; the white part is then generous)
    sd = single_threaded_blas(correlated_slope_std)(ws.t[sub], x[sub], ws.mean[sub])
    if not np.all(np.isfinite(sd)):  # too few windows for a covariance: the least-squares std
        resid = ws.mean - A @ np.linalg.lstsq(A, ws.mean, rcond=None)[0]
        s2 = (resid ** 2).sum(axis=0) / max(len(ws) - 2, 1)
        sd = np.sqrt(s2 / max(float(np.sum((x - x.mean()) ** 2)), 1e-300))
    unit = COVARIATES[covariate].unit
    return {"unit": f"raw/{unit}", "value": dict(zip("xyz", slope.tolist())), "std": dict(zip("xyz", sd.tolist()))}


def held_gain_rel_std(start: Calibration, held: dict[str, Any] | None = None) -> np.ndarray:
    """(3,) relative std of the start's per-axis gains as it (or ``held``, its held covariance) states them (0
    where none is stated)."""
    out = np.zeros(3)
    if held is None:
        held = start.metadata.get(HELD_KEY) if isinstance(start.metadata, dict) else None
    if not held:
        return out
    names, cov = held.get("names", []), np.asarray(held.get("cov", []), dtype=float)
    s = np.abs(np.diag(start.sensitivity))
    for n, name in enumerate(names):
        if name in ("s_x", "s_y", "s_z"):
            i = "xyz".index(name[2])
            out[i] = float(np.sqrt(cov[n, n])) / s[i]
    return out


def dominant_pose(ws: WindowSet, start: Calibration, tol_deg: float = POSE_TOL_DEG,
                  hold_deg: float = POSE_HOLD_DEG) -> tuple[np.ndarray, np.ndarray]:
    """(indices of the windows that hold one pose, its unit direction in g under the start). First the windows
    within ``tol_deg`` of the direction with the most windows that near (each window's own direction tried, so
    handling moments do not pull it); then each channel's line in the temperature over them is taken out of
    every window (a drift of the zero-g levels turns the apparent direction, not the sensor) and the pose is
    the windows within ``hold_deg`` of the same direction: a sensor that moved within a few degrees (a wearer
    standing) is not one pose."""
    def near(mean: np.ndarray, deg: float) -> np.ndarray:
        a = start.apply_reference(mean)
        u = a / np.linalg.norm(a, axis=1, keepdims=True)
        close = (u @ u.T) >= np.cos(np.radians(deg))  # (M, M): fine for the few hundred windows a pose gives
        return np.flatnonzero(close[int(np.argmax(close.sum(axis=1)))])

    idx = near(ws.mean, tol_deg)
    temp = ws.covariate("temp")
    mean = ws.mean
    if temp is not None and np.all(np.isfinite(temp[idx])) and len(idx) >= 3 and np.ptp(temp[idx]) > 0:
        x = temp - np.mean(temp[idx])
        slope = np.linalg.lstsq(np.column_stack([np.ones(len(idx)), x[idx]]), mean[idx], rcond=None)[0][1]
        mean = mean - np.outer(np.where(np.isfinite(x), x, 0.0), slope)
    idx = near(mean, hold_deg)
    a = start.apply_reference(mean[idx])
    d = (a / np.linalg.norm(a, axis=1, keepdims=True)).mean(axis=0)
    return idx, d / np.linalg.norm(d)


def _mean_and_std(pose: WindowSet, v: np.ndarray) -> tuple[float, float]:
    """``v`` (one value per window) at the pose's mean temperature (a line in it where there is one) and that
    value's std under the windows' covariance, as the slopes' (``correlated_slope_std``, coef 0)."""
    temp = pose.covariate("temp")
    x = temp if temp is not None and np.all(np.isfinite(temp)) and np.ptp(temp) > 0 else None
    A = np.ones((len(v), 1)) if x is None else np.column_stack([np.ones(len(v)), x - x.mean()])
    value = float(np.linalg.lstsq(A, v, rcond=None)[0][0])
    order = np.argsort(pose.t, kind="stable")
    sub = order if len(order) <= REML_MAX_WINDOWS else order[np.linspace(0, len(order) - 1, REML_MAX_WINDOWS).astype(int)]
    # thinned: not scaled down (the white part is then generous)
    sd = float(single_threaded_blas(correlated_slope_std)(pose.t[sub], None if x is None else x[sub], v[sub, None],
                                                          coef=0)[0])
    if not np.isfinite(sd):
        resid = v - A @ np.linalg.lstsq(A, v, rcond=None)[0]
        sd = float(np.sqrt(np.sum(resid ** 2) / max(len(v) - A.shape[1], 1) / len(v)))
    return value, sd


def _contiguous_heldout(ws: WindowSet, x: np.ndarray | None, K: np.ndarray, folds: int) -> tuple[float, list[float], list[int]]:
    """RMS [mg] of each channel's reading in held-out contiguous folds, predicted by a constant (``x`` None) or a
    line in ``x`` fitted on the other folds; the raw residual taken to g through K^-1."""
    order = np.argsort(ws.t, kind="stable")
    parts = np.array_split(order, folds)
    errs, fold_rms, sizes = [], [], []
    for k, test in enumerate(parts):
        train = np.concatenate([p for j, p in enumerate(parts) if j != k])
        y = ws.mean[train]
        if x is None:
            pred = np.broadcast_to(y.mean(axis=0), (len(test), 3))
        else:
            A = np.column_stack([np.ones(len(train)), x[train]])
            coef = np.linalg.lstsq(A, y, rcond=None)[0]
            pred = np.column_stack([np.ones(len(test)), x[test]]) @ coef
        e = np.linalg.solve(K, (ws.mean[test] - pred).T).T * 1e3
        errs.append(e)
        fold_rms.append(float(np.sqrt(np.mean(e ** 2))))
        sizes.append(len(test))
    e = np.concatenate(errs)
    return float(np.sqrt(np.mean(e ** 2))), fold_rms, sizes


@dataclass
class SinglePose:
    """What one pose determines (``determined``: values with std), what it does not (``undetermined``: name ->
    reason), the calibration returned (the start's K and o, with the temperature slopes as a term where they
    hold out better than none) and whether anything is determined (``status``: "partial" or "refused")."""

    status: str
    reason: str
    calibration: Calibration
    windows: WindowSet
    heldout: HeldoutResult | None
    determined: dict[str, Any] = field(default_factory=dict)
    undetermined: dict[str, str] = field(default_factory=dict)
    n_other_windows: int = 0

    def to_json_dict(self) -> dict[str, Any]:
        return {"windows_in_pose": len(self.windows), "windows_in_other_postures": self.n_other_windows,
                "determined": self.determined, "undetermined": self.undetermined}


def single_pose(ws: WindowSet, start: Calibration, *, folds: int = FOLDS, why_not_norm: str = "") -> SinglePose | None:
    """The single-pose answer for windows whose norm determines nothing (``why_not_norm``: the order rule's
    reason), or None when the windows do not hold one pose (fewer than MIN_POSE_WINDOWS, or than MIN_POSE_SHARE
    of them, within POSE_TOL_DEG of the dominant direction)."""
    idx, g_dir = dominant_pose(ws, start)
    if len(idx) < max(MIN_POSE_WINDOWS, MIN_POSE_SHARE * len(ws)):
        return None
    pose = ws.subset(np.sort(idx))
    others = len(ws) - len(pose)
    K, o = start.sensitivity, start.offset
    rel = held_gain_rel_std(start)
    who = start.message or "the start"
    axis = int(np.argmax(np.abs(g_dir)))
    across = [a for i, a in enumerate("xyz") if abs(g_dir[i]) < np.cos(np.radians(45.0))]
    undetermined: dict[str, str] = {}
    for a in across:
        undetermined[f"o_{a}"] = (f"one pose: an offset across gravity does not change the norm (|a| = 1 g) to first "
                                  f"order, and a channel's constant reading is its offset plus its share of gravity; "
                                  f"held at {who}")
    for a in "xyz":
        undetermined[f"s_{a}"] = f"one pose: the sensitivities need several postures; held at {who}"
    undetermined["cross-axis terms"] = "one pose: the axes' cross-coupling needs several postures; held at the start"
    determined: dict[str, Any] = {}

    # along gravity: |a| - 1 g under the held calibration is the sum of an offset error and a gain error there
    norm_mg = (np.linalg.norm(start.apply_reference(pose.mean), axis=1) - 1.0) * 1e3
    err_mg, noise_mg = _mean_and_std(pose, norm_mg)
    rel_g = float(np.sqrt(np.sum((g_dir * rel) ** 2)))  # the held gains' relative std along gravity
    off_g_std = float(np.hypot(noise_mg, rel_g * 1e3))
    determined["norm_along_gravity_mg"] = {  # a measurement of the held calibration, not a parameter
        "value": err_mg, "std": noise_mg,
        "meaning": "|a| - 1 g of the pose under the held calibration at the pose's mean temperature: the offset "
                   "error along gravity plus the gain error there (one pose cannot split them)"}
    # the offset along gravity is not applied even when the held gains are tight: the norm also carries the
    # undetermined offsets across gravity to second order (50 mg across: 1.25 mg along), which no std here covers
    gain = f"±{100 * rel_g:.3g} %" if rel_g > 0 else "of unstated uncertainty"
    undetermined["offset along gravity"] = (
        f"one pose reads |a| - 1 g = {err_mg:.3g} mg along gravity: an offset there and a gain error there read "
        f"alike (with the held gains {gain}: {off_g_std:.3g} mg), and the undetermined offsets across gravity add "
        f"to the norm at second order; held at {who}")

    cal = Calibration(start.model, np.array(o, dtype=float), K.copy(), n_windows=len(pose), converged=True, observable=False,
                      message=f"one pose: offsets and sensitivities held at {who}",
                      metadata={k: v for k, v in start.metadata.items() if k != HELD_KEY})
    temp = pose.covariate("temp")
    view = calibration_view(TERM)
    span = None if temp is None or not np.any(np.isfinite(temp)) else float(np.ptp(temp[np.isfinite(temp)]))
    heldout = None
    if span is None or not np.all(np.isfinite(temp)) or span < (view.min_span or 0.0):
        undetermined["temperature slopes"] = ("no temperature column" if span is None else
                                              f"the pose's temperature spans {span:.3g} °C < {view.min_span:g} °C: "
                                              f"{view.span_reason}")
        status = "refused"
        reason = f"one pose ({len(pose)} windows): nothing the data determine can be applied"
    else:
        slopes = channel_slopes(pose, "temp")
        raw = np.array([slopes["value"][a] for a in "xyz"])
        raw_sd = np.array([slopes["std"][a] for a in "xyz"])
        Kinv = np.linalg.inv(K)
        value = Kinv @ raw * 1e3  # mg/°C along each calibrated axis
        stat = np.sqrt(np.diag(Kinv @ np.diag(raw_sd ** 2) @ Kinv.T)) * 1e3
        sd = np.hypot(stat, np.abs(value) * rel)
        folds = max(2, min(folds, len(pose) // 3))
        with_mg, fold_rms, sizes = _contiguous_heldout(pose, temp, K, folds)
        without_mg, _, _ = _contiguous_heldout(pose, None, K, folds)
        t_ref = float(np.mean(temp))
        A = np.column_stack([np.ones(len(pose)), temp - t_ref])
        coef = np.linalg.lstsq(A, pose.mean, rcond=None)[0]
        insample = float(np.sqrt(np.mean((np.linalg.solve(K, (pose.mean - A @ coef).T).T * 1e3) ** 2)))
        heldout = HeldoutResult(with_mg, insample, "contiguous per-channel (one pose)", folds, fold_rms, sizes,
                                [f"one pose: each channel's reading predicted in held-out contiguous folds (a line in "
                                 f"the temperature fitted on the others), not |a| - 1 g; a constant holds out at "
                                 f"{without_mg:.3g} mg"])
        magnitude = {"unit": view.unit, "value": dict(zip("xyz", value.tolist())), "std": dict(zip("xyz", sd.tolist())),
                     "std_statistical": dict(zip("xyz", stat.tolist())),
                     "std_gain": dict(zip("xyz", (np.abs(value) * rel).tolist())),
                     "raw_channel_slopes": slopes,
                     "method": "per-channel least squares of the pose's window means on the temperature; std: the "
                               "slope's under the windows' covariance (white, or white plus a slow wander where it "
                               "gains the restricted likelihood), widened for the wander's few degrees of freedom "
                               "(Satterthwaite), with the held gains' relative std"}
        chi2 = float(np.sum((raw / raw_sd) ** 2))  # the three slopes against none, in their own std
        magnitude["test"] = {"heldout_rms_mg_with": with_mg, "heldout_rms_mg_without": without_mg,
                             "heldout_gain_mg": without_mg - with_mg, "folds": folds, "fold_rms_mg": fold_rms,
                             "heldout_scheme": "each channel's reading in contiguous time folds, the line fitted on the "
                                               "other folds, against a constant fitted likewise",
                             "chi2": chi2, "chi2_threshold": SLOPES_CHI2}
        if with_mg < without_mg and chi2 > SLOPES_CHI2:
            determined["temperature_slopes"] = magnitude
            names = view.param_names()
            cal.model = f"offsets+{TERM}"  # the extended family whose K is held (here o too: named undetermined)
            cal.param_names = list(names)
            cal.covariance = np.diag(raw_sd ** 2)
            cal.metadata.update({"extended": {"terms": [TERM], "t_ref_c": t_ref,
                                              "magnitudes": {TERM: {"unit": view.unit, "value": magnitude["value"],
                                                                    "std": magnitude["std"]}}},
                                 "params": {**{f"o_{a}": float(o[i]) for i, a in enumerate("xyz")},  # held
                                            **dict(zip(names, raw.tolist()))}, "t_ref_c": t_ref})
            g = "xyz"[axis]
            undetermined[f"temperature slope along gravity ({g}): offset or gain"] = (
                f"one pose: a temperature change of the offset and of the gain along gravity read alike; the "
                f"{g} slope is stated as an offset slope and corrects this pose either way")
            status = "partial"
            cal.observable = True  # what is fitted (the slopes) is determined; K and o are held, and named so
            reason = (f"one pose ({len(pose)} windows within {POSE_HOLD_DEG:g}° of one direction once the temperature is out"
                      + (f", {others} in other postures not used" if others else "")
                      + f"): each channel's temperature slope determined over {span:.3g} °C (held-out "
                        f"{with_mg:.3g} mg per channel, against {without_mg:.3g} mg without); the offsets across "
                        f"gravity and the sensitivities are not determined and stay at {who}")
        else:
            undetermined["temperature slopes"] = (f"the per-channel slopes are not told from none: held-out {with_mg:.3g} "
                                                  f"vs {without_mg:.3g} mg with a constant, chi² {chi2:.3g} "
                                                  f"(need < the constant's and > {SLOPES_CHI2:g})")
            status = "refused"
            reason = f"one pose ({len(pose)} windows): nothing the data determine improves on {who}"
    if why_not_norm:
        undetermined["norm fit"] = why_not_norm
    return SinglePose(status, reason, cal, pose, heldout, determined, undetermined, others)
