"""Faster forms in core/diagnosis against the plain forms they replace (kept here as the oracles): same
numbers, bit for bit.

quantization_test evaluates the two likelihoods per distinct sample value (quantised samples take few) and
gathers the per-sample terms, summed over the samples in their order as the plain form does; the plain form
evaluated every sample at every point of the noise-std search.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import ndtr

from gravcal.core.diagnosis.noise import (DELTA_BIC, _distinct, _loglik_continuous, _loglik_quantised, _pooled,
                                         lsb_of, quantization_test)
from gravcal.core.diagnosis.synthetic import PLANT, window_session
from gravcal.core.diagnosis.terms import TermSelector, lag_grid
from gravcal.core.estimators.extended import fit_extended
from gravcal.core.estimators.lotters import LottersBatch
from gravcal.core.model.terms import CALIBRATION_TERMS, calibration_view


def loglik_oracle(vals: list[np.ndarray], s: float, lsb: float) -> tuple[float, float]:
    """Continuous and quantised log-likelihoods of the stretches, every sample evaluated."""
    la, lb = 0.0, 0.0
    for v in vals:
        mu = float(v.mean())
        z = (v - mu) / s
        la += float(np.sum(-0.5 * z * z - math.log(s * math.sqrt(2 * math.pi)) + math.log(lsb)))
        p = ndtr((v - mu + lsb / 2) / s) - ndtr((v - mu - lsb / 2) / s)
        lb += float(np.sum(np.log(np.maximum(p, 1e-300))))
    return la, lb


def quantization_oracle(stretches_raw: list[np.ndarray], scale: np.ndarray) -> dict:
    """The per-sample form of noise.quantization_test."""
    res: dict = {"axes": [], "found": False}
    if not stretches_raw:
        res["why"] = "no static stretch"
        return res
    dbic_tot, held_gain_tot = 0.0, 0.0
    for ax in range(3):
        parts = [s[:, ax] for s in stretches_raw]
        allv = np.concatenate(parts)
        lsb = lsb_of(allv[: 200_000])
        if lsb == 0.0:
            res["axes"].append({"lsb_mg": 0.0, "delta_bic": None})
            continue

        def loglik(vals, s):
            return loglik_oracle(vals, s, lsb)

        def best_s(vals):
            var = float(np.mean(np.concatenate([v - v.mean() for v in vals]) ** 2))
            s_a = math.sqrt(max(var, 1e-30))
            grid = s_a * np.linspace(0.05, 1.2, 47)
            lb = [loglik(vals, g)[1] for g in grid]
            return s_a, float(grid[int(np.argmax(lb))])

        s_a, s_b = best_s(parts)
        la, _ = loglik(parts, s_a)
        _, lb = loglik(parts, s_b)
        d_bic = 2 * (lb - la) - math.log(allv.size)
        half = len(parts) // 2
        early, late = parts[:half], parts[half:]
        if early:
            sa_e, sb_e = best_s(early)
            held = loglik(late, sb_e)[1] - loglik(late, sa_e)[0]
        else:
            held = 0.0
        dbic_tot += d_bic
        held_gain_tot += held
        res["axes"].append({"lsb_raw": lsb, "lsb_mg": lsb / scale[ax] * 1e3, "noise_std_lsb": s_b / lsb,
                            "delta_bic": round(d_bic, 2), "heldout_loglik_gain": round(held, 2)})
    res["delta_bic"] = round(dbic_tot, 2)
    res["heldout_loglik_gain"] = round(held_gain_tot, 2)
    res["found"] = bool(dbic_tot > DELTA_BIC and held_gain_tot > 0)
    return res


def stretches(seed: int, noise_lsb: float, lsb: float, n_parts: int) -> list[np.ndarray]:
    """Static stretches of different lengths and levels on a grid of ``lsb`` (an axis may be continuous)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_parts):
        n = int(rng.integers(300, 5000))
        level = rng.integers(-500, 500, 3) + 0.3  # 0.3 step from a grid line: a latent std well inside the search
        x = np.round((level + rng.normal(0, noise_lsb * lsb, (n, 3))) / lsb) * lsb
        x[:, 2] = level[2] + rng.normal(0, 1.3, n)  # continuous
        out.append(x)
    return out


