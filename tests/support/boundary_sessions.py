"""Independent sessions with a planted term at a chosen strength of evidence, and what diagnosis names on them.

The strength is the noncentrality λ: the chi² the 6-parameter baseline leaves on the session's noise-free
windows, with the windows' true variances (noise / n + residual motion²). A term test's Δchi² is then
noncentral chi²(3, λ) and its ΔBIC that minus 3 ln m, so P(ΔBIC > threshold) follows from λ alone. The planted
term is scaled per session (``independent_sessions.session(effect_scale=...)``, the same draws otherwise) to
give the requested λ. bench/bench_coverage.py --boundary reports the share named at the ΔBIC threshold and at
half of it, beside that prediction.
"""
from __future__ import annotations

import numpy as np
from gravcal.core.estimators.extended import fit_extended, parameterization

from .independent_sessions import session

NOISE_G, FLOOR_G = 0.004, 0.002  # independent_sessions.session's defaults


def noncentrality(kind: str, seed: int, effect_scale: float = 1.0) -> float:
    """λ of the session's planted term against the 6-parameter baseline (see the module docstring)."""
    s = session(kind, seed, noise_g=1e-9, floor_g=0.0, effect_scale=effect_scale)
    ws, tr = s.windows, s.truth
    var = NOISE_G**2 / ws.n + FLOOR_G**2
    K = np.diag(np.diag(tr.K))
    par = parameterization("6", K, tr.o)
    return float(fit_extended(par, ws, par.pack(K, tr.o), var).chi2)


def boundary_session(kind: str, seed: int, lam: float):
    """The session of ``kind`` with its planted term scaled to noncentrality ``lam``."""
    return session(kind, seed, effect_scale=float(np.sqrt(lam / noncentrality(kind, seed))))


def named_share(kind: str, seeds: range, lam: float, thresholds: tuple[float, ...]) -> dict:
    """Share of the sessions in which diagnosis (windows only, no simulation, no nested folds) names the planted
    term (and any other term: a false positive), at each ΔBIC threshold (set on the diagnosis module for the run and restored), with its ΔBIC."""
    from gravcal.core.diagnosis import terms as T  # noqa: PLC0415
    from gravcal.core.diagnosis.procedure import diagnose_windows  # noqa: PLC0415
    from gravcal.core.estimators.start import ellipsoid_fit  # noqa: PLC0415

    named = {t: [] for t in thresholds}
    other = {t: [] for t in thresholds}  # sessions where some other term is named (a false positive)
    dbic: list[float] = []
    dbic_any: list[float] = []  # every term test's ΔBIC (the planted term's and the others')
    saved = T.DELTA_BIC
    try:
        for seed in seeds:
            s = boundary_session(kind, seed, lam)
            for thr in thresholds:
                T.DELTA_BIC = thr
                try:
                    d = diagnose_windows(s.windows, ellipsoid_fit(s.windows), has_temp=True, simulate=False, nested=False)
                except ValueError:
                    continue
                found = [f["effect"] for f in d.findings]
                named[thr].append(kind in found)
                other[thr].append(any(e != kind for e in found))
                if thr == thresholds[0]:
                    dbic += [t.delta_bic for t in d.tests if t.effect == kind and t.delta_bic is not None]
                    dbic_any += [t.delta_bic for t in d.tests if t.delta_bic is not None]
    finally:
        T.DELTA_BIC = saved
    return {"named": {t: float(np.mean(v)) if v else float("nan") for t, v in named.items()},
            "other_named": {t: float(np.mean(v)) if v else float("nan") for t, v in other.items()},
            "sessions": {t: len(v) for t, v in named.items()}, "delta_bic_median": float(np.median(dbic)) if dbic else None,
            "delta_bic_max_any_term": float(np.max(dbic_any)) if dbic_any else None, "term_tests": len(dbic_any)}
