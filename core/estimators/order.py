"""Model order: which parameters the windows determine, and which the evidence warrants.

Two questions, answered in this order (docs/twelve-parameters.md, "Model order"):

1. Observability (what *can* be updated): ``observability.is_observable``, the one rule (predicted
   RMS calibrated-acceleration error of an order <= ``tol_g``; statistical, systematic and consider
   parts, see observability.py).

2. Evidence (what *should* be updated), only between the 6-parameter model and the full set
   (cross-axis terms): both are fitted (LottersBatch) and compared by BIC (and
   AIC) on the weighted chi-square, and by k-fold held-out norm error. The cross-axis terms
   are chosen only when BIC prefers them *and* they lower the held-out error.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..calibration import Calibration
from ..crlb import RANK_RTOL, norm_noise_var, sphere_directions
from ..model.terms import calibration_view
from ..windows import WindowSet
from .extended import ExtendedParameterization, extended_residuals_g, fit_extended, parameterization
from .floor import quasi_static_floor
from .inuse12 import full_start, with_frame
from .lotters import LottersBatch
from .parameterization import norm_and_projection
from .observability import (N_PARAMS, ORDERS, SIGMA_FLOOR_G, SYSTEMATIC_G, TOL_G, OrderDecision, coverage, held_note,
                            is_observable, mg_or_none)


# -- evidence: information criteria and held-out error ---------------------------------------
def _norm_residuals(cal: Calibration, ws: WindowSet) -> np.ndarray:
    return 1.0 - np.linalg.norm(cal.apply(ws.mean), axis=1)  # [g], eq. 14


def _fit(ws: WindowSet, model: str, start: Calibration) -> Calibration:
    return LottersBatch(model).fit(ws, start)


def reference_start(model: str, start: Calibration, lab: Calibration | None) -> Calibration:
    """Held values for ``model`` in a comparison: the 6-parameter model holds the cross-axis terms of the
    lab calibration (or none), never ones the same data produced; 9/12 take their frame."""
    if model == "12":
        return with_frame(start, lab)
    if model == "9":
        return with_frame(start, None)
    S = np.diag(np.diag(with_frame(start, None).sensitivity))
    if model == "6" and lab is not None:
        K = lab.sensitivity.copy()
        K[np.diag_indices(3)] = np.diag(S)
        return Calibration(start.model, start.offset, K)
    return Calibration(start.model, start.offset, S)


def compare_orders(ws: WindowSet, models: tuple[str, ...], start: Calibration, *, lab: Calibration | None = None,
                   sigma_floor_g: float = SIGMA_FLOOR_G, folds: int = 5) -> dict[str, dict[str, Any]]:
    """Fit each order and score it: in-sample RMS, AIC and BIC (Gaussian: chi2 with the same per-window
    weights for every order, scaled by the largest model's reduced chi2 when > 1), and k-fold held-out
    RMS norm error [mg] (time-contiguous folds; the windows scored were not used for the fit)."""
    m = len(ws)
    fits = {k: _fit(ws, k, reference_start(k, start, lab)) for k in models}
    ref = fits[models[-1]]
    w = 1.0 / norm_noise_var(ws, ref, sigma_floor_g=sigma_floor_g)
    out: dict[str, dict[str, Any]] = {}
    order = np.argsort(ws.t, kind="stable")
    k_folds = min(folds, m // max(2 * max(N_PARAMS[k] for k in models), 1))
    # -2 log-likelihood up to a constant: chi2 / scale, with the noise scale of the window model unless the
    # largest model's reduced chi2 shows it is too small (then that, like LottersBatch's floor): a known-noise
    # comparison, so a lucky reduced chi2 < 1 does not inflate the evidence for extra terms
    r_full = _norm_residuals(fits[models[-1]], ws)
    scale = max(1.0, float(np.sum(w * r_full * r_full)) / max(m - N_PARAMS[models[-1]], 1))
    splits = fold_splits(ws, order, k_folds) if k_folds >= 2 else []  # every order's folds: the same windows
    for k, cal in fits.items():
        r = _norm_residuals(cal, ws)
        P = N_PARAMS[k]
        rss = float(np.sum(w * r * r))
        loglik_term = rss / scale
        entry: dict[str, Any] = {
            "n_params": P,
            "insample_rms_mg": round(float(np.sqrt(np.mean(r * r))) * 1e3, 4),
            "aic": round(loglik_term + 2 * P, 3),
            "bic": round(loglik_term + P * math.log(m), 3),
            "heldout_rms_mg": None,
        }
        if k_folds >= 2:
            held = np.empty(m)
            for idx, train, test in splits:
                try:
                    c = LottersBatch(k).fit_fold(train, reference_start(k, cal, lab))
                except ValueError:
                    held[idx] = np.nan
                    continue
                held[idx] = _norm_residuals(c, test)
            if np.all(np.isfinite(held)):
                entry["heldout_rms_mg"] = round(float(np.sqrt(np.mean(held * held))) * 1e3, 4)
        out[k] = entry
    out["_fits"] = fits  # type: ignore[assignment]
    return out


# -- the decision ---------------------------------------------------------------------------------
def select_order(ws: WindowSet, *, start: Calibration | None = None, lab: Calibration | None = None,
                 candidates: tuple[str, ...] | None = None, tol_g: float = TOL_G, systematic_g: float = SYSTEMATIC_G,
                 sigma_floor_g: float = SIGMA_FLOOR_G, compare: bool = True, folds: int = 5) -> OrderDecision:
    """Choose the model order for these windows and say why.

    ``start``: the current calibration (linearisation point and held values: the previous estimate
    online, a datasheet/bootstrap calibration offline; default an ellipsoid fit of the windows).
    ``lab``: a lab calibration whose frame makes the full set "12" instead of "9".
    ``compare``: fit and compare 6 vs the full set (BIC + held-out) when both are observable; without
    it (cheap, for every window online) the decision is observability only.
    Returns OrderDecision(model="none") when not even the offsets are determined.
    """
    full = "12" if lab is not None else "9"
    cands = tuple(candidates) if candidates is not None else ("offsets", "6", full)
    for c in cands:
        if c not in N_PARAMS:
            raise ValueError(f"unknown model order {c!r}; expected one of {', '.join(ORDERS)}")
    cands = tuple(sorted(cands, key=lambda c: N_PARAMS[c]))
    if len(ws) == 0:
        return OrderDecision("none", "no quasi-static windows yet: nothing is determined", {"n_windows": 0})
    if start is None:
        try:
            start = full_start(ws)
        except ValueError as exc:
            return OrderDecision("none", f"no start calibration and none derivable from the windows ({exc})",
                                 {"n_windows": len(ws)})
    cov = coverage(ws, start)
    evidence: dict[str, Any] = {"coverage": cov, "tol_mg": tol_g * 1e3, "systematic_mg": systematic_g * 1e3,
                                "sigma_floor_mg": sigma_floor_g * 1e3, "orders": {}}
    observable = []
    for c in cands:
        ok, ob = is_observable(ws, start, c, tol_g=tol_g, sigma_floor_g=sigma_floor_g, systematic_g=systematic_g)
        ob = {k: v for k, v in ob.items() if not k.startswith("_")}
        ob["observable"] = bool(ok)
        evidence["orders"][c] = ob
        if ok:
            observable.append(c)
    where = (f"{cov['n_windows']} windows, {cov['distinct_postures']} distinct postures, spread "
             f"{cov['spread_deg']:.0f}°")
    if not observable:
        o = evidence["orders"][cands[0]]
        pred = "unbounded" if o["predicted_mg"] is None else f"{o['predicted_mg']:.3g} mg"
        note = held_note(o)
        return OrderDecision("none", f"{where}: not even the offsets are determined (predicted error {pred} > "
                                     f"{tol_g * 1e3:.3g} mg{'; ' + note if note else ''}); holding the current "
                                     f"calibration", evidence)
    best = observable[-1]
    rejected = [c for c in cands if c not in observable]

    def why_not(c: str) -> str:
        o = evidence["orders"][c]
        if len(ws) < N_PARAMS[c]:
            return f"{c}: {len(ws)} windows < {N_PARAMS[c]} parameters"
        pred = "unbounded" if o["predicted_mg"] is None else f"{o['predicted_mg']:.3g} mg"
        amp = "inf" if o["amplification"] is None else f"{o['amplification']:.3g}"
        return f"{c}: predicted error {pred} (amplification {amp})"

    reason = f"{where}; {best} observable (predicted error {evidence['orders'][best]['predicted_mg']:.3g} mg)"
    if rejected:
        reason += "; not observable: " + ", ".join(why_not(c) for c in rejected)
    chosen_cal = None
    if compare and best in ("9", "12") and "6" in observable:
        scores = compare_orders(ws, ("6", best), start, lab=lab, sigma_floor_g=sigma_floor_g, folds=folds)
        fits = scores.pop("_fits")
        evidence["comparison"] = scores
        s6, sf = scores["6"], scores[best]
        better_bic = sf["bic"] < s6["bic"]
        h6, hf = s6["heldout_rms_mg"], sf["heldout_rms_mg"]
        better_held = True if (h6 is None or hf is None) else hf < h6
        cmp = (f"BIC {best} {sf['bic']:.1f} vs 6 {s6['bic']:.1f}" +
               ("" if h6 is None or hf is None else f", held-out {hf:.3g} vs {h6:.3g} mg"))
        if better_bic and better_held:
            reason += f"; cross-axis terms chosen ({cmp})"
        else:
            best = "6"
            reason += f"; cross-axis terms not warranted ({cmp}): 6 chosen"
        chosen_cal = fits[best]
    evidence["chosen"] = best
    return OrderDecision(best, reason, evidence, chosen_cal)


# -- extended terms (the registry's calibration terms): testability, observability, evidence ------------
def extended_base(model: str) -> str:
    """"6+temperature_offset" -> "6"; a plain order is its own base."""
    return model.split("+", 1)[0]


def extended_terms(model: str) -> tuple[str, ...]:
    return tuple(model.split("+")[1:])


def term_testability(ws: WindowSet, term: str, *, temp_column: int = 0) -> tuple[bool, str]:
    """Can the windows test registered term ``term`` at all? Its covariate must be there and finite, with
    the spread (5-95 %) its calibration view states (``min_span``: below it the term is a constant,
    indistinguishable from the offsets); whether a wider spread determines the term is the observability
    rule's call. Returns (testable, the reason when not)."""
    view = calibration_view(term)
    cov = view.covariate
    if cov is None or cov == "accel":
        return True, ""
    if cov == "temp" and temp_column != 0:
        values = ws.aux[:, temp_column] if ws.aux.ndim == 2 and ws.aux.shape[1] > temp_column else None
    else:
        values = ws.covariate(cov)
    if cov == "time":
        span_h = (float(np.max(ws.t)) - float(np.min(ws.t))) / 3600.0 if len(ws) else 0.0
        if span_h < view.min_span:
            return False, (f"the windows span {span_h * 3600:.0f} s ({span_h:.2g} h) < {view.min_span:g} h: "
                           f"{view.span_reason}")
        return True, ""
    return view.testability(values)


def _extended_params(par: Any, cal: Calibration) -> np.ndarray:
    """The parameter vector of ``cal`` in ``par``: its stated extended params when it has them."""
    params = cal.metadata.get("params") if isinstance(cal.metadata, dict) else None
    if isinstance(params, dict) and all(n in params for n in par.names) and cal.model == par.model:
        return np.array([float(params[n]) for n in par.names])
    return par.pack(cal.sensitivity, cal.offset)


def extended_observability(ws: WindowSet, cal: Calibration, model: str, *, sigma_floor_g: float = SIGMA_FLOOR_G,
                           systematic_g: float = SYSTEMATIC_G) -> dict[str, Any]:
    """The observability numbers of ``observability`` for an extended model (``"<base>+<term>..."``):
    the Fisher information with each window's covariates (temperature, time), and the error metric G
    averaged over all orientations *and* the windows' covariates (the RMS calibrated-acceleration
    error over the session's conditions). No consider term (the extended orders hold no parameter
    with a stated uncertainty beyond the base order's cross-axis part)."""
    par = parameterization(model, cal.sensitivity, cal.offset)
    if not isinstance(par, ExtendedParameterization):
        raise ValueError(f"{model!r} is not an extended model")
    p = _extended_params(par, cal)
    P = par.n_params
    bound = par.at_windows(ws)
    var0 = norm_noise_var(ws, cal)
    a, J = bound.accel_and_jacobian(p, ws.mean)
    _, B = norm_and_projection(a, J)
    F = (B / (var0 + sigma_floor_g**2)[:, None]).T @ B
    Fbar = (B / (var0 + 1.0)[:, None]).T @ B / max(len(ws), 1)
    # metric: sphere directions x the windows' covariate quantiles
    u = sphere_directions(64)
    q = np.linspace(0.05, 0.95, 7)
    rows = np.repeat(np.arange(len(q)), len(u))
    idx = np.clip((q * (len(ws) - 1)).round().astype(int), 0, max(len(ws) - 1, 0))
    aux = np.sort(ws.aux, axis=0)[idx][rows] if ws.aux.size else np.zeros((len(rows), 0))
    tt = np.sort(ws.t)[idx][rows]
    K, o = par.unpack(p)
    raw = np.tile(u, (len(q), 1)) @ K.T + o
    synth = WindowSet(raw, np.zeros((len(raw), 3, 3)), np.ones(len(raw)), tt, aux, np.arange(len(raw)),
                      np.arange(len(raw)) + 1)
    _, Jg = par.at_windows(synth).accel_and_jacobian(p, raw)
    G = np.einsum("mip,miq->pq", Jg, Jg) / len(raw)
    d = np.sqrt(np.maximum(np.diag(F), 1e-300))
    w, V = np.linalg.eigh(F / np.outer(d, d))
    singular = len(ws) < P or w.min() <= RANK_RTOL * max(w.max(), 1e-300)
    if singular:
        stat = amp = math.inf
    else:
        Finv = ((V / w) @ V.T) / np.outer(d, d)
        stat = float(np.sqrt(max(np.trace(G @ Finv), 0.0)))
        db = np.sqrt(np.maximum(np.diag(Fbar), 1e-300))
        wb, Vb = np.linalg.eigh(Fbar / np.outer(db, db))
        Fbinv = ((Vb / np.maximum(wb, 1e-300)) @ Vb.T) / np.outer(db, db)
        wg, Vg = np.linalg.eigh(0.5 * (G + G.T))
        Gh = (Vg * np.sqrt(np.maximum(wg, 0.0))) @ Vg.T  # G^1/2
        amp = float(np.sqrt(max(np.linalg.eigvalsh(Gh @ Fbinv @ Gh).max(), 0.0)))
    total = math.sqrt(stat**2 + (amp * systematic_g) ** 2) if math.isfinite(stat) and math.isfinite(amp) else math.inf
    std = np.sqrt(np.maximum(np.diag(((V / np.maximum(w, 1e-300)) @ V.T) / np.outer(d, d)), 0.0)) \
        if not singular else np.full(P, math.inf)
    return {"n_params": P, "stat_mg": mg_or_none(stat), "amplification": round(amp, 2) if math.isfinite(amp) else None,
            "predicted_mg": mg_or_none(total), "extra_std": dict(zip(par.extra_names, std[len(par.base.names):].tolist())),
            "_total_g": total}


def is_observable_extended(ws: WindowSet, cal: Calibration, model: str, *, tol_g: float = TOL_G,
                           sigma_floor_g: float = SIGMA_FLOOR_G, systematic_g: float = SYSTEMATIC_G
                           ) -> tuple[bool, dict[str, Any]]:
    """The observability rule (``is_observable``) for an extended model: every extra term testable
    (``term_testability``), and the predicted RMS error over orientations and the session's conditions
    <= ``tol_g`` (extended_observability). The base order is judged by ``is_observable`` separately."""
    for term in extended_terms(model):
        ok, why = term_testability(ws, term)
        if not ok:
            return False, {"untestable": term, "reason": why, "predicted_mg": None}
    obs = extended_observability(ws, cal, model, sigma_floor_g=sigma_floor_g, systematic_g=systematic_g)
    obs["reason"] = "" if obs["_total_g"] <= tol_g else (
        f"predicted error {obs['predicted_mg']} mg > {tol_g * 1e3:.3g} mg" if obs["predicted_mg"] is not None
        else "the terms are not determined (singular Fisher information)")
    return bool(obs["_total_g"] <= tol_g), obs


def fit_extended_floor(model: str, ws: WindowSet, start: Calibration, *, sigma_floor_g: float | None = None,
                       p0: np.ndarray | None = None):
    """fit_extended (iterated eq. 11a) of ``model`` held at ``start``, with the quasi-static floor derived
    from the data as LottersBatch does (None: the floor that brings the reduced chi² to 1, if > 1).
    Returns (ExtendedFit, floor [g])."""
    par = parameterization(model, start.sensitivity, start.offset)
    p0 = _extended_params(par, start) if p0 is None else p0
    var0 = norm_noise_var(ws, start)
    floor2 = 0.0 if sigma_floor_g is None else float(sigma_floor_g) ** 2
    fit = fit_extended(par, ws, p0, var0 + floor2)
    dof = len(ws) - par.n_params
    if sigma_floor_g is None and dof > 0 and fit.chi2 / dof > 1.0:
        r2 = fit.resid_g ** 2

        floor2 = quasi_static_floor(r2, var0, dof, 1e-14)
        fit = fit_extended(par, ws, fit.p, var0 + floor2)
    return fit, math.sqrt(floor2)


def compare_extended(ws: WindowSet, base: str, model: str, start: Calibration, *, lab: Calibration | None = None,
                     sigma_floor_g: float = SIGMA_FLOOR_G, folds: int = 5,
                     shared: dict[Any, Any] | None = None) -> dict[str, dict[str, Any]]:
    """The evidence for an extended model against its base, as compare_orders does for 6 vs the full set:
    both fitted (iterated eq. 11a) with the same fixed per-window weights, BIC on the chi² (scaled by the
    larger model's reduced chi² when > 1), and k-fold held-out RMS norm error [mg] (time-contiguous folds:
    with a temperature ramp a fold is a temperature range the fit has not seen). ``shared``: a dict the
    caller keeps across comparisons of several candidates on the same ``ws``, ``base``, ``start``, ``lab``
    and ``sigma_floor_g``; the base's fits, which do not depend on the candidate, are then done once."""
    ref = reference_start(base, start, lab)
    m = len(ws)
    var = norm_noise_var(ws, start, sigma_floor_g=sigma_floor_g)
    pars = {k: parameterization(k, ref.sensitivity, ref.offset) for k in (base, model)}
    Pm = pars[model].n_params
    order = np.argsort(ws.t, kind="stable")
    k_folds = min(folds, m // max(2 * Pm, 1))
    cache = {} if shared is None else shared
    fits: dict[str, Any] = {}
    helds: dict[str, np.ndarray | None] = {}
    if ("splits", k_folds) not in cache:
        cache[("splits", k_folds)] = fold_splits(ws, order, k_folds) if k_folds >= 2 else []
    for k, par in pars.items():
        key = (k, k_folds)
        if key not in cache:
            fit = fit_extended(par, ws, par.pack(start.sensitivity, start.offset), var)
            cache[key] = (fit, _fold_residuals(par, ws, fit.p, var, cache[("splits", k_folds)], k_folds))
        fits[k], helds[k] = cache[key]
    scale = max(1.0, fits[model].chi2 / max(m - Pm, 1))
    out: dict[str, dict[str, Any]] = {}
    for k, fit in fits.items():
        P = pars[k].n_params
        held = helds[k]
        out[k] = {"n_params": P, "insample_rms_mg": round(float(np.sqrt(np.mean(fit.resid_g ** 2))) * 1e3, 4),
                  "bic": round(fit.chi2 / scale + P * math.log(m), 3),
                  "heldout_rms_mg": None if held is None or not np.all(np.isfinite(held))
                  else round(float(np.sqrt(np.mean(held * held))) * 1e3, 4)}
    return out


def _fold_residuals(par: Any, ws: WindowSet, p: np.ndarray, var: np.ndarray,
                    splits: list[tuple[np.ndarray, WindowSet, WindowSet]], k_folds: int) -> np.ndarray | None:
    """1 - |a| [g] of every window from the fit (from ``p``) on the other time-contiguous folds (``splits``,
    fold_splits); None for fewer than 2 folds."""
    if k_folds < 2:
        return None
    held = np.empty(len(ws))
    for idx, train, test in splits:
        f = fit_extended(par, train, p, var[complement(idx, len(ws))])
        held[idx] = extended_residuals_g(par, f.p, test)
    return held


def fold_splits(ws: WindowSet, order: np.ndarray, k_folds: int) -> list[tuple[np.ndarray, WindowSet, WindowSet]]:
    """(held-out indices, training windows, held-out windows) of k_folds time-contiguous folds (``order``: the
    windows by time), made once for every model compared on them."""
    return [(idx, ws.subset(complement(idx, len(ws))), ws.subset(idx)) for idx in np.array_split(order, k_folds)]


def complement(idx: np.ndarray, m: int) -> np.ndarray:
    """The sorted indices of range(m) not in ``idx`` (np.setdiff1d of a permutation of range(m), without its sort)."""
    keep = np.ones(m, dtype=bool)
    keep[idx] = False
    return np.flatnonzero(keep)
