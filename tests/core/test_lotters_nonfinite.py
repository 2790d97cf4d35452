"""LottersBatch from a start far off the windows' scale (sensitivity 1e150 x): the Gauss-Newton iterate
overflows, and that fit ends unconverged before its non-finite information reaches LAPACK's eigh (which
raises on some systems and may loop on others), so the retry from the ellipsoid start gives the fit; without
the retry the fit is refused (ValueError naming the overflow) or unconverged, never a calibration. Run in a
child process, so a hang fails by timeout."""
from __future__ import annotations

import json
import textwrap

import pytest

from tests.support.child import run_child

CHILD = textwrap.dedent("""
    import json, sys
    import numpy as np
    from gravcal.core.calibration import Calibration
    from gravcal.core.diagnosis.synthetic import window_session
    from gravcal.core.estimators.lotters import LottersBatch

    model = sys.argv[1]
    s = window_session(0, {}, n_windows=60)
    far = Calibration("6", s.start.offset, s.start.sensitivity * 1e150)
    with np.errstate(all="ignore"):
        got = LottersBatch(model).fit(s.ws, far)
        ref = LottersBatch(model).fit(s.ws, None)  # the ellipsoid start
        try:
            plain = LottersBatch(model, retry_from_ellipsoid=False).fit(s.ws, far)
            refused = "converged" if plain.converged else "unconverged"
        except ValueError as exc:
            refused = str(exc)
    print(json.dumps({"converged": got.converged, "ref_converged": ref.converged, "refused": refused,
                      "same": bool(np.array_equal(got.offset, ref.offset)
                                   and np.array_equal(got.sensitivity, ref.sensitivity))}))
""")


@pytest.mark.parametrize("model", ["6", "9", "6+temperature_offset"])
def test_a_start_that_overflows_the_fit_ends_it_unconverged_and_the_retry_fits(model):
    stdout = run_child(CHILD, model, timeout=120, what=f"LottersBatch({model!r}) from an overflowing start")
    r = json.loads(stdout)
    assert r["converged"] and r["ref_converged"] and r["same"]  # the retry's fit, bit for bit
    assert r["refused"] == "unconverged" or "overflowed to non-finite values" in r["refused"], r["refused"]
