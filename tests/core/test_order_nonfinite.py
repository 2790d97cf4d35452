"""The order and observability rules (select_order, is_observable, check_observable, the extended models'
rule, the coverage, fit_inuse through them) on windows holding a NaN/inf refuse them naming the windows,
instead of building an information or a scatter matrix from them for LAPACK's eigh (which raises on some
systems and may loop forever on others). The online calibrator's store never holds such a window; these
are the API entries. Run in a child process, so a hang fails by timeout."""
from __future__ import annotations

import json
import textwrap

import pytest

from tests.support.child import run_child

CHILD = textwrap.dedent("""
    import json, sys
    import numpy as np
    from gravcal.core.diagnosis.synthetic import window_session
    from gravcal.core.estimators.inuse12 import fit_inuse
    from gravcal.core.estimators.observability import check_observable, coverage, is_observable
    from gravcal.core.estimators.order import is_observable_extended, select_order
    from gravcal.core.model.terms import CALIBRATION_TERMS, calibration_view

    temp = next(t for t in CALIBRATION_TERMS if calibration_view(t).covariate == "temp")
    s = window_session(0, {}, n_windows=200)
    calls = {"select_order": lambda: select_order(s.ws, start=s.start).model,
             "is_observable": lambda: bool(is_observable(s.ws, s.start, "6")[0]),
             "check_observable": lambda: str(check_observable(s.ws, "6", s.start)),
             "is_observable_extended": lambda: bool(is_observable_extended(s.ws, s.start, "6+" + temp)[0]),
             "coverage": lambda: coverage(s.ws, s.start)["distinct_postures"],
             "fit_inuse": lambda: bool(fit_inuse(s.ws, "9").converged)}
    clean = {k: repr(f()) for k, f in calls.items()}
    s.ws.mean[5, 1] = {"nan": np.nan, "inf": np.inf}[sys.argv[1]]
    out = {}
    for k, f in calls.items():
        try:
            out[k] = "no error: " + repr(f())
        except ValueError as exc:
            out[k] = str(exc)
    print(json.dumps({"clean": clean, "bad": out}))
""")


@pytest.mark.parametrize("value", ["nan", "inf"])
def test_the_order_rules_refuse_nonfinite_windows_naming_them(value):
    stdout = run_child(CHILD, value, timeout=180, what=f"an order/observability rule on a window mean holding {value}")
    r = json.loads(stdout)
    assert len(r["bad"]) == 6 and all(v for v in r["clean"].values())
    for name, message in r["bad"].items():
        assert message == "1 window mean(s) are NaN/inf (windows [5])", (name, message)
