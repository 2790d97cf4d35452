"""gravcal's batch fit on the independent sessions, scored against their truth: (estimate - truth) / std.

One function per session (``session_z``) returns the z of every stated quantity by class (offsets,
sensitivities, cross-axis terms, misalignment angles, term magnitudes); ``pooled`` gathers them over
seeds. tests/core/test_coverage.py asserts on them; bench/bench_coverage.py prints the table.
"""
from __future__ import annotations

import math

import numpy as np
from gravcal.core.calibration import Calibration
from gravcal.core.estimators.consider import with_held_uncertainty
from gravcal.core.estimators.lotters import LottersBatch

from .independent_sessions import KINDS, Session, session

NOT_DETERMINED_STD_G = 0.03  # LottersBatch's max_std_g: a std above 3 % of 1 g is stated as "not determined"
TERMS = ("temperature_offset", "temperature_sensitivity", "offset_drift", "sensitivity_drift", "supply_offset",
         "nonlinearity")
QUANTITIES = ("offset", "sensitivity", "cross_axis", "misalignment_deg", *TERMS)
"""Scored classes: the parameters o, s (raw units) and the symmetric cross-axis terms m (raw), the misalignment
angles [deg] and each term's magnitude in its report units (mg/°C, %/°C, mg/h, %/h, mg/V, 1/g)."""


def fit(s: Session) -> Calibration:
    if s.kind == "offsets_held":
        start = Calibration("6", np.full(3, 2048.0), s.held_K)
        start = with_held_uncertainty(start, {f"s_{a}": s.held_rel_std * s.held_K[i, i] for i, a in enumerate("xyz")},
                                      source="previous calibration")
        return LottersBatch("offsets").fit(s.windows, start)
    return LottersBatch(s.model).fit(s.windows)


def _magnitude_z(cal: Calibration, term: str, truth: dict[str, float]) -> list[float]:
    mag = cal.metadata["extended"]["magnitudes"][term]
    return [(mag["value"][k] - v) / mag["std"][k] for k, v in truth.items()]


def session_z(kind: str, seed: int) -> dict[str, list[float]]:
    """z = (estimate - truth) / stated std of every quantity the fit of one session states, by class; a
    session the fit refuses or states as not converged / not determined (a std above 3 % of 1 g) is
    counted ({"refused": [1.0]} or {"flagged": [1.0]}), not scored. (A term's parameter above 3 % of 1 g per
    covariate unit is scored: its unit is per °C, per h or per V, and its std is stated all the same.)"""
    s = session(kind, seed)
    try:
        cal = fit(s)
    except ValueError:  # refused (e.g. too little orientation coverage): nothing stated, nothing to score
        return {"refused": [1.0]}
    base_std_g = [v for n, v in cal.metadata["std_g"].items() if n.split("_")[0] in ("s", "o", "m")]
    if not cal.converged or max(base_std_g) > NOT_DETERMINED_STD_G:
        return {"flagged": [1.0]}  # stated as not converged, or K, o not determined: its numbers are no claim
    std = cal.std
    est = {n: float(v) for n, v in cal.metadata["params"].items()}
    tr, S = s.truth, s.truth.S
    out: dict[str, list[float]] = {}

    def score(q: str, name: str, value: float) -> None:
        if name not in std:
            raise AssertionError(f"{kind} seed {seed}: the fit states no std for {name} (model {cal.model})")
        out.setdefault(q, []).append((est[name] - value) / std[name])

    nine = s.model == "9"  # K = S: s_xx ... on the diagonal, s_xy ... off it
    for i, a in enumerate("xyz"):
        score("offset", f"o_{a}", tr.o[i])
        if kind != "offsets_held":
            score("sensitivity", f"s_{a + a if nine else a}", S[i, i])
    if kind.startswith("misaligned"):
        for i, j in ((0, 1), (0, 2), (1, 2)):
            score("cross_axis", f"{'s' if nine else 'm'}_{'xyz'[i]}{'xyz'[j]}", S[i, j])
        angles = cal.metadata["misalignment_deg"] if nine else cal.metadata["extended"]["magnitudes"]["misalignment"]
        out["misalignment_deg"] = [(angles["value"][k] - v) / angles["std"][k] for k, v in tr.misalignment_deg().items()]
    if kind in TERMS:
        out[kind] = _magnitude_z(cal, kind, dict(zip("xyz", tr.term_magnitudes()[kind])))
    return out


def pooled(kinds: tuple[str, ...], seeds: range, mapper=None) -> dict[str, dict[str, np.ndarray]]:
    """{kind: {quantity: z array}} over ``seeds`` (``mapper``: a parallel map(fn, args), default a loop)."""
    args = [(k, s) for k in kinds for s in seeds]
    results = mapper(session_z, args) if mapper is not None else [session_z(*a) for a in args]
    out: dict[str, dict[str, list[float]]] = {k: {q: [] for q in (*QUANTITIES, "refused", "flagged")} for k in kinds}
    for (k, _), res in zip(args, results):
        for q, zs in res.items():
            out[k][q].extend(zs)
    return {k: {q: np.asarray(v) for q, v in d.items() if v} for k, d in out.items()}


def rms(z: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(z))))


def beyond_2sigma_bounds(n: int, alpha: float = 1e-3) -> tuple[int, int]:
    """Counts of |z| > 2 among n standard normal z that a two-sided test at level ``alpha`` accepts
    (binomial, p = P(|z| > 2) = 4.55 %)."""
    from scipy.stats import binom  # noqa: PLC0415

    p = math.erfc(2 / math.sqrt(2))
    return int(binom.ppf(alpha / 2, n, p)), int(binom.isf(alpha / 2, n, p))


def rms_bounds(n: int, alpha: float = 1e-3) -> tuple[float, float]:
    """RMS of n independent standard normal z accepted at level ``alpha``: sqrt(chi²_n quantiles / n)."""
    from scipy.stats import chi2  # noqa: PLC0415

    return math.sqrt(chi2.ppf(alpha / 2, n) / n), math.sqrt(chi2.isf(alpha / 2, n) / n)


__all__ = ["KINDS", "TERMS", "QUANTITIES", "fit", "session_z", "pooled", "rms", "beyond_2sigma_bounds", "rms_bounds"]
