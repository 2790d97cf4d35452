"""The work diagnosis shares or skips gives the numbers and the choices of the fits done in full.

TermSelector starts each held-out fold's fit from the all-window optimum and each lag time constant's fit
from the previous grid point's; both must converge to the optimum a fit from the baseline reaches (the fit's
own tolerance: relative cost change 1e-12, so the RMS agrees to far below 1e-6). The lagged covariate of a
recording's history is cached by the history's values and the time constant: a changed history or time
constant must not be served a stale lag. The stepwise selection computes held-out errors only where they can
change a decision (ΔBIC above the threshold; in decreasing ΔBIC until one candidate passes): its choices must be
those of the rule applied to every candidate fully evaluated.
"""
from __future__ import annotations

import numpy as np
import pytest

from gravcal.core.diagnosis.synthetic import PLANT, window_session
from gravcal.core.diagnosis.terms import TermSelector, lag_grid
from gravcal.core.estimators.extended import extended_residuals_g, fit_extended
from gravcal.core.estimators.lotters import LottersBatch
from gravcal.core.model.effect import LAG_KEY, lagged_deviations
from gravcal.core.model.lag import first_order_lag
from gravcal.core.model.terms import CALIBRATION_TERMS, calibration_view

LAGGED = next(t for t in CALIBRATION_TERMS if calibration_view(t).profiled is not None)
LINEAR = "temperature_offset"


def selector(seed: int, effects: dict[str, float]) -> TermSelector:
    s = window_session(seed, effects)
    base = LottersBatch("6").fit(s.ws, s.start)
    sel = TermSelector(s.ws, "6", base, has_temp=True)
    sel.var = sel.var0 + 1e-6  # a floor, as select_terms sets one
    return sel


def heldout_from_scratch(sel: TermSelector, terms: tuple[str, ...], n_params_max: int) -> float:
    """The held-out RMS [mg] with every fit started at the baseline (a lagged term: the grid on each fold)."""
    k = sel.n_folds(n_params_max)
    res = np.empty(sel.m)
    profiled = any(calibration_view(t).profiled is not None for t in terms)
    tau_all = sel.lag_tau_s
    for test in np.array_split(sel.order, k):
        train = np.setdiff1d(sel.order, test)
        best = None
        for tau in (lag_grid() if profiled else [tau_all]):
            sel.lag_tau_s = tau
            par = sel._new_par(terms)
            p0 = par.pack(sel.base_cal.sensitivity, sel.base_cal.offset)
            f = fit_extended(par, sel.ws.subset(train), p0, sel.var[train], free=sel.free_mask(par, {}))
            if best is None or f.chi2 < best[1].chi2:
                best = (par, f)
        sel.lag_tau_s = tau_all
        res[test] = extended_residuals_g(best[0], best[1].p, sel.ws.subset(test))
    return float(np.sqrt(np.mean(res * res)) * 1e3)


@pytest.mark.parametrize("seed", [3, 4])
@pytest.mark.parametrize("terms", [(LINEAR,), (LAGGED,), (LINEAR, LAGGED)])
def test_heldout_equals_the_fits_from_the_baseline(seed, terms):
    sel = selector(seed, {LINEAR: PLANT[LINEAR]})
    p_max = sel.par(terms).n_params
    sel.fit(terms, {})  # the all-window optimum the folds start from
    shared = sel.heldout_mg(terms, {}, p_max)
    scratch = heldout_from_scratch(sel, terms, p_max)
    base = heldout_from_scratch(sel, (), p_max)
    assert abs(shared - scratch) <= 1e-6 * scratch, (shared, scratch)
    assert abs(scratch - base) > 1e-3 * base  # the terms change the score: a comparison that can tell