@pytest.mark.parametrize("seed,noise_lsb,lsb,n_parts", [(0, 0.35, 1.0, 4), (1, 4.0, 1.0, 4), (2, 0.6, 0.25, 1),
                                                        (3, 1.0, 2.0, 7), (4, 0.2, 1.0, 2), (7, 0.5, 1.0, 60)])
def test_quantization_test_equals_the_per_sample_form(seed, noise_lsb, lsb, n_parts):
    parts = stretches(seed, noise_lsb, lsb, n_parts)
    scale = np.array([100.0, 110.0, 95.0])
    fast, plain = quantization_test(parts, scale), quantization_oracle(parts, scale)
    assert fast == plain  # floats compared exactly
    assert fast["axes"][0]["lsb_raw"] == lsb and fast["axes"][0]["noise_std_lsb"] > 0


@pytest.mark.parametrize("seed", range(4))
def test_likelihoods_equal_the_per_sample_sums_bit_for_bit(seed):
    """The two log-likelihoods themselves (unrounded) at latent stds across the search range."""
    lsb = (1.0, 0.25, 2.0, 1.0)[seed]
    parts = [p[:, 0] for p in stretches(10 + seed, (0.3, 0.8, 2.0, 6.0)[seed], lsb, 3 + seed)]
    grids = _pooled([_distinct(v) for v in parts])
    for s in np.std(np.concatenate(parts)) * np.array([0.05, 0.3, 0.77, 1.0, 1.2]):
        la, lb = loglik_oracle(parts, float(s), lsb)
        assert (_loglik_continuous(grids, float(s), lsb), _loglik_quantised(grids, float(s), lsb)) == (la, lb)


def test_quantization_found_and_not_found_as_the_per_sample_form_says():
    coarse, fine = stretches(5, 0.3, 1.0, 4), stretches(6, 5.0, 1.0, 4)
    for parts, found in ((coarse, True), (fine, False)):
        r = quantization_test(parts, np.ones(3) * 100)
        assert r["found"] is found and r == quantization_oracle(parts, np.ones(3) * 100)


# -- TermSelector: the covariate rows, starts, free masks, fold windows and confounding checks it keeps --------
# (each built once per model and window set; a key that misses what the value depends on would serve a stale one)
def selector(seed: int, effects: dict[str, float]) -> TermSelector:
    s = window_session(seed, effects)
    sel = TermSelector(s.ws, "6", LottersBatch("6").fit(s.ws, s.start), has_temp=True)
    sel.var = sel.var0 + 1e-6
    return sel


def fit_afresh(sel, terms, held, train=None):
    """The plain form: the parameterization built, bound to the windows and started at the baseline anew."""
    par = sel._new_par(terms)
    ws, var = (sel.ws, sel.var) if train is None else (sel.ws.subset(train), sel.var[train])
    return fit_extended(par, ws, par.pack(sel.base_cal.sensitivity, sel.base_cal.offset), var,
                        free=sel.free_mask(par, held))


def same_fit(a, b) -> bool:
    return (np.array_equal(a.p, b.p) and np.array_equal(a.cov, b.cov) and a.chi2 == b.chi2
            and np.array_equal(a.resid_g, b.resid_g) and a.iterations == b.iterations)


