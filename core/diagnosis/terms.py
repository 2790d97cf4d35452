"""Name the cause: test catalogue terms against the window residuals.

Significance rule (stated once, used everywhere): a candidate term is FOUND when, added to the
current model,

1. it is observable: every axis kept has an effect std <= ``TOL_G`` (10 mg, order.TOL_G, the model-order
   rule) over the covered covariate range; axes that are not determined are held at 0 and named;
2. BIC prefers it by more than ``DELTA_BIC`` = 10 ("strong evidence"): chi²(M) - chi²(M+T) - k ln m > 10,
   chi² with the SAME per-window variances for every model (window noise + one quasi-static floor);
3. it lowers the held-out RMS norm error (time-contiguous folds: windows not used for the fit).

Selection is joint: forward, every remaining candidate is re-tested against the current extended
model and the strongest passing one enters; backward, each chosen term is re-tested given all the
others and leaves when it no longer passes. So of two terms that explain the same residual only the
better one is named, and a term that entered early but is explained by later ones is dropped. A term
whose columns the current model already spans is reported untestable ("indistinguishable from ...").
Axes a term cannot determine are null in its magnitude, with the reason, never 0.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import brentq

from gravcal.core.calibration import Calibration
from gravcal.core.crlb import h_variance
from gravcal.core.estimators.extended import (EXTRA_TERMS, ExtendedParameterization, extended_class,
                                              extended_residuals_g, fit_extended, model_name)
from gravcal.core.estimators.observability import TOL_G
from gravcal.core.model.datasheet import THERMAL_LAG_TAU_GRID_S
from gravcal.core.model.terms import calibration_view
from gravcal.core.estimators.parameterization import PARAMETERIZATIONS
from gravcal.core.windows import WindowSet

from .magnitude_std import held_axes_considered, t_widened_cov
from .noise import DELTA_BIC
from .term_reasons import axis_reasons, raw_unit, untestable_reason

CONFOUND_FRACTION = 0.02  # a column with < 2 % of its weighted norm outside the model's span is confounded


@dataclass
class TermTest:
    effect: str
    status: str  # "found" | "not_found" | "untestable"
    why: str = ""
    delta_bic: float | None = None
    heldout_before_mg: float | None = None
    heldout_after_mg: float | None = None
    magnitude: dict[str, Any] = field(default_factory=dict)
    undetermined_axes: list[str] = field(default_factory=list)

    def evidence(self) -> dict[str, Any]:
        return {"delta_bic": self.delta_bic, "delta_bic_threshold": DELTA_BIC,
                "heldout_rms_mg_without": self.heldout_before_mg, "heldout_rms_mg_with": self.heldout_after_mg,
                "undetermined_axes": self.undetermined_axes, "rule": "found = observable and ΔBIC > 10 and "
                "held-out RMS lower"}


def norm_var_g2(ws: WindowSet, cal: Calibration, floor_g: float) -> np.ndarray:
    """Per-window variance of h = |a| [g²]: delta method on cov/n plus floor²."""
    return h_variance(cal.apply_reference(ws.mean), np.linalg.inv(cal.sensitivity), ws.cov_of_mean) + floor_g**2


def floor_for(resid_g: np.ndarray, var0: np.ndarray, dof: int) -> float:
    """Quasi-static floor [g] making the reduced chi² of these residuals 1 (0 when already <= 1)."""
    r2 = resid_g**2
    if dof <= 0 or float(np.sum(r2 / var0)) <= dof:
        return 0.0
    f2 = brentq(lambda f2: float(np.sum(r2 / (var0 + f2))) - dof, 0.0, float(r2.max()) * 10 + 1e-18, xtol=1e-20)
    return math.sqrt(f2)


class TermSelector:
    """Fits and held-out scores of base + terms on one WindowSet with fixed weights."""

    def __init__(self, ws: WindowSet, base: str, base_cal: Calibration, *, has_temp: bool, folds: int = 5,
                 t_ref_c: float | None = None, t0_s: float | None = None, held_base: list[int] | None = None,
                 lag_history: tuple[np.ndarray, np.ndarray] | None = None):
        self.ws, self.base, self.base_cal, self.has_temp = ws, base, base_cal, has_temp
        # (t [s], temperature [°C]) a lagged term runs over: the inputs of every window of the recording, also
        # when these windows are one fold's training set (temperature is an input, known at every window)
        self.lag_history = lag_history if lag_history is not None else (
            (ws.t, ws.aux[:, 0]) if has_temp else None)
        self.m = len(ws)
        self.t_ref_c = float(np.median(ws.aux[:, 0])) if (has_temp and t_ref_c is None) else (t_ref_c or 25.0)
        self.t0_s = float(ws.t.min()) if t0_s is None else float(t0_s)
        supply = ws.covariate("vsupply")
        self.v_ref = float(np.median(supply)) if supply is not None and np.all(np.isfinite(supply)) else None
        self.var0 = norm_var_g2(ws, base_cal, 0.0)
        self.var = self.var0
        self.order = np.argsort(ws.t, kind="stable")
        self.folds = folds
        self.lag_tau_s: float | None = None  # a lagged term's time constant [s], set by profile_lag
        self.lag_profile: dict[str, Any] = {}
        self._heldout_memo: dict[tuple, float | None] = {}
        self._fit_memo: dict[tuple, tuple] = {}
        self._par_memo: dict[tuple, Any] = {}
        # what every fit of a model (or on a fold) recomputed: the windows' covariate rows, the start, the
        # free mask; the folds' index sets and windows; the confounding checks of the stepwise passes
        self._bound_memo: dict[tuple, Any] = {}
        self._p0_memo: dict[tuple, np.ndarray] = {}
        self._free_memo: dict[tuple, np.ndarray] = {}
        self._fold_memo: dict[int, list[tuple[np.ndarray, np.ndarray, WindowSet, WindowSet]]] = {}
        self._confounded_memo: dict[tuple, list[int]] = {}
        # base parameters these windows do not determine (e.g. the offsets across the axis of a single
        # posture) stay at base_cal: left free, they would let the fit turn the direction and hide a trend
        self.held_base: list[int] = list(held_base or [])
        self.judges_held_base = held_base is None
        par, f = self.fit((), {})
        self.var = self.var0 + floor_for(f.resid_g, self.var0, self.m - par.n_params) ** 2  # provisional floor
        if self.judges_held_base:
            self.hold_undetermined()

    def hold_undetermined(self) -> None:
        """Hold the worst-determined base parameter, one at a time, while one has a std above TOL_G at the current
        weights (a single posture determines one combination of the offsets: that one is kept)."""
        s = float(np.mean(np.abs(np.diag(self.base_cal.sensitivity))))
        n = self.par(()).n_params
        self.held_base = []
        while len(self.held_base) < n:
            _, f = self.fit((), {})
            rel = np.where(np.isin(np.arange(n), self.held_base), 0.0, f.std / s)
            if rel.max() <= TOL_G:
                break
            self.held_base.append(int(np.argmax(rel)))

    # -- model objects -----------------------------------------------------------------------------
    def par(self, terms: tuple[str, ...]):
        """The parameterization of base + ``terms`` at the current lag time constant (built once: every
        candidate test and held-out fold asks for the same few)."""
        key = (terms, self.lag_tau_s)
        if key not in self._par_memo:
            self._par_memo[key] = self._new_par(terms)
        return self._par_memo[key]

    def _new_par(self, terms: tuple[str, ...]):
        name = model_name(self.base, terms)
        K0, o0 = self.base_cal.sensitivity, self.base_cal.offset
        if not terms:
            return PARAMETERIZATIONS[self.base](K0, o0)
        kw = {} if self.v_ref is None else {"v_ref": self.v_ref}
        history = self.lag_history if self.has_temp else None
        return extended_class(name)(K0, o0, t_ref_c=self.t_ref_c, t0_s=self.t0_s, lag_tau_s=self.lag_tau_s,
                                    lag_history=history, **kw)

    def free_mask(self, par, held: dict[str, list[int]]) -> np.ndarray:
        free = np.ones(par.n_params, dtype=bool)
        free[self.held_base] = False
        if isinstance(par, ExtendedParameterization):
            k = par.base.n_params
            for term in par.terms:
                for i in held.get(term, []):
                    free[k + i] = False
                k += 3
        return free

    def fit(self, terms: tuple[str, ...], held: dict[str, list[int]]):
        """base + ``terms`` fitted on all windows (the same model is asked for by every candidate's test:
        fitted once)."""
        key = (terms, _held_key(terms, held), tuple(self.held_base), float(self.var.sum()), self.lag_tau_s)
        if key not in self._fit_memo:
            self._fit_memo[key] = self._fit(terms, held, None)
        return self._fit_memo[key]

    def _fit(self, terms: tuple[str, ...], held: dict[str, list[int]], fold: tuple[int, int] | None,
             p0: np.ndarray | None = None):
        """base + ``terms`` fitted on all windows (``fold`` None) or on the training windows of fold
        ``fold`` = (number of folds, which)."""
        par = self.par(terms)
        if fold is None:
            ws, var = self.ws, self.var
        else:
            train, _, ws, _ = self.fold_sets(fold[0])[fold[1]]
            var = self.var[train]
        free_key = (terms, self.lag_tau_s, _held_key(terms, held), tuple(self.held_base))
        if free_key not in self._free_memo:
            self._free_memo[free_key] = self.free_mask(par, held)
        return par, fit_extended(self.bound(terms, fold), ws, self.start(terms) if p0 is None else p0, var,
                                 free=self._free_memo[free_key])

    def start(self, terms: tuple[str, ...]) -> np.ndarray:
        """The parameters of base_cal in par(terms) (the terms without effect): every fit's default start."""
        key = (terms, self.lag_tau_s)
        if key not in self._p0_memo:
            self._p0_memo[key] = self.par(terms).pack(self.base_cal.sensitivity, self.base_cal.offset)
        return self._p0_memo[key]

    def bound(self, terms: tuple[str, ...], fold: tuple[int, int] | None = None):
        """par(terms) bound to the covariates of all windows or of fold ``fold``'s training windows (what
        fit_extended binds on every call; built once per model and window set)."""
        par = self.par(terms)
        if not isinstance(par, ExtendedParameterization):
            return par
        key = (terms, self.lag_tau_s, fold)
        if key not in self._bound_memo:
            if fold is None:
                self._bound_memo[key] = par.at_windows(self.ws)
            else:  # the all-window binding's rows sliced (equal to binding the fold's windows)
                train, _, ws, _ = self.fold_sets(fold[0])[fold[1]]
                self._bound_memo[key] = self.bound(terms).subset(train, ws)
        return self._bound_memo[key]

    def fold_sets(self, k: int) -> list[tuple[np.ndarray, np.ndarray, WindowSet, WindowSet]]:
        """(train indices, test indices, train windows, test windows) of the ``k`` time-contiguous folds."""
        if k not in self._fold_memo:
            out = []
            for test in np.array_split(self.order, k):
                train = np.setdiff1d(self.order, test)
                out.append((train, test, self.ws.subset(train), self.ws.subset(test)))
            self._fold_memo[k] = out
        return self._fold_memo[k]

    def n_folds(self, n_params: int) -> int:
        return int(min(self.folds, self.m // max(n_params, 1)))  # training folds keep >= (k-1)/k m >= P windows

    def heldout_mg(self, terms: tuple[str, ...], held: dict[str, list[int]], n_params_max: int) -> float | None:
        """RMS 1 - |a| [mg] over time-contiguous held-out folds (None: too few windows for 2 folds)."""
        key = (terms, _held_key(terms, held), n_params_max, tuple(self.held_base), float(self.var.sum()),
               self.lag_tau_s)
        if key not in self._heldout_memo:
            self._heldout_memo[key] = self._heldout_mg(terms, held, n_params_max)
        return self._heldout_memo[key]

    def _heldout_mg(self, terms: tuple[str, ...], held: dict[str, list[int]], n_params_max: int) -> float | None:
        k = self.n_folds(n_params_max)
        if k < 2:
            return None
        res = np.empty(self.m)
        profiled = any(calibration_view(t).profiled is not None for t in terms)
        tau_all = self.lag_tau_s
        # the all-window optimum as the folds' start: each fold converges to its own optimum (the fit's
        # tolerance), in fewer Gauss-Newton steps than from the baseline
        start = None
        if not profiled:
            try:
                whole = self.fit(terms, held)[1]
                start = whole.p if whole.converged else None
            except (ValueError, np.linalg.LinAlgError):
                pass
        try:
            for i, (_, test, _, wte) in enumerate(self.fold_sets(k)):
                try:
                    if profiled:  # the time constant is chosen on the training folds too: nothing seen of the test
                        par, f = min(self._grid_fits(terms, held, (k, i)), key=lambda pf: pf[1].chi2)
                        if par is None:  # no time constant of the grid could be fitted
                            return None
                    else:
                        par, f = self._fit(terms, held, (k, i), start)
                except (ValueError, np.linalg.LinAlgError):
                    return None
                if not profiled and isinstance(par, ExtendedParameterization):  # bound at the fit's time constant
                    par = self.bound(terms).subset(test, wte)
                res[test] = extended_residuals_g(par, f.p, wte)
        finally:
            self.lag_tau_s = tau_all
        return float(np.sqrt(np.mean(res * res)) * 1e3)

    def _grid_fits(self, terms: tuple[str, ...], held: dict[str, list[int]], fold: tuple[int, int]) -> list[tuple]:
        """(par, fit) of ``terms`` at each time constant of the lag grid on fold ``fold`` (a failed fit has
        chi2 inf). Each fit starts from the previous grid point's solution: neighbouring time constants have
        nearly the same optimum, so Gauss-Newton needs fewer steps to the same converged point."""
        out, p0 = [], None
        for tau in lag_grid():
            self.lag_tau_s = float(tau)
            try:
                par, f = self._fit(terms, held, fold, p0)
            except (ValueError, np.linalg.LinAlgError):
                out.append((None, type("Failed", (), {"chi2": math.inf})()))
                continue
            out.append((par, f))
            p0 = f.p if f.converged else None
        return out

    # -- observability of one term's axes -----------------------------------------------------------
    def effect_std_g(self, par, f, term: str) -> np.ndarray:
        """Std [g] of each axis' effect over the covered range of the term's covariate."""
        k = par.base.n_params + 3 * list(par.terms).index(term)
        view = calibration_view(term)
        values = self.ws.covariate(view.covariate) if view.covariate not in (None, "accel") else None
        span = 1.0 if values is None else float(np.ptp(values)) / (3600.0 if view.covariate == "time" else 1.0)
        return view.effect_std_g(f.std[k:k + 3], np.abs(np.diag(self.base_cal.sensitivity)), span)

    def confounded(self, terms: tuple[str, ...], held: dict[str, list[int]], term: str) -> list[int]:
        """Axes of ``term`` whose Jacobian column lies (almost) in the span of the current model's free columns."""
        key = (terms, _held_key(terms + (term,), held), term, tuple(self.held_base), float(self.var.sum()),
               self.lag_tau_s)
        if key not in self._confounded_memo:
            self._confounded_memo[key] = self._confounded(terms, held, term)
        return list(self._confounded_memo[key])

    def _confounded(self, terms: tuple[str, ...], held: dict[str, list[int]], term: str) -> list[int]:
        par = self.par(terms + (term,))
        _, B, _ = self.bound(terms + (term,)).norm_and_jacobian(self.start(terms + (term,)), self.ws.mean)
        w = 1.0 / np.sqrt(self.var)
        Bw = B * w[:, None]
        k = par.base.n_params + 3 * list(par.terms).index(term)
        free = self.free_mask(par, held)
        others = [j for j in range(par.n_params) if free[j] and not (k <= j < k + 3)]
        A = Bw[:, others]
        out = []
        for i in range(3):
            col = Bw[:, k + i]
            nc = np.linalg.norm(col)
            if nc == 0:
                out.append(i)
                continue
            r = col - A @ np.linalg.lstsq(A, col, rcond=None)[0]
            if np.linalg.norm(r) < CONFOUND_FRACTION * nc:
                out.append(i)
        return out


def evaluate_term(sel: TermSelector, chosen: tuple[str, ...], held: dict[str, list[int]], term: str,
                  unobservable: list[int], p_max: int, *, verdict_only: bool = False,
                  with_heldout: bool = True) -> TermTest:
    """``term`` added to the model ``chosen`` (held axes ``held``): ΔBIC, held-out error with and without,
    magnitudes on the determined axes (undetermined ones null, with the reason). ``verdict_only``: the
    held-out errors only where they can change the verdict (ΔBIC above the threshold); a term the ΔBIC
    already fails gets none (the cross-validated fits are most of the cost), so passes() is unchanged.
    ``with_heldout`` False: ΔBIC only (no verdict; the forward step ranks by it first)."""
    conf = sel.confounded(chosen, held, term)
    h = sorted(set(unobservable) | set(conf))
    reasons = axis_reasons(sel, chosen, term, unobservable, conf)
    if len(h) == 3:
        return TermTest(term, "untestable", "indistinguishable from " + (", ".join(chosen) if chosen else
                        "the base parameters") + " with these windows (orientations / covariates)",
                        undetermined_axes=list("xyz"), magnitude={"undetermined": reasons})
    hh = {**held, term: h}
    par_m, f_m = sel.fit(chosen, held)
    par_t, f_t = sel.fit(chosen + (term,), hh)
    # a profiled time constant is one more fitted parameter, chosen among the grid's values: a uniform prior
    # over them costs 2 ln(grid size) more (the search over the grid is a selection too)
    profiled = calibration_view(term).profiled is not None
    k_extra = (3 - len(h)) + profiled
    d_bic = (f_m.chi2 - f_t.chi2) - k_extra * math.log(sel.m) - (2 * math.log(LAG_GRID_POINTS) if profiled else 0.0)
    if not with_heldout or (verdict_only and not d_bic > DELTA_BIC):
        return TermTest(term, "not_found", f"ΔBIC {d_bic:.1f} <= {DELTA_BIC:g}" if with_heldout else
                        "held-out error not evaluated", round(d_bic, 2))
    ho_m = sel.heldout_mg(chosen, held, p_max)
    ho_t = sel.heldout_mg(chosen + (term,), hh, p_max)
    cov_t = t_widened_cov(sel, chosen + (term,), hh, f_t)
    if h:  # axes held at 0 are not 0 for being undetermined: the others' std as uncertain as freeing them makes it
        cov_t = held_axes_considered(sel, chosen + (term,), held, f_t, cov_t, k=par_t.base.n_params
                                     + 3 * list(par_t.terms).index(term), axes=h)
    mag = par_t.magnitudes(f_t.p, cov=cov_t)[term]  # the full covariance: J C J^T through the conversion
    keys = calibration_view(term).keys
    k = par_t.base.n_params + 3 * list(par_t.terms).index(term)
    mag["raw_value"] = {key: (None if i in h else float(f_t.p[k + i])) for i, key in enumerate(keys)}
    mag["raw_std"] = {key: (None if i in h else float(np.sqrt(max(cov_t[k + i, k + i], 0.0))))
                      for i, key in enumerate(keys)}
    mag["raw_unit"] = raw_unit(term)
    if calibration_view(term).convention:
        mag["convention"] = calibration_view(term).convention
    if calibration_view(term).profiled is not None and sel.lag_profile:
        mag["tau_s"] = dict(sel.lag_profile)
    for i in h:
        mag["value"][keys[i]] = None
        mag.get("std", {})[keys[i]] = None
    if reasons:
        mag["undetermined"] = reasons
    tt = TermTest(term, "not_found", "", round(d_bic, 2), _r(ho_m), _r(ho_t), mag, ["xyz"[i] for i in h])
    given = f" given {', '.join(chosen)}" if chosen else ""
    if ho_m is None or ho_t is None:
        tt.status = "untestable"
        tt.why = (f"{sel.m} windows are too few for held-out folds of the {p_max}-parameter model "
                  f"(need >= {2 * p_max}); ΔBIC alone {d_bic:.1f} is not enough by the rule")
    elif d_bic <= DELTA_BIC:
        tt.why = f"ΔBIC {d_bic:.1f} <= {DELTA_BIC:g}{given}"
    elif not ho_t < ho_m:
        tt.why = f"does not lower the held-out error{given} ({ho_m:.3f} -> {ho_t:.3f} mg)"
    return tt


LAG_GRID_POINTS = 15  # log-spaced over datasheet.THERMAL_LAG_TAU_GRID_S: about 1.5 steps per factor 2


def lag_grid() -> np.ndarray:
    """The time constants [s] a lagged term is profiled over."""
    return np.geomspace(*THERMAL_LAG_TAU_GRID_S, LAG_GRID_POINTS)


def profile_lag(sel: TermSelector, term: str) -> None:
    """Choose the lagged term's time constant: the grid value of least chi² of base + ``term`` (its
    coefficients fitted linearly at each tau). The interval is the grid points within Δchi² = 1 of the
    minimum (a profile-likelihood 68 % interval, at the grid's resolution)."""
    grid = lag_grid()
    chi2 = []
    for tau in grid:
        sel.lag_tau_s = float(tau)
        try:
            chi2.append(sel.fit((term,), {})[1].chi2)
        except (ValueError, np.linalg.LinAlgError):
            chi2.append(math.inf)
    chi2 = np.asarray(chi2)
    best = int(np.argmin(chi2))
    inside = grid[chi2 <= chi2[best] + 1.0]
    sel.lag_tau_s = float(grid[best])
    sel.lag_profile = {"value": round(float(grid[best]), 1), "interval_68": [round(float(inside.min()), 1),
                       round(float(inside.max()), 1)], "at_grid_edge": best in (0, len(grid) - 1),
                       "method": f"profile over {len(grid)} log-spaced values {grid[0]:g}-{grid[-1]:g} s, "
                                 f"interval Δchi² <= 1"}


def passes(tt: TermTest) -> bool:
    """The rule (module docstring): testable, ΔBIC > 10 and a lower held-out error."""
    return (tt.status != "untestable" and tt.delta_bic is not None and tt.delta_bic > DELTA_BIC
            and tt.heldout_before_mg is not None and tt.heldout_after_mg is not None
            and tt.heldout_after_mg < tt.heldout_before_mg)


def _strongest_passing(sel: TermSelector, chosen: tuple[str, ...], held: dict[str, list[int]], remaining: list[str],
                       held_all: dict[str, list[int]], p_max: int) -> TermTest | None:
    """The passing candidate of largest ΔBIC (the first in ``remaining`` order among equals), or None. The
    held-out errors are computed in decreasing ΔBIC order until one passes: the ones below it cannot change
    which enters."""
    ranked = [evaluate_term(sel, chosen, held, t, held_all[t], p_max, with_heldout=False) for t in remaining]
    ranked = [tt for tt in ranked if tt.status != "untestable" and tt.delta_bic is not None and tt.delta_bic > DELTA_BIC]
    for tt in sorted(ranked, key=lambda tt: -tt.delta_bic):  # stable: ties keep the candidates' order
        full = evaluate_term(sel, chosen, held, tt.effect, held_all[tt.effect], p_max)
        if passes(full):
            return full
    return None



def _floor_and_axes(sel: TermSelector, testable: list[str], tests: dict[str, TermTest]
                    ) -> tuple[dict[str, list[int]], list[str], int]:
    """One floor for every model, from the largest model (base + all testable terms, determined axes), set on
    ``sel``; returns each term's undetermined axes, the terms with one determined and the largest model's size."""
    held_all: dict[str, list[int]] = {t: [] for t in testable}
    provisional = sel.var
    for term in testable:  # each term on its own with the base: hold its worst-determined axis until the rest are
        # its std judged with the floor of the model that contains it: the baseline's floor carries the very misfit
        # the term explains, and would hold a determined axis at 0 (a misalignment angle on a training fold). Not
        # with an offsets-only baseline (one posture): there an axis across gravity is "determined" only through
        # the tilt of the held offsets, and the baseline's floor keeps it held
        if sel.base != "offsets":
            par, f = sel.fit((term,), {})
            sel.var = sel.var0 + floor_for(f.resid_g, sel.var0, sel.m - int(sel.free_mask(par, {}).sum())) ** 2
        while len(held_all[term]) < 3:
            par, f = sel.fit((term,), held_all)
            sd = np.where(np.isin(np.arange(3), held_all[term]), 0.0, np.nan_to_num(sel.effect_std_g(par, f, term),
                                                                                   nan=np.inf))
            if sd.max() <= TOL_G:
                break
            held_all[term].append(int(np.argmax(sd)))
    sel.var = provisional
    live = [t for t in testable if len(held_all[t]) < 3]
    for term in testable:
        if term not in live:
            tests[term] = TermTest(term, "untestable", f"not observable: effect std > {TOL_G * 1e3:.0f} mg on every "
                                                       f"axis with these windows", undetermined_axes=list("xyz"))
    p_max = sel.par(tuple(live)).n_params
    # the floor comes from the terms linear in their parameters: a profiled term's time constant is chosen on
    # these residuals, and adding it must not move every other term's verdict through the floor
    linear = tuple(t for t in live if calibration_view(t).profiled is None)
    if linear:
        par, f = sel.fit(linear, held_all)
        dof = sel.m - int(sel.free_mask(par, held_all).sum())
    else:
        par, f = sel.fit((), {})
        dof = sel.m - par.n_params
    floor = floor_for(f.resid_g, sel.var0, dof)
    sel.var = sel.var0 + floor**2
    sel.floor_g, sel.floor_dof = floor, dof
    return held_all, live, p_max


def _without(chosen: tuple[str, ...], held: dict[str, list[int]], term: str):
    return tuple(c for c in chosen if c != term), {k: v for k, v in held.items() if k != term}


def select_terms(sel: TermSelector, candidates: tuple[str, ...], spread_deg: float, *, report: bool = True
                 ) -> tuple[tuple[str, ...], dict[str, list[int]], list[TermTest]]:
    """Joint stepwise selection (module docstring). Returns (terms found, held axes, one TermTest per candidate;
    none when ``report`` is False: the selection alone, as the nested held-out error needs it).

    Forward: every remaining candidate is re-tested against the current model and the strongest passing one
    enters; backward: every chosen term is re-tested given all the others and leaves if it no longer passes.
    The final TermTests are those against the selected model: a found term given the other found terms,
    a term not found added to all of them."""
    tests: dict[str, TermTest] = {}
    testable = []
    for term in candidates:
        if term not in EXTRA_TERMS:
            continue
        why = untestable_reason(term, sel, spread_deg)
        if why:
            tests[term] = TermTest(term, "untestable", why)
        else:
            testable.append(term)
    for term in testable:
        if calibration_view(term).profiled is not None:
            profile_lag(sel, term)
    held_all, live, p_max = _floor_and_axes(sel, testable, tests)
    if sel.judges_held_base and sel.held_base and sel.base != "offsets":
        # which base parameters the windows do not determine was judged at the baseline's floor, which carries
        # the misfit the terms explain (a temperature offset makes a gain look undetermined; held at the
        # baseline's value, which absorbed part of the term, it biases the term and shrinks its std): judged
        # again at the floor of the terms' model with every base parameter free
        sel.held_base = []
        _floor_and_axes(sel, testable, tests)
        sel.hold_undetermined()
        held_all, live, p_max = _floor_and_axes(sel, testable, tests)
    chosen: tuple[str, ...] = ()
    held: dict[str, list[int]] = {}
    seen = {chosen}
    dropped: set[str] = set()
    for _ in range(2 * len(live) + 2):
        best = _strongest_passing(sel, chosen, held, [t for t in live if t not in chosen], held_all, p_max)
        changed = False
        if best is not None:
            chosen, held = chosen + (best.effect,), {**held, best.effect: ["xyz".index(a) for a in best.undetermined_axes]}
            changed = True
        for term in list(chosen):  # backward: each chosen term must still earn its place given the others
            others, held_o = _without(chosen, held, term)
            if not passes(evaluate_term(sel, others, held_o, term, held_all[term], p_max, verdict_only=True)):
                chosen, held = others, held_o
                dropped.add(term)
                changed = True
        if not changed or chosen in seen:
            break
        seen.add(chosen)
    if not report:
        return chosen, held, []
    for term in live:
        if term in chosen:
            others, held_o = _without(chosen, held, term)
            tt = evaluate_term(sel, others, held_o, term, held_all[term], p_max)
            tt.status, tt.why = "found", ""
        else:
            tt = evaluate_term(sel, chosen, held, term, held_all[term], p_max)
            if tt.status != "untestable" and term in dropped:
                tt.why = "left in the backward pass: " + (tt.why or "no longer earns its place given the others")
            elif tt.status != "untestable" and passes(tt):
                tt.why = "not selected: the selection stopped before it (it passes only given this final model)"
        tests[term] = tt
    ordered = [tests[t] for t in candidates if t in tests]
    return chosen, held, ordered


def _held_key(terms: tuple[str, ...], held: dict[str, list[int]]) -> tuple:
    """The held axes of ``terms`` as a hashable key (held axes of terms not in the model do not matter)."""
    return tuple(sorted((t, tuple(v)) for t, v in held.items() if t in terms))


def _r(x: float | None) -> float | None:
    return None if x is None else round(x, 4)
