"""The calibration-level effect of registered terms: rows of the Lötters Jacobian and their application.

For a window (or sample) with covariates c, the extended model reads raw = K(c) a + o(c) with

    K(c) = K_ref + sum_p p * dK_p(c),   o(c) = o_ref + sum_p p * do_p(c)

(``core/model/spec.py`` says what each term's view adds). :func:`term_rows` builds the per-row
derivatives dK_p, do_p (eq. 13's Jacobian of an extended parameter is -K^-1 (dK_p a + do_p));
:func:`apply_terms` corrects raw samples at their own covariates, so a Calibration can apply every
term it carries without knowing which exist.
"""
from __future__ import annotations

from typing import Any, Iterator

import numpy as np

from .lag import first_order_lag
from .spec import COVARIATES, CROSS_PAIRS
from .terms import CALIBRATION_TERMS, calibration_view

LAG_KEY = "lag_tau_s"
"""Metadata / references key of the time constant [s] of the lagged terms."""


def default_lag_tau_s() -> float:
    """The registered default time constant of the lagged terms [s]."""
    return next((float(calibration_view(t).profiled) for t in CALIBRATION_TERMS
                 if calibration_view(t).profiled is not None), 0.0)


def references(meta: dict[str, Any]) -> dict[str, float]:
    """Covariate references of an extended calibration's metadata (defaults where absent), and the lag's
    time constant."""
    refs = {c.name: float(meta.get(c.ref_key, c.default_ref)) for c in COVARIATES.values() if c.ref_key}
    refs[LAG_KEY] = float(meta.get(LAG_KEY, default_lag_tau_s()))
    return refs