def test_selector_fits_equal_the_fits_built_afresh_bit_for_bit():
    lagged = next(t for t in CALIBRATION_TERMS if calibration_view(t).profiled is not None)
    sel = selector(21, {"temperature_offset": PLANT["temperature_offset"], "offset_drift": PLANT["offset_drift"]})
    k = 5
    folds = [(np.setdiff1d(sel.order, test), test) for test in np.array_split(sel.order, k)]
    cases = [((), {}), (("temperature_offset",), {}), (("temperature_offset",), {"temperature_offset": [1]}),
             (("temperature_offset", "offset_drift"), {"offset_drift": [0, 2]}), ((lagged,), {})]
    for tau in (lag_grid()[2], lag_grid()[9]):  # a bound at one time constant must not serve another
        sel.lag_tau_s = float(tau)
        for terms, held in cases:  # the same model with other held axes: its own free mask
            assert same_fit(sel._fit(terms, held, None)[1], fit_afresh(sel, terms, held))
            for i, (train, test) in enumerate(folds):
                assert np.array_equal(sel.fold_sets(k)[i][0], train) and np.array_equal(sel.fold_sets(k)[i][1], test)
                assert same_fit(sel._fit(terms, held, (k, i))[1], fit_afresh(sel, terms, held, train))
    assert not same_fit(fit_afresh(sel, (lagged,), {}), fit_afresh(sel, ("temperature_offset",), {}))


def test_confounded_axes_follow_the_held_axes_and_the_weights():
    """A temperature rising linearly in time: temperature_offset is offset_drift's column on every axis it
    shares free with it."""
    sel = selector(22, {})
    sel.ws.aux[:, 0] = 25.0 + 2.0 * (sel.ws.t - sel.ws.t.min()) / 3600.0
    plain = type(sel)._confounded
    expected = {(): [0, 1, 2], (0, 1, 2): [], (2,): [0, 1], (0,): [1, 2]}  # held offset_drift axes -> confounded
    for var in (sel.var, sel.var0 * np.linspace(1.0, 100.0, sel.m)):
        sel.var = var
        for held_axes, axes in expected.items():
            held = {"offset_drift": list(held_axes)}
            terms = ("offset_drift",)
            got = sel.confounded(terms, held, "temperature_offset")
            assert got == plain(sel, terms, held, "temperature_offset") == axes, (held_axes, got)
        assert sel.confounded((), {}, "temperature_offset") == []  # without offset_drift: a column of its own
    # one window 0.3 °C off the line: within 2 % of the column at equal weights, far outside when it weighs 100 x
    j = sel.m // 2
    sel.ws.aux[j, 0] += 0.3
    sel._bound_memo.clear()  # the windows' covariates changed in place (a selector's windows never do)
    verdicts = []
    for var in (sel.var0 + 1e-6, np.where(np.arange(sel.m) == j, 0.01, 1.0) * (sel.var0 + 1e-6)):
        sel.var = var
        verdicts.append(sel.confounded(("offset_drift",), {}, "temperature_offset"))
        assert verdicts[-1] == plain(sel, ("offset_drift",), {}, "temperature_offset")
    assert verdicts == [[0, 1, 2], []]


# -- the seed pool's workers: one BLAS thread each, the same numbers as in this process ----------------------
def blas_threads(_task: int) -> list[int]:
    from threadpoolctl import threadpool_info

    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


def session_numbers(seed: int) -> tuple:
    from gravcal.core.diagnosis import diagnose_windows

    s = window_session(seed, {"temperature_offset": PLANT["temperature_offset"]})
    d = diagnose_windows(s.ws, s.start, has_temp=True, candidates=CALIBRATION_TERMS, simulate=False, nested=False)
    return (d.findings, d.selection_heldout_mg, d.floor_mg, d.resid_extended_g.tobytes(),
            [(t.effect, t.delta_bic, t.heldout_before_mg, t.heldout_after_mg) for t in d.tests])


def test_pool_workers_run_one_blas_thread_and_give_this_process_numbers(monkeypatch):
    from seed_pool import pmap

    # two workers on any machine (and under pytest-xdist), so the pool's own processes are what is checked
    monkeypatch.delenv("PYTEST_XDIST_WORKER", raising=False)
    monkeypatch.setenv("GRAVCAL_TEST_WORKERS", "2")
    in_workers = pmap(blas_threads, [(0,), (1,)])
    assert len(in_workers) == 2 and all(t and t == [1] * len(t) for t in in_workers), in_workers
    assert pmap(session_numbers, [(5,)]) == [session_numbers(5)]
