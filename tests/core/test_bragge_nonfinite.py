"""Bragge's lab calibration on a NaN/inf input refuses it with a message naming what is not finite, instead of
handing the face clustering, eigvalsh or the SVD (LAPACK: raises on some systems, may loop forever on
others) a NaN. Run in a child process, so a hang fails by timeout."""
from __future__ import annotations

import textwrap

import pytest

from tests.support.child import run_child

CHILD = textwrap.dedent("""
    import sys
    import numpy as np
    from gravcal.core.estimators.bragge import bragge_fit, calibrate_faces, calibrate_lab
    from gravcal.core.samples import raw_triad
    from gravcal.core.simulate import simulate

    where = sys.argv[1]
    try:
        if where == "direction":
            d = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
            means = d * 0.04 + 0.5
            print("clean", np.isfinite(bragge_fit(d, means).offset).all())
            d[5, 2] = np.nan
            bragge_fit(d, means)
        else:
            sim = simulate("six_position", seed=5, duration=600.0, fs=100.0)
            ws = calibrate_lab(sim.samples["t"].astype(float), raw_triad(sim.samples), fs=100.0).windows
            print("clean", calibrate_faces(ws).calibration.converged)
            if where == "mean":
                ws.mean[2, 0] = np.nan
            else:
                ws.cov[2, 1, 1] = np.inf
            calibrate_faces(ws)
        print("no error")
    except ValueError as exc:
        print(exc)
""")


@pytest.mark.parametrize("where, named", [("mean", "1 window mean(s) are NaN/inf (windows [2])"),
                                          ("cov", "1 window covariance(s) are NaN/inf (windows [2])"),
                                          ("direction", "the directions hold NaN/inf values")])
def test_a_nonfinite_lab_input_is_refused_naming_it(where, named):
    stdout = run_child(CHILD, where, timeout=120, what=f"the lab calibration on a non-finite {where}")
    clean, message = stdout.strip().split("\n")
    assert clean == "clean True"  # the same input without the NaN/inf calibrates
    assert named in message, message
