"""What is left in a model's window residuals: structure along temperature, time or supply.

A model that describes the sensor leaves window residuals that are noise plus the quasi-static floor:
nothing a smooth function of a covariate predicts on held-out windows. Each candidate structure is an
offset-type shape along gravity, r_w ~ sum_k u_k f_j(c_w) (u the window's gravity direction, f_j
Legendre polynomials of the covariate scaled to [-1, 1]); it is PRESENT under the rule of the term
tests (terms.py): ΔBIC > 10 with the residuals' own floor, and a lower RMS on time-contiguous held-out
folds. The present structure of largest held-out gain is the one described ("residual vs temperature
is curved").
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.polynomial import legendre

from gravcal.core.windows import WindowSet

from .noise import DELTA_BIC

# (covariate, highest polynomial degree, words for the shape: first degree, higher degrees)
SHAPES: tuple[tuple[str, int, str, str], ...] = (
    ("temperature", 2, "rises or falls with temperature", "is curved"),
    ("temperature rate", 1, "follows the temperature's rate of change (a lag)", "is curved"),
    ("time", 4, "trends with time", "wanders in time"),
    ("supply", 1, "rises or falls with supply voltage", "is curved"),
)
FOLDS = 5


RATE_SPAN_S = 300.0  # the temperature's rate of change over this span [s] (window temperatures are noisy)


def temperature_rate(t: np.ndarray, T: np.ndarray) -> np.ndarray:
    """dT/dt [°C/h] at each window: the change of the windows' running-mean temperature over RATE_SPAN_S."""
    order = np.argsort(t, kind="stable")
    ts, Ts = t[order], T[order]
    half = RATE_SPAN_S / 2
    lo, hi = np.searchsorted(ts, ts - half), np.searchsorted(ts, ts + half, side="right")
    c = np.concatenate([[0.0], np.cumsum(Ts)])
    smooth = (c[hi] - c[lo]) / np.maximum(hi - lo, 1)
    rate = (np.interp(ts + half, ts, smooth) - np.interp(ts - half, ts, smooth)) / (
        np.minimum(ts + half, ts[-1]) - np.maximum(ts - half, ts[0]) + 1e-9) * 3600.0
    out = np.empty_like(rate)
    out[order] = rate
    return out


def _covariate(ws: WindowSet, name: str, has_temp: bool) -> np.ndarray | None:
    if name == "time":
        return ws.t
    if name == "temperature":
        return ws.aux[:, 0] if has_temp else None
    if name == "temperature rate":
        return temperature_rate(ws.t, ws.aux[:, 0]) if has_temp else None
    v = ws.covariate("vsupply")
    return v if v is not None and np.all(np.isfinite(v)) and np.ptp(v) > 0 else None


def design(u: np.ndarray, c: np.ndarray, degree: int) -> np.ndarray:
    """Columns u_k P_j(c) for j = 1..degree (c scaled to [-1, 1])."""
    x = 2 * (c - c.min()) / max(float(np.ptp(c)), 1e-12) - 1
    cols = [u[:, k] * legendre.legval(x, np.eye(degree + 1)[j]) for j in range(1, degree + 1) for k in range(3)]
    return np.column_stack(cols)


def _wls(X: np.ndarray, r: np.ndarray, w: np.ndarray) -> np.ndarray:
    return np.linalg.lstsq(X * w[:, None], r * w, rcond=None)[0]


def residual_structure(ws: WindowSet, resid_g: np.ndarray, u: np.ndarray, var_g2: np.ndarray, *,
                       has_temp: bool) -> tuple[list[dict[str, Any]], dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Every candidate structure with its ΔBIC, held-out gain [mg] and verdict (``present``), present ones
    first by held-out gain; and per covariate (its values, the structure's fitted residual [g]) for a plot.
    ``var_g2``: per-window variance of the residual (noise + floor); u (m, 3) the windows' gravity directions."""
    m = len(ws)
    order = np.argsort(ws.t, kind="stable")
    w = 1.0 / np.sqrt(var_g2)
    rms = lambda x: float(np.sqrt(np.mean(x * x)) * 1e3)  # noqa: E731
    out, curves = [], {}
    for name, top, first_words, curved_words in SHAPES:
        c = _covariate(ws, name, has_temp)
        if c is None or np.ptp(c) == 0:
            continue
        best = None
        for deg in range(1, top + 1):
            X = design(u, c, deg)
            if m < 4 * X.shape[1]:
                break
            coef = _wls(X, resid_g, w)
            fitted = X @ coef
            d_bic = float(np.sum((resid_g * w) ** 2) - np.sum(((resid_g - fitted) * w) ** 2)) - X.shape[1] * math.log(m)
            pred = np.empty(m)
            for test in np.array_split(order, FOLDS):
                train = np.setdiff1d(order, test)
                pred[test] = X[test] @ _wls(X[train], resid_g[train], w[train])
            gain = rms(resid_g) - rms(resid_g - pred)
            cand = {"covariate": name, "degree": deg, "delta_bic": round(d_bic, 2), "heldout_gain_mg": round(gain, 4),
                    "structure_rms_mg": round(rms(fitted), 4),
                    "shape": first_words if deg == 1 else curved_words,
                    "present": bool(d_bic > DELTA_BIC and gain > 0)}
            if best is None or (cand["present"] and (not best["present"] or gain > best["heldout_gain_mg"])):
                best, curves[name] = cand, (c, fitted)
        if best is not None:
            out.append(best)
    return sorted(out, key=lambda s: (not s["present"], -s["heldout_gain_mg"])), curves


def describe(s: dict[str, Any]) -> str:
    """'residual vs temperature is curved' (or the structure's own words)."""
    shape = s["shape"]
    text = f"residual {shape}" if shape.startswith(("rises", "trends", "wanders", "follows")) else \
        f"residual vs {s['covariate']} {shape}"
    if s.get("replaces"):  # standin.py: the shape fits better in place of chosen terms
        one = len(s["replaces"]) == 1
        text += (f", better than {' and '.join(s['replaces'])} in {'its' if one else 'their'} place (ΔBIC "
                 f"{s['delta_bic']:.0f}, held-out {s['heldout_with_term_mg']:.3g} -> {s['heldout_with_shape_mg']:.3g} "
                 f"mg): {'a stand-in, not a cause' if one else 'stand-ins, not causes'}")
    return text
