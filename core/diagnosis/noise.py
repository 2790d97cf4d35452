"""Noise of static stretches: Allan deviation, colored noise, quantization, idle-sleep repeats.

All functions take raw samples already converted to g per axis (diagonal of the fitted K), so
numbers are in g / mg. Tests follow the rule stated in core/diagnosis/terms.py: a term is
FOUND when the information criterion prefers it by more than ``DELTA_BIC`` (Kass & Raftery's
"strong evidence", 2 ln B > 10) AND it predicts held-out data better.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.special import ndtr

from gravcal.core.repeats import FlatStretches, flat_stretches  # noqa: F401 (idle-sleep repeats, numpy only)

DELTA_BIC = 10.0  # "strong" evidence (2 ln Bayes factor > 10, Kass & Raftery 1995)
MIN_STRETCH_SAMPLES = 64


# -- Allan deviation -------------------------------------------------------------------------------
def allan_variance(x: np.ndarray, fs: float, m_list: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Overlapping Allan variance of x (N,) [unit²] at cluster sizes m (samples); returns (tau [s], avar).
    Entries with too few clusters (< 2) are NaN."""
    x = np.asarray(x, dtype=float)
    c = np.concatenate([[0.0], np.cumsum(x - x.mean())])
    out = np.full(len(m_list), np.nan)
    n = x.size
    for k, m in enumerate(m_list):
        m = int(m)
        if 2 * m >= n:
            continue
        avg = (c[m:] - c[:-m]) / m  # moving means of length m
        d = avg[m:] - avg[:-m]
        out[k] = 0.5 * float(np.mean(d * d))
    return np.asarray(m_list, dtype=float) / fs, out


@dataclass
class AllanResult:
    tau_s: np.ndarray  # (L,)
    adev_g: np.ndarray  # (L, 3) pooled over stretches, per axis [g]
    n_clusters: np.ndarray  # (L,) effective number of independent clusters (for the uncertainty)
    white_g: np.ndarray  # (3,) per-sample white std [g] (from the shortest tau)

    def to_dict(self) -> dict[str, Any]:
        return {"tau_s": self.tau_s.tolist(), "adev_mg": (self.adev_g * 1e3).tolist(),
                "white_sample_std_mg": (self.white_g * 1e3).tolist()}


