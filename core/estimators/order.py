"""Model order by observability: which parameters can the windows determine now?

Two questions, answered in this order (docs/twelve-parameters.md, "Model order"):

1. Observability (what *can* be updated). For every candidate order — offsets (3), 6,
   the full identifiable set 9 (or 12 with a lab frame) — the Fisher information of the
   windows (``core/crlb.py``) gives two numbers, both as RMS calibrated-acceleration error
   over all orientations [g]:

   * statistical: sqrt(tr(G F^-1)) with the window noise plus a quasi-static floor;
   * systematic: a per-window model error of ``systematic_g`` RMS (nonlinearity, residual
     motion, temperature) amplified by the geometry, ``amp = sqrt(lambda_max(G Fbar^-1))``
     with Fbar the per-window information at unit noise. amp depends only on the coverage of
     the sphere, not on the number of windows: it is why orientation 1 with theta = 30° never
     gives sensitivities however long one records (amp ~ 1600 for 6 parameters, ~ 4 for offsets).

   * consider: the parameters the order holds (offsets-only holds the sensitivities) carry the
     uncertainty the current calibration states for them (lotters.held_uncertainty: its covariance,
     its stated held covariance, or the datasheet spread for a nominal start); through these
     windows it biases the estimated ones by Gc dtheta (Schmidt consider gain), RMS over all
     orientations sqrt(tr(G Gc C_h Gc^T)). Upright windows cannot tell a sensitivity error from
     an offset: from a datasheet start the offsets are then not determined.

   An order is observable when sqrt(stat^2 + (amp * systematic)^2 + consider^2) <= ``tol_g``.

2. Evidence (what *should* be updated), only between the 6-parameter model and the full set
   (cross-axis terms): both are fitted (H-estimate's LottersBatch) and compared by BIC (and
   AIC) on the weighted chi-square, and by k-fold held-out norm error. The cross-axis terms
   are chosen only when BIC prefers them *and* they lower the held-out error.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..calibration import Calibration
from ..crlb import RANK_RTOL, bound_from_fisher, fisher_inuse, norm_noise_var, on_ellipsoid, sphere_directions, sphere_metric
from ..model.terms import calibration_view
from ..windows import Window, WindowSet

ORDERS = ("offsets", "6", "9", "12")
N_PARAMS = {"offsets": 3, "6": 6, "9": 9, "12": 9}
TOL_G = 0.010  # auto: predicted RMS acceleration error allowed [g]: 1 % of 1 g (a third of Lötters' 3 %)
TOL_EXPLICIT_G = 0.030  # an order the user asked for is refused only beyond Lötters' 3 % criterion
SYSTEMATIC_G = 0.0005  # per-window model error that no window count averages away [g] (nonlinearity, residual motion)
SIGMA_FLOOR_G = 0.002  # quasi-static floor on each window's norm noise [g] (residual body motion)
POSTURE_CELLS = 400  # sphere cells (~10° apart) for counting distinct postures


@dataclass
class OrderDecision:
    """The order chosen (``model``: "none", "offsets", "6", "9" or "12"), why, and the numbers."""

    model: str
    reason: str
    evidence: dict[str, Any] = field(default_factory=dict)
    calibration: Calibration | None = None  # the fit of the chosen order when select_order fitted it

    @property
    def updates_sensitivities(self) -> bool:
        return self.model in ("6", "9", "12")


# -- coverage and observability -----------------------------------------------------------
def coverage(ws: WindowSet, cal: Calibration) -> dict[str, Any]:
    """How much of the sphere the windows cover (directions through ``cal``).

    spread_deg: largest angle from the mean direction (Lötters' theta); scatter_eig: eigenvalues of
    mean(u u^T) (1/3 each for the full sphere, (1, 0, 0) for one posture); distinct_postures:
    occupied cells of a ~10° grid on the sphere."""
    a = cal.apply_reference(ws.mean)
    u = a / np.linalg.norm(a, axis=1, keepdims=True)
    c = u.sum(axis=0)
    nc = np.linalg.norm(c)
    spread = 180.0 if nc < 1e-12 else float(np.degrees(np.arccos(np.clip(u @ (c / nc), -1, 1).min())))
    cells = np.argmax(u @ sphere_directions(POSTURE_CELLS).T, axis=1)
    return {
        "n_windows": len(ws),
        "spread_deg": round(spread, 2),
        "scatter_eig": np.round(np.linalg.eigvalsh(u.T @ u / len(u))[::-1], 4).tolist(),
        "distinct_postures": int(np.unique(cells).size),
    }


def observability(ws: WindowSet, cal: Calibration, model: str, *, sigma_floor_g: float = SIGMA_FLOOR_G,
                  systematic_g: float = SYSTEMATIC_G) -> dict[str, Any]:
    """Predicted errors of order ``model`` for these windows at ``cal`` (see module docstring)."""
    # one Jacobian for both informations: with the window noise (+ floor), and per window at unit noise
    F, param, Fu = fisher_inuse(ws, cal, model, sigma_floor_g=sigma_floor_g, unit_floor_g=1.0)
    G = sphere_metric(param, cal)
    bound = bound_from_fisher(param.model, param.names, F, G, len(ws))
    Fbar = Fu / max(len(ws), 1)  # geometry only
    w = np.linalg.eigvalsh(Fbar) if len(ws) else np.zeros(1)
    if len(ws) == 0 or w.min() <= 1e-12 * max(w.max(), 1e-300):
        amp = math.inf
    else:
        L = np.linalg.cholesky(G)
        amp = float(np.sqrt(np.linalg.eigvalsh(L.T @ np.linalg.solve(Fbar, L)).max()))
    stat = bound.accel_rms_g
    consider, held = _consider_g(ws, cal, param, F, G, sigma_floor_g) if math.isfinite(stat) else (0.0, None)
    total = (math.sqrt(stat**2 + (amp * systematic_g) ** 2 + consider**2)
             if math.isfinite(stat) and math.isfinite(amp) and math.isfinite(consider) else math.inf)
    return {
        "n_params": param.n_params,
        "stat_mg": _mg(stat),
        "amplification": round(amp, 2) if math.isfinite(amp) else None,
        "consider_mg": _mg(consider),
        "held": None if held is None else {"names": held.names, "source": held.source},
        "predicted_mg": _mg(total),
        # the same without the held parameters' uncertainty: determined *given* the held values
        "predicted_given_held_mg": _mg(math.hypot(stat, amp * systematic_g) if math.isfinite(stat) and math.isfinite(amp)
                                       else math.inf),
        "fisher_eig_per_window": np.round(w * float(np.mean(np.abs(np.diag(cal.sensitivity)))) ** 2, 8).tolist()
        if len(ws) else [],
        "undetermined": bound.undetermined,
        "_total_g": total,
    }


def _consider_g(ws: WindowSet, cal: Calibration, param, F: np.ndarray, G: np.ndarray,
                sigma_floor_g: float) -> tuple[float, Any]:
    """RMS calibrated-acceleration error [g] over all orientations that the uncertainty of the parameters
    ``param`` holds (``cal``'s stated uncertainty, lotters.held_uncertainty) puts into the estimated ones
    through these windows: sqrt(tr(G_sphere Gc C_h Gc^T)), Gc the consider gain (Schmidt) at ``cal``."""
    from .lotters import consider_gain, held_jacobian, held_uncertainty  # noqa: PLC0415 (lotters imports this module lazily)

    held = held_uncertainty(cal, param)
    if held is None or len(ws) == 0:
        return 0.0, held
    _, r_star = on_ellipsoid(ws, cal)
    p = param.pack(cal.sensitivity, cal.offset)
    _, B, _ = param.norm_and_jacobian(p, r_star)
    var = norm_noise_var(ws, cal, sigma_floor_g=sigma_floor_g)
    w, V = np.linalg.eigh(0.5 * (F + F.T))
    if w.min() <= RANK_RTOL * max(w.max(), 1e-300):
        return math.inf, held
    Gc = consider_gain((V / w) @ V.T, B, var, held_jacobian(param, p, r_star, held))
    return float(np.sqrt(max(np.trace(G @ Gc @ held.cov @ Gc.T), 0.0))), held


def held_note(obs: dict[str, Any]) -> str:
    """What to say when the held parameters' uncertainty dominates an order's predicted error ('' if not)."""
    c, stat, held = obs.get("consider_mg"), obs.get("stat_mg"), obs.get("held")
    if held is None or c is None or stat is None or c <= stat:
        return ""
    what = "sensitivities" if all(n.startswith("s_") and len(n) == 3 for n in held["names"]) else ", ".join(held["names"])
    return (f"the uncertainty of the held {what} ({held['source']}) dominates: {c:.3g} mg of the predicted error "
            f"(window noise {stat:.3g} mg); windows in other postures (lying, bending: the sensor's axes "
            f"along and against gravity) determine the sensitivities (order 6), or start from a calibration "
            f"with a small covariance")


def is_observable(ws: WindowSet, cal: Calibration, model, *, tol_g: float = TOL_G,
                  sigma_floor_g: float = SIGMA_FLOOR_G, systematic_g: float = SYSTEMATIC_G) -> tuple[bool, dict[str, Any]]:
    """THE observability rule of gravcal (one place; select_order, check_observable and LottersBatch's
    ``observable`` flag all use it): order ``model`` (a name or a Parameterization, evaluated at ``cal``)
    is observable from ``ws`` when there are at least as many windows as parameters and the predicted
    RMS calibrated-acceleration error sqrt(stat² + (amp·systematic)² + consider²) [g] over all orientations
    is <= ``tol_g`` (consider: the held parameters' stated uncertainty, see the module docstring). Returns (verdict, the numbers of ``observability``)."""
    obs = observability(ws, cal, model, sigma_floor_g=sigma_floor_g, systematic_g=systematic_g)
    return bool(len(ws) >= obs["n_params"] and obs["_total_g"] <= tol_g), obs


def _mg(x: float) -> float | None:
    return round(x * 1e3, 3) if math.isfinite(x) else None


def _default_start(ws: WindowSet) -> Calibration:
    from .inuse12 import _full_start  # noqa: PLC0415

    return _full_start(ws)


def check_observable(ws: WindowSet, model: str, start: Calibration, *, tol_g: float = TOL_EXPLICIT_G,
                     sigma_floor_g: float = SIGMA_FLOOR_G, systematic_g: float = SYSTEMATIC_G) -> dict[str, Any]:
    """Raise ValueError saying what is missing if ``model`` cannot be determined from ``ws``;
    return the observability numbers otherwise."""
    if model not in N_PARAMS:
        raise ValueError(f"unknown model order {model!r}; expected one of {', '.join(ORDERS)}")
    m, P = len(ws), N_PARAMS[model]
    if m < P:
        raise ValueError(f"model {model} has {P} parameters but there are only {m} quasi-static window(s): "
                         f"need at least {P}, from different postures")
    cov = coverage(ws, start)
    ok, obs = is_observable(ws, start, model, tol_g=tol_g, sigma_floor_g=sigma_floor_g, systematic_g=systematic_g)
    if not ok:
        what = "offsets" if model == "offsets" else ("sensitivities" if model == "6" else "sensitivities and cross-axis terms")
        pred = "unbounded (singular Fisher information)" if obs["predicted_mg"] is None else f"{obs['predicted_mg']:.3g} mg"
        raise ValueError(
            f"model {model}: the {m} windows do not determine the {what}: they cover {cov['distinct_postures']} "
            f"distinct posture(s) within {cov['spread_deg']:.0f}° of one direction (scatter eigenvalues "
            f"{', '.join(f'{e:.3g}' for e in cov['scatter_eig'])}); predicted error {pred} > {tol_g * 1e3:.3g} mg"
            + (f" ({note})" if (note := held_note(obs)) else "") +
            ". Record more varied postures (lying, bending), or use --model auto")
    return obs


# -- evidence: information criteria and held-out error ---------------------------------------
def _norm_residuals(cal: Calibration, ws: WindowSet) -> np.ndarray:
    return 1.0 - np.linalg.norm(cal.apply(ws.mean), axis=1)  # [g], eq. 14


def _fit(ws: WindowSet, model: str, start: Calibration) -> Calibration:
    from .lotters import LottersBatch  # noqa: PLC0415 (H-estimate's estimator: one Gauss-Newton in gravcal)

    return LottersBatch(model).fit(ws, start)


def _reference_start(model: str, start: Calibration, lab: Calibration | None) -> Calibration:
    """Held values for ``model`` in a comparison: the 6-parameter model holds the cross-axis terms of the
    lab calibration (or none), never ones the same data produced; 9/12 take their frame."""
    from .inuse12 import with_frame  # noqa: PLC0415

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
    from ..crlb import norm_noise_var  # noqa: PLC0415

    m = len(ws)
    fits = {k: _fit(ws, k, _reference_start(k, start, lab)) for k in models}
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
            for idx in np.array_split(order, k_folds):
                train = np.setdiff1d(order, idx)
                try:
                    c = _fit(ws.subset(train), k, _reference_start(k, cal, lab))
                except ValueError:
                    held[idx] = np.nan
                    continue
                held[idx] = _norm_residuals(c, ws.subset(idx))
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
            start = _default_start(ws)
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


class OnlineOrderSelector:
    """select_order as windows accumulate (the daemon / recursive estimator): observability after every
    ``every`` new windows (cheap), the 6-vs-full comparison (fits) every ``compare_every`` windows; in
    between, the last comparison's verdict on the cross-axis terms stands. The caller keeps ``start``
    current (``selector.start = estimator.calibration``) so the information is evaluated at the estimate."""

    def __init__(self, start: Calibration, *, lab: Calibration | None = None, every: int = 10,
                 compare_every: int = 100, **kw: Any):
        self.start, self.lab, self.every, self.compare_every, self.kw = start, lab, int(every), int(compare_every), kw
        self._parts: list[WindowSet] = []
        self._since, self._since_compare = 0, 0
        self._cross_axis: bool | None = None  # verdict of the last comparison
        self.decision = OrderDecision("none", "no quasi-static windows yet: nothing is determined", {"n_windows": 0})

    @property
    def windows(self) -> WindowSet:
        if len(self._parts) > 1:
            self._parts = [WindowSet(*(np.concatenate([getattr(p, f) for p in self._parts]) for f in
                                       ("mean", "cov", "n", "t", "aux", "start", "end")))]
        return self._parts[0] if self._parts else WindowSet.from_points(np.zeros((0, 3)), 1.0)

    def update(self, window: Window | WindowSet) -> OrderDecision:
        """Add one window (or several) and return the current decision."""
        ws = WindowSet.from_windows([window]) if isinstance(window, Window) else window
        if len(ws) == 0:
            return self.decision
        if self._parts and ws.aux.shape[1] != self._parts[0].aux.shape[1]:
            ws = WindowSet(ws.mean, ws.cov, ws.n, ws.t, np.zeros((len(ws), self._parts[0].aux.shape[1])), ws.start, ws.end)
        self._parts.append(ws)
        self._since += len(ws)
        self._since_compare += len(ws)
        if self._since < self.every:
            return self.decision
        self._since = 0
        compare = self._since_compare >= self.compare_every or self._cross_axis is None
        d = select_order(self.windows, start=self.start, lab=self.lab, compare=compare, **self.kw)
        if compare and "comparison" in d.evidence:
            self._cross_axis = d.model in ("9", "12")
            self._since_compare = 0
        elif d.model in ("9", "12") and self._cross_axis is False:
            d = OrderDecision("6", d.reason + "; cross-axis terms held back (last comparison preferred 6)",
                              d.evidence)
        self.decision = d
        return d


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
    from .extended import ExtendedParameterization, parameterization  # noqa: PLC0415

    par = parameterization(model, cal.sensitivity, cal.offset)
    if not isinstance(par, ExtendedParameterization):
        raise ValueError(f"{model!r} is not an extended model")
    p = _extended_params(par, cal)
    P = par.n_params
    bound = par.at_windows(ws)
    var0 = norm_noise_var(ws, cal)
    a, J = bound.accel_and_jacobian(p, ws.mean)
    h = np.linalg.norm(a, axis=1)
    B = np.einsum("mi,mip->mp", a / h[:, None], J)
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
    return {"n_params": P, "stat_mg": _mg(stat), "amplification": round(amp, 2) if math.isfinite(amp) else None,
            "predicted_mg": _mg(total), "extra_std": dict(zip(par.extra_names, std[len(par.base.names):].tolist())),
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
    from scipy.optimize import brentq  # noqa: PLC0415

    from .extended import fit_extended, parameterization  # noqa: PLC0415

    par = parameterization(model, start.sensitivity, start.offset)
    p0 = _extended_params(par, start) if p0 is None else p0
    var0 = norm_noise_var(ws, start)
    floor2 = 0.0 if sigma_floor_g is None else float(sigma_floor_g) ** 2
    fit = fit_extended(par, ws, p0, var0 + floor2)
    dof = len(ws) - par.n_params
    if sigma_floor_g is None and dof > 0 and fit.chi2 / dof > 1.0:
        r2 = fit.resid_g ** 2

        def excess(f2: float) -> float:
            return float(np.sum(r2 / np.maximum(var0 + f2, 1e-14)) - dof)

        hi = max(float(np.max(r2)), 1e-12) * 10
        floor2 = brentq(excess, 0.0, hi, xtol=1e-18, rtol=1e-10) if excess(hi) < 0 else hi
        fit = fit_extended(par, ws, fit.p, var0 + floor2)
    return fit, math.sqrt(floor2)


def compare_extended(ws: WindowSet, base: str, model: str, start: Calibration, *, lab: Calibration | None = None,
                     sigma_floor_g: float = SIGMA_FLOOR_G, folds: int = 5) -> dict[str, dict[str, Any]]:
    """The evidence for an extended model against its base, as compare_orders does for 6 vs the full set:
    both fitted (iterated eq. 11a) with the same fixed per-window weights, BIC on the chi² (scaled by the
    larger model's reduced chi² when > 1), and k-fold held-out RMS norm error [mg] (time-contiguous folds:
    with a temperature ramp a fold is a temperature range the fit has not seen)."""
    from .extended import extended_residuals_g, fit_extended, parameterization  # noqa: PLC0415

    ref = _reference_start(base, start, lab)
    m = len(ws)
    var = norm_noise_var(ws, start, sigma_floor_g=sigma_floor_g)
    pars = {k: parameterization(k, ref.sensitivity, ref.offset) for k in (base, model)}
    fits = {k: fit_extended(par, ws, par.pack(start.sensitivity, start.offset), var) for k, par in pars.items()}
    Pm = pars[model].n_params
    scale = max(1.0, fits[model].chi2 / max(m - Pm, 1))
    order = np.argsort(ws.t, kind="stable")
    k_folds = min(folds, m // max(2 * Pm, 1))
    out: dict[str, dict[str, Any]] = {}
    for k, fit in fits.items():
        P = pars[k].n_params
        entry: dict[str, Any] = {"n_params": P, "insample_rms_mg": round(float(np.sqrt(np.mean(fit.resid_g ** 2))) * 1e3, 4),
                                 "bic": round(fit.chi2 / scale + P * math.log(m), 3), "heldout_rms_mg": None}
        if k_folds >= 2:
            held = np.empty(m)
            for idx in np.array_split(order, k_folds):
                train = np.setdiff1d(order, idx)
                f = fit_extended(pars[k], ws.subset(train), fit.p, var[train])
                held[idx] = extended_residuals_g(pars[k], f.p, ws.subset(idx))
            if np.all(np.isfinite(held)):
                entry["heldout_rms_mg"] = round(float(np.sqrt(np.mean(held * held))) * 1e3, 4)
        out[k] = entry
    return out
