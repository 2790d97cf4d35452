"""Measured vs simulated: statistics that must agree if the model were right.

The session is re-simulated at window level with a fitted model (the calibration-level view of
the sensor model's terms, ``linear_part``/triad_truth: raw = K(T, t) a + o(T, t)): the same windows
(orientations = the fitted directions, times, temperatures, sample counts) and the noise measured
from the data (each window's own sample covariance / n, white). Each replica is refitted like the
measurement, so fitting effects are in both. For every statistic the p-value is the fraction of
replicas at least as extreme as the measurement ((k + 1) / (R + 1)).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.stats import ks_2samp

from gravcal.core.estimators.extended import ExtendedParameterization, extended_residuals_g, fit_extended
from gravcal.core.windows import WindowSet

P_DISAGREE = 0.05  # a statistic "disagrees" when the measurement is this unlikely (40 replicas: p >= 1/41)


def covariate_design(ws: WindowSet, dirs: np.ndarray, has_temp: bool) -> dict[str, np.ndarray]:
    """Regressors whose explained variance of the residual is compared (each with an intercept)."""
    d: dict[str, np.ndarray] = {"time": ws.t[:, None], "orientation": np.column_stack([dirs, dirs**2]),
                                "magnitude": np.max(np.abs(dirs), axis=1)[:, None]}
    if has_temp:
        d["temperature"] = ws.aux[:, :1]
    return d


def explained(r: np.ndarray, X: np.ndarray) -> float:
    """R² of r on [1, X]."""
    A = np.column_stack([np.ones(len(r)), X])
    if len(r) <= A.shape[1]:
        return float("nan")
    c = np.linalg.lstsq(A, r, rcond=None)[0]
    e = r - A @ c
    v = float(np.sum((r - r.mean()) ** 2))
    return float(1 - np.sum(e * e) / v) if v > 0 else 0.0


def statistics(r_g: np.ndarray, design: dict[str, np.ndarray]) -> dict[str, float]:
    out = {"rms_mg": float(np.sqrt(np.mean(r_g**2)) * 1e3)}
    for k, X in design.items():
        out[f"r2_{k}"] = explained(r_g, X)
    return out


@dataclass
class Comparison:
    measured: dict[str, float]
    simulated_mean: dict[str, float]
    simulated_p95: dict[str, float]
    p_value: dict[str, float]
    ks_p: float
    sim_residuals_g: np.ndarray  # pooled simulated residuals (for plots)

    def disagreements(self) -> list[str]:
        out = [k for k, p in self.p_value.items() if p <= P_DISAGREE]
        if self.ks_p <= P_DISAGREE:
            out.append("distribution")
        return out

    def to_dict(self) -> dict[str, Any]:
        f = lambda d: {k: (None if not np.isfinite(v) else round(float(v), 5)) for k, v in d.items()}  # noqa: E731
        return {"measured": f(self.measured), "simulated_mean": f(self.simulated_mean),
                "simulated_p95": f(self.simulated_p95), "p_value": f(self.p_value),
                "ks_p_value": round(float(self.ks_p), 6), "disagree": self.disagreements()}


def simulate_compare(par, p: np.ndarray, ws: WindowSet, var_g2: np.ndarray, resid_g: np.ndarray, *,
                     has_temp: bool, replicas: int = 40, seed: int = 0, free: np.ndarray | None = None) -> Comparison:
    """Compare the measured residuals with ``replicas`` window-level simulations of model (par, p)."""
    rng = np.random.default_rng(seed)
    par = getattr(par, "parent", par)
    bound = par.at_windows(ws) if isinstance(par, ExtendedParameterization) else par
    a, _ = bound.accel_and_jacobian(p, ws.mean)
    dirs = a / np.linalg.norm(a, axis=1, keepdims=True)
    if hasattr(bound, "rows_K_o"):
        K, o = bound.rows_K_o(p)
    else:
        K0, o0 = par.unpack(p)
        K, o = np.broadcast_to(K0, (len(ws), 3, 3)), np.broadcast_to(o0, (len(ws), 3))
    truth = np.einsum("mij,mj->mi", K, dirs) + o
    L = np.linalg.cholesky(ws.cov_of_mean + 1e-18 * np.eye(3))
    design = covariate_design(ws, dirs, has_temp)
    meas = statistics(resid_g, design)
    sims: list[dict[str, float]] = []
    pooled = []
    p0 = p.copy()
    for _ in range(replicas):
        m_sim = truth + np.einsum("mij,mj->mi", L, rng.standard_normal((len(ws), 3)))
        ws_s = WindowSet(m_sim, ws.cov, ws.n, ws.t, ws.aux, ws.start, ws.end)
        f = fit_extended(par, ws_s, p0, var_g2, free=free)
        r = extended_residuals_g(par, f.p, ws_s)
        pooled.append(r)
        sims.append(statistics(r, design))
    keys = list(meas)
    arr = {k: np.array([s[k] for s in sims]) for k in keys}
    pval = {k: float((np.sum(arr[k] >= meas[k]) + 1) / (replicas + 1)) for k in keys}
    pooled_r = np.concatenate(pooled)
    ks = float(ks_2samp(resid_g, pooled_r).pvalue)
    return Comparison(meas, {k: float(np.nanmean(v)) for k, v in arr.items()},
                      {k: float(np.nanpercentile(v, 95)) for k, v in arr.items()}, pval, ks, pooled_r)
