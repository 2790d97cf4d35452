"""diagnose's term magnitudes scored against the truth of sessions gravcal's simulator did not make.

One function per session (``session_z``): a session of tests/support/independent_sessions.py with one planted
term is diagnosed with that term as the only candidate (the model holds: what a stated std can promise), and
the term's magnitude per axis is scored as z = (value - truth) / std in its report units (mg/°C, %/°C, mg/h,
%/h, mg/V, 1/g; the misalignment angles in degrees from orthogonal) when the term is named (reported as
found or as explaining part of an unexplained residual: what a user reads). A session diagnose refuses, or
where the term is not named, is counted, not scored (the planted terms are mostly far above the detection
floor, so the conditioning on being named is weak; docs/coverage.md). tests/core/test_diagnose_coverage.py asserts
on the z; bench/bench_coverage.py --diagnose prints the table.
"""
from __future__ import annotations

import numpy as np
from gravcal.core.diagnosis import diagnose_windows
from gravcal.core.estimators.lotters import LottersBatch

from .coverage_runs import TERMS
from .independent_sessions import session

KIND_TERM = {"misaligned": "misalignment", **{t: t for t in TERMS}}
"""Session kind -> the term it plants (the kinds diagnose is scored on)."""
DIAGNOSE_KINDS = tuple(KIND_TERM)


def session_z(kind: str, seed: int) -> dict[str, list[float]]:
    """{term: z per determined axis} of one session, or {"refused": [1]} / {"not_found": [1]}."""
    s = session(kind, seed)
    term = KIND_TERM[kind]
    try:
        start = LottersBatch("6").fit(s.windows)
        idx = [start.param_names.index(f"s_{a}") for a in "xyz"]
        held = {"names": [f"s_{a}" for a in "xyz"], "cov": start.covariance[np.ix_(idx, idx)].tolist(),
                "source": "the 6-parameter start fit"}  # what an offsets-only baseline holds, as uncertain as stated
        d = diagnose_windows(s.windows, start, has_temp=True, candidates=(term,), simulate=False, nested=False,
                             held_uncertainty=held)
    except ValueError:
        return {"refused": [1.0]}
    tt = next(t for t in d.tests if t.effect == term)
    if tt.status != "found":
        return {"not_found": [1.0]}
    mag = tt.magnitude  # the finding's (the same dict)
    # a baseline holding the sensitivities (offsets only) or a term holding an axis at 0 is another regime:
    # scored apart (what the fit holds is not in the statistical std)
    regime = "" if d.base_model == "6" and not tt.undetermined_axes else "|held"  # held sensitivities or an axis
    truth = s.truth.misalignment_deg() if term == "misalignment" else dict(zip("xyz", s.truth.term_magnitudes()[term]))
    return {term + regime: [(mag["value"][k] - v) / mag["std"][k] for k, v in truth.items()
                   if mag["value"].get(k) is not None and mag["std"].get(k)]}