def test_history_lag_is_recomputed_when_the_history_or_time_constant_changes():
    rng = np.random.default_rng(2)
    t = np.sort(rng.uniform(0, 3600, 120))
    temp = 25 + 5 * np.sin(t / 600) + rng.normal(0, 0.1, t.size)
    view = calibration_view(LAGGED)
    sub = np.arange(10, 60)

    def lagged(history, tau):
        refs = {LAG_KEY: tau, view.covariate: 25.0}
        return lagged_deviations((LAGGED,), {"time": t[sub], view.covariate: temp[sub]}, refs, sub.size,
                                 history)[view.deviation_key][:, 0]

    for tau in (120.0, 900.0):
        for _ in range(2):  # the second call is served from the cache
            assert np.array_equal(lagged((t, temp), tau), first_order_lag(t, temp, tau)[sub] - 25.0)
    changed = temp.copy()
    changed[:30] += 3.0
    assert np.array_equal(lagged((t, changed), 900.0), first_order_lag(t, changed, 900.0)[sub] - 25.0)
    temp[:30] += 3.0  # the same array changed in place
    assert np.array_equal(lagged((t, temp), 900.0), first_order_lag(t, temp, 900.0)[sub] - 25.0)


def fresh_selection(seed: int, effects: dict[str, float], report: bool):
    from gravcal.core.diagnosis.terms import select_terms
    from gravcal.core.estimators.observability import coverage

    sel = selector(seed, effects)
    sel.var = sel.var0
    return sel, select_terms(sel, CALIBRATION_TERMS, coverage(sel.ws, sel.base_cal)["spread_deg"], report=report)


@pytest.mark.parametrize("seed, effects", [(5, {LINEAR: PLANT[LINEAR]}),
                                           (6, {"offset_drift": PLANT["offset_drift"], "supply_offset": PLANT["supply_offset"]}),
                                           (7, {})])
def test_the_selection_without_its_report_chooses_the_same_terms(seed, effects):
    """The nested held-out error runs the selection without its report (held-out errors only where they decide)."""
    _, (chosen, held, tests) = fresh_selection(seed, effects, report=True)
    _, (chosen_v, held_v, tests_v) = fresh_selection(seed, effects, report=False)
    assert (chosen_v, held_v, tests_v) == (chosen, held, [])
    assert sorted(chosen) == sorted(effects)  # the planted terms: a selection that can tell


@pytest.mark.parametrize("seed", [8, 9])
def test_the_forward_step_takes_the_passing_candidate_of_largest_delta_bic(seed):
    """Held-out errors are computed in ΔBIC order until one passes; the pick is the rule's: of all candidates
    fully evaluated, the passing one of largest ΔBIC."""
    from gravcal.core.diagnosis.terms import _strongest_passing, evaluate_term, passes

    effects = {LINEAR: PLANT[LINEAR], "temperature_sensitivity": PLANT["temperature_sensitivity"],
               "offset_drift": PLANT["offset_drift"]}
    sel, _ = fresh_selection(seed, effects, report=False)
    held_all = {t: [] for t in CALIBRATION_TERMS}
    p_max = sel.par(CALIBRATION_TERMS).n_params
    chosen, held, picks = (), {}, []
    while True:
        remaining = [t for t in CALIBRATION_TERMS if t not in chosen]
        full = [evaluate_term(sel, chosen, held, t, held_all[t], p_max) for t in remaining]
        ok = [tt for tt in full if passes(tt)]
        rule = max(ok, key=lambda tt: tt.delta_bic).effect if ok else None
        got = _strongest_passing(sel, chosen, held, remaining, held_all, p_max)
        assert (None if got is None else got.effect) == rule, (chosen, [(tt.effect, tt.delta_bic) for tt in ok])
        if rule is None:
            break
        picks.append([tt.delta_bic for tt in ok])
        chosen, held = chosen + (rule,), {**held, rule: ["xyz".index(a) for a in got.undetermined_axes]}
    assert len(chosen) >= 2 and any(len(p) >= 2 for p in picks)  # the order among several passing ones was tested
