"""diagnose's term magnitudes scored against the truth of sessions gravcal's simulator did not make.

One function per session (``session_z``): a session of tests/support/independent_sessions.py with one planted
term is diagnosed with that term as the only candidate (the model holds: what a stated std can promise), and
the term's magnitude per axis is scored as z = (value - truth) / std in its report units (mg/°C, %/°C, mg/h,
%/h, mg/V, 1/g; the misalignment angles in degrees from orthogonal).

Every session where the term is testable is scored, named or not: diagnose evaluates the term in the model
that contains it (base + term) in every session, and that estimate and std are what it states when the term is
named. Scored only where named, the kinds near the detection floor would be selected on a large |estimate|
(a winner's curse: |z| inflated with no fault in the std); scored in every session the z test the std itself,
and ``named`` records the selection apart (docs/coverage.md, "diagnose's magnitudes"). A session diagnose
refuses, or where the term is untestable, is counted, not scored. tests/core/test_diagnose_coverage.py asserts
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


def session_z(kind: str, seed: int) -> dict:
    """{"regime": "statistical" | "held", "named": bool, "z": [z per determined axis]} of one session, or
    {"regime": "refused"} / {"regime": "untestable"}. "statistical": a 6-parameter baseline, every base parameter
    and every axis of the term determined (the std is the fit's alone); "held": something held (the
    sensitivities of an offsets-only baseline, an undetermined base parameter or axis)."""
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
        return {"regime": "refused"}
    tt = next(t for t in d.tests if t.effect == term)
    mag = tt.magnitude
    if tt.status == "untestable" or not mag.get("std"):
        return {"regime": "untestable"}
    statistical = d.base_model == "6" and not tt.undetermined_axes and not d.undetermined
    truth = s.truth.misalignment_deg() if term == "misalignment" else dict(zip("xyz", s.truth.term_magnitudes()[term]))
    z = [(mag["value"][k] - v) / mag["std"][k] for k, v in truth.items()
         if mag["value"].get(k) is not None and mag["std"].get(k)]
    return {"regime": "statistical" if statistical else "held", "named": tt.status == "found", "z": z}