def lagged_deviations(terms: tuple[str, ...] | list[str], values: dict[str, np.ndarray | None],
                      refs: dict[str, float], n: int,
                      history: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """(n, 3) deviation of each lagged covariate the terms use: the covariate through a first-order lag of
    time constant refs[LAG_KEY] in time order (values["time"] [s]), minus its reference. ``history``
    (times [s], covariate values): a longer record the rows belong to, so that a subset of windows (a
    held-out fold) carries the lag built up before its first row instead of restarting it."""
    out = {}
    for term in terms:
        view = calibration_view(term)
        if not view.lagged or view.deviation_key in out:
            continue
        v, t = values.get(view.covariate), values.get("time")
        if v is None or t is None:
            raise ValueError(f"a lagged {COVARIATES[view.covariate].label} term needs the "
                             f"{COVARIATES[view.covariate].label} and the time of each row; not given")
        if history is not None:
            th_sorted, lag_sorted = _history_lag(history, refs[LAG_KEY])
            lag = np.interp(np.broadcast_to(np.asarray(t, dtype=float), (n,)), th_sorted, lag_sorted)
            z = lag - refs.get(view.covariate, COVARIATES[view.covariate].default_ref)
            out[view.deviation_key] = np.repeat(z[:, None], 3, axis=1)
            continue
        if n < 2:
            raise ValueError(f"a lagged {COVARIATES[view.covariate].label} term needs the history of the rows, "
                             f"not one row at a time (offline only)")
        x = np.broadcast_to(np.asarray(v, dtype=float), (n,))
        lag = first_order_lag(np.broadcast_to(np.asarray(t, dtype=float), (n,)), x, refs[LAG_KEY])
        z = lag - refs.get(view.covariate, COVARIATES[view.covariate].default_ref)
        out[view.deviation_key] = np.repeat(z[:, None], 3, axis=1)
    return out


_HISTORY_LAG_CACHE: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
_HISTORY_LAG_CACHE_SIZE = 256
_HISTORY_LAG_CACHE_MAX_ROWS = 20_000  # window-level histories


def _history_lag(history: tuple[np.ndarray, np.ndarray], tau_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(times, lagged covariate) of a history in time order. Cached: a diagnosis binds the same recording's
    history at the same few time constants for every fold and candidate, and the lag is a sequential loop."""
    th, xh = (np.asarray(a, dtype=float).ravel() for a in history)
    if th.size > _HISTORY_LAG_CACHE_MAX_ROWS:  # sample-level histories: too large to key a cache on
        o = np.argsort(th, kind="stable")
        return th[o], first_order_lag(th, xh, tau_s)[o]
    key = (float(tau_s), th.tobytes(), xh.tobytes())
    hit = _HISTORY_LAG_CACHE.get(key)
    if hit is None:
        o = np.argsort(th, kind="stable")
        hit = (th[o], first_order_lag(th, xh, tau_s)[o])
        for a in hit:
            a.setflags(write=False)
        if len(_HISTORY_LAG_CACHE) >= _HISTORY_LAG_CACHE_SIZE:
            _HISTORY_LAG_CACHE.pop(next(iter(_HISTORY_LAG_CACHE)))
        _HISTORY_LAG_CACHE[key] = hit
    return hit


def covariate_deviation(name: str, values: dict[str, np.ndarray | None], refs: dict[str, float],
                        accel_sq: np.ndarray | None, n: int) -> np.ndarray:
    """(n, 3) per-axis deviation z of covariate ``name`` from its reference: temp [°C], vsupply [V],
    time [h] (values["time"] in s), accel (diag K0 a0², given as ``accel_sq``)."""
    if name == "accel":
        if accel_sq is None:
            raise ValueError("the nonlinearity needs the reference acceleration of each row")
        return np.asarray(accel_sq, dtype=float).reshape(n, 3)
    v = values.get(name)
    if v is None:
        raise ValueError(f"needs the {COVARIATES[name].label} of each row [{COVARIATES[name].unit}]; none given")
    z = np.broadcast_to(np.asarray(v, dtype=float), (n,)) - refs.get(name, COVARIATES[name].default_ref)
    if name == "time":
        z = z / 3600.0
    return np.repeat(z[:, None], 3, axis=1)


def needed_covariates(terms: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """Covariates (by name, "accel" excluded: derived from the samples) the terms need."""
    out = []
    for t in terms:
        c = calibration_view(t).covariate
        if c is not None and c != "accel" and c not in out:
            out.append(c)
        if calibration_view(t).lagged and "time" not in out:
            out.append("time")  # the lag runs over the rows' times
    return tuple(out)


def constant_rows(terms: tuple[str, ...], n_base: int, n_params: int) -> tuple[np.ndarray, np.ndarray]:
    """dK (P, 3, 3), do (P, 3) of the extra parameters at the reference: only "cross" terms act there."""
    dK, do = np.zeros((n_params, 3, 3)), np.zeros((n_params, 3))
    k = n_base
    for term in terms:
        if calibration_view(term).acts_on == "cross":
            for m, (i, j) in enumerate(CROSS_PAIRS):
                dK[k + m, i, j] = dK[k + m, j, i] = 1.0
        k += 3
    return dK, do


def term_entries(terms: tuple[str, ...], n_base: int, deviations: dict[str, np.ndarray]
                 ) -> Iterator[tuple[int, bool, int, np.ndarray]]:
    """The entries of the extra parameters' derivative rows that depend on the row's covariates: (parameter
    index, on the offset (do) rather than the sensitivity (dK's diagonal), axis, the values (M,)), in parameter
    order; ``deviations`` as for :func:`term_rows`. Every other entry is the constant rows' (constant_rows)."""
    k = n_base
    for term in terms:
        view = calibration_view(term)
        if view.acts_on != "cross":
            z = deviations[view.deviation_key]
            for i in range(3):
                yield k + i, bool(view.on_offset), i, z[:, i]
        k += 3


def term_rows(terms: tuple[str, ...], n_base: int, dK: np.ndarray, do: np.ndarray,
              deviations: dict[str, np.ndarray]) -> None:
    """Fill the per-row derivatives dK (M, P, 3, 3), do (M, P, 3) of the extra parameters in place;
    ``deviations``: covariate name -> (M, 3) deviations from :func:`covariate_deviation`."""
    for q, on_offset, i, z in term_entries(terms, n_base, deviations):
        if on_offset:
            do[:, q, i] = z
        else:
            dK[:, q, i, i] = z


def apply_terms(K: np.ndarray, o: np.ndarray, terms: tuple[str, ...], extra: np.ndarray, raw: np.ndarray,
                covariates: dict[str, np.ndarray | None], refs: dict[str, float]) -> np.ndarray:
    """Calibrated acceleration [g] (N, 3) of raw samples under K, o at the reference plus the extra
    parameters ``extra`` (3 per term, in ``terms`` order) at each sample's covariates."""
    raw = np.asarray(raw, dtype=float).reshape(-1, 3)
    n = raw.shape[0]
    P = 3 * len(terms)
    # only the covariate-dependent rows: the cross-axis terms act at the reference, and K (the fit's K at the
    # reference, ExtendedFit.calibration) already holds them; adding their constant rows again doubled them
    dK = np.zeros((n, P, 3, 3))
    do = np.zeros((n, P, 3))
    Kinv = np.linalg.inv(K)
    accel_sq = None
    if any(calibration_view(t).covariate == "accel" for t in terms):
        a0 = (raw - o) @ Kinv.T
        accel_sq = np.abs(np.diag(K)) * a0 * a0
    devs = {c: covariate_deviation(c, covariates, refs, accel_sq, n)
            for c in {calibration_view(t).covariate for t in terms} - {None}}
    devs.update(lagged_deviations(terms, covariates, refs, n))
    term_rows(tuple(terms), 0, dK, do, devs)
    Kc = K[None] + np.einsum("p,npij->nij", extra, dK)
    oc = o[None] + np.einsum("p,npi->ni", extra, do)
    return np.linalg.solve(Kc, (raw - oc)[..., None])[..., 0]