def pooled_allan(stretches: list[np.ndarray], fs: float, n_tau: int = 16) -> AllanResult | None:
    """Allan deviation pooled over static stretches (each (n_i, 3) [g]); None when none is long enough."""
    stretches = [s for s in stretches if s.shape[0] >= MIN_STRETCH_SAMPLES]
    if not stretches:
        return None
    longest = max(s.shape[0] for s in stretches)
    m_list = np.unique(np.round(np.logspace(0, math.log10(max(longest // 3, 2)), n_tau)).astype(int))
    num = np.zeros((len(m_list), 3))
    den = np.zeros(len(m_list))
    for s in stretches:
        for ax in range(3):
            tau, av = allan_variance(s[:, ax], fs, m_list)
            ok = np.isfinite(av)
            w = np.where(ok, s.shape[0] / m_list, 0.0)  # ~ number of clusters
            num[:, ax] += np.where(ok, av, 0.0) * w
        den += np.where(np.isfinite(av), s.shape[0] / m_list, 0.0)
    keep = den > 0
    adev = np.sqrt(num[keep] / den[keep][:, None])
    tau = m_list[keep] / fs
    return AllanResult(tau, adev, den[keep], adev[0] * math.sqrt(float(m_list[keep][0])))


# -- colored noise: white-only vs white + bias instability + random walk on the Allan variance ------
def _avar_design(tau: np.ndarray, colored: bool) -> np.ndarray:
    cols = [1.0 / tau]  # white: sigma² / (fs tau) -> coefficient q_w / tau
    if colored:
        cols += [np.ones_like(tau), tau]  # flicker floor (B² 2 ln 2 / pi), rate random walk (K² tau / 3)
    return np.column_stack(cols)


def _nnls_fit(A: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    from scipy.optimize import nnls

    sw = np.sqrt(w)
    return nnls(A * sw[:, None], y * sw)[0]


def colored_noise_test(train: AllanResult, test: AllanResult | None) -> dict[str, Any]:
    """Does the Allan variance need more than white noise? Weighted LS on AVAR with relative error
    sqrt(2 / n_clusters) (chi² ~ -2 log L up to a constant), BIC with 2 extra parameters per axis,
    held-out: the AVAR of ``test`` stretches predicted by each model fitted on ``train``."""
    tau = train.tau_s
    out: dict[str, Any] = {"axes": []}
    d_bic_tot, held_white, held_col = 0.0, 0.0, 0.0
    n_tot = 0
    bias_inst = np.zeros(3)
    rate_walk = np.zeros(3)
    for ax in range(3):
        y = train.adev_g[:, ax] ** 2
        w = train.n_clusters / 2.0 / np.maximum(y, 1e-30) ** 2  # var(AVAR_hat) ~ 2 AVAR² / n
        fits = {}
        for colored in (False, True):
            A = _avar_design(tau, colored)
            c = _nnls_fit(A, y, w)
            chi2 = float(np.sum(w * (A @ c - y) ** 2))
            fits[colored] = (c, chi2)
        n = len(tau)
        d_bic = (fits[False][1] - fits[True][1]) - 2 * math.log(n)
        d_bic_tot += d_bic
        n_tot += n
        c_col = fits[True][0]
        bias_inst[ax] = math.sqrt(max(c_col[1], 0.0) * math.pi / (2 * math.log(2)))  # B from the flat AVAR part
        rate_walk[ax] = math.sqrt(max(c_col[2], 0.0) * 3.0)  # K from AVAR = K² tau / 3
        if test is not None and len(test.tau_s):
            yt = test.adev_g[:, ax] ** 2
            wt = test.n_clusters / 2.0 / np.maximum(yt, 1e-30) ** 2
            for colored in (False, True):
                pred = _avar_design(test.tau_s, colored) @ fits[colored][0]
                e = float(np.sum(wt * (pred - yt) ** 2))
                if colored:
                    held_col += e
                else:
                    held_white += e
        out["axes"].append({"delta_bic": round(d_bic, 2), "bias_instability_mg": round(bias_inst[ax] * 1e3, 5),
                            "random_walk_mg_per_sqrt_s": round(rate_walk[ax] * 1e3, 6)})
    out["delta_bic"] = round(d_bic_tot, 2)
    out["heldout_chi2_white"] = round(held_white, 3) if test is not None else None
    out["heldout_chi2_colored"] = round(held_col, 3) if test is not None else None
    better_held = test is not None and held_col < held_white
    out["found"] = bool(d_bic_tot > DELTA_BIC and better_held)
    out["bias_instability_mg"] = (bias_inst * 1e3).round(5).tolist()
    out["random_walk_mg_per_sqrt_s"] = (rate_walk * 1e3).round(6).tolist()
    return out


# -- quantization ---------------------------------------------------------------------------------
def lsb_of(x: np.ndarray) -> float:
    """Quantisation step of x (smallest spacing that all values sit on), 0 when continuous."""
    u = np.unique(np.asarray(x, dtype=float))
    if u.size < 2:
        return 0.0
    step = float(np.min(np.diff(u)))
    if step <= 0:
        return 0.0
    # Every value a whole number of steps from the lowest, to within the values' rounding (a few units in the
    # last place of the largest): a grid. The step is refined over the whole span, so its own rounding does not
    # grow with the number of steps; a tolerance growing with that number would pass any continuous data once
    # the smallest of many gaps makes the steps many.
    n_steps = round(float(u[-1] - u[0]) / step)
    fine = float(u[-1] - u[0]) / n_steps
    k = (u - u[0]) / fine
    rounding = 8.0 * (float(np.spacing(max(abs(u[0]), abs(u[-1])))) / fine + np.finfo(float).eps * n_steps)
    if rounding < 0.01 and np.all(np.abs(k - np.round(k)) <= rounding):
        return step
    return 0.0


def quantization_test(stretches_raw: list[np.ndarray], scale: np.ndarray) -> dict[str, Any]:
    """Gaussian vs quantised-Gaussian likelihood of static samples (mean removed per stretch).

    Model A: x continuous N(mu, s²) (density x lsb as the bin probability); model B: x = Q(y),
    y ~ N(mu, s²), bin probability Phi((x + lsb/2 - mu)/s) - Phi((x - lsb/2 - mu)/s). B has one
    more parameter (lsb); BIC decides, held-out: B fitted on the earlier half of the stretches, scored on the later.
    ``scale`` (3,) raw units per g, to report the step in mg.
    """
    res: dict[str, Any] = {"axes": [], "found": False}
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
        distinct = [_distinct(v) for v in parts]
        pool = _pooled(distinct)
        s_a, s_b = _best_s(pool, lsb)
        la = _loglik_continuous(pool, s_a, lsb)
        lb = _loglik_quantised(pool, s_b, lsb)
        n = allv.size
        d_bic = 2 * (lb - la) - math.log(n)
        half = len(parts) // 2  # earlier stretches fit, later ones judge (contiguous in time)
        if half:
            early, late = _pooled(distinct[:half]), _pooled(distinct[half:])
            sa_e, sb_e = _best_s(early, lsb)
            held = _loglik_quantised(late, sb_e, lsb) - _loglik_continuous(late, sa_e, lsb)
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


@dataclass
class _Pooled:
    """Stretches of one axis as their distinct values: sample j of the pool is ``values[index[j]]``, so an
    elementwise function of the samples is the function of the few distinct values, gathered; stretch k's
    samples are ``index[bounds[k][0]:bounds[k][1]]``."""

    samples: list[np.ndarray]  # each stretch's samples (views)
    means: list[float]  # each stretch's mean (mu estimated per stretch)
    values: np.ndarray  # each stretch's distinct samples, sorted, the stretches concatenated
    mu: np.ndarray  # the mean of the stretch each distinct value belongs to
    index: np.ndarray  # (N,) each sample's position in ``values``
    bounds: list[tuple[int, int]]


def _distinct(v: np.ndarray) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """(samples, mean, distinct values, each sample's position among them) of one stretch."""
    values, index = np.unique(v, return_inverse=True)
    return v, float(v.mean()), values, index.reshape(-1)


def _pooled(stretches: list[tuple[np.ndarray, float, np.ndarray, np.ndarray]]) -> _Pooled:
    values, mu, index, bounds = [], [], [], []
    n_values = n_samples = 0
    for _, mean, vals, idx in stretches:
        values.append(vals)
        mu.append(np.full(vals.size, mean))
        index.append(idx + n_values)
        bounds.append((n_samples, n_samples + idx.size))
        n_values += vals.size
        n_samples += idx.size
    return _Pooled([st[0] for st in stretches], [st[1] for st in stretches], np.concatenate(values),
                   np.concatenate(mu), np.concatenate(index), bounds)


def _stretch_sums(per_sample: np.ndarray, pool: _Pooled) -> float:
    """Sum over the stretches of each stretch's sum of its samples' terms (each a numpy sum over that
    stretch's samples in their order: the float sums of the per-sample form)."""
    total = 0.0
    for a, b in pool.bounds:
        total += float(np.add.reduce(per_sample[a:b]))
    return total


def _loglik_continuous(pool: _Pooled, s: float, lsb: float) -> float:
    """Model A: sum of log(N(x; mu, s²) lsb) over the samples (the density times the bin width)."""
    z = (pool.values - pool.mu) / s
    return _stretch_sums((-0.5 * z * z - math.log(s * math.sqrt(2 * math.pi)) + math.log(lsb))[pool.index], pool)


def _loglik_quantised(pool: _Pooled, s: float, lsb: float) -> float:
    """Model B: sum of log P(bin of x) = log(Phi((x - mu + lsb/2)/s) - Phi((x - mu - lsb/2)/s)), the normal
    CDF evaluated once per distinct value."""
    p = ndtr((pool.values - pool.mu + lsb / 2) / s) - ndtr((pool.values - pool.mu - lsb / 2) / s)
    return _stretch_sums(np.log(np.maximum(p, 1e-300))[pool.index], pool)


def _best_s(pool: _Pooled, lsb: float) -> tuple[float, float]:
    """Continuous: ML s = sample std; quantised: latent s by a 1-D search (Sheppard: s² ~ var - lsb²/12)."""
    var = float(np.mean(np.concatenate([v - mu for v, mu in zip(pool.samples, pool.means)]) ** 2))
    s_a = math.sqrt(max(var, 1e-30))
    grid = s_a * np.linspace(0.05, 1.2, 47)
    lb = [_loglik_quantised(pool, g, lsb) for g in grid]
    return s_a, float(grid[int(np.argmax(lb))])
