"""fit_extended on a window set holding a non-finite value ends, unconverged, instead of handing LAPACK's
least-squares solver a NaN (dgelsd, behind np.linalg.lstsq, raises on some such systems and loops forever on
others, e.g. a 4 x 4 identity with one NaN off the diagonal). Run in a child process, so a hang fails by timeout."""
from __future__ import annotations

import textwrap

import pytest

from tests.support.child import run_child

CHILD = textwrap.dedent("""
    import sys
    import numpy as np
    from gravcal.core.diagnosis.synthetic import PLANT, window_session
    from gravcal.core.estimators.extended import fit_extended, model_name, parameterization
    from gravcal.core.model.terms import CALIBRATION_TERMS, calibration_view

    supply = next(t for t in CALIBRATION_TERMS if calibration_view(t).covariate == "vsupply")
    s = window_session(3, {supply: PLANT[supply]})
    par = parameterization(model_name("6", (supply,)), s.start.sensitivity, s.start.offset)
    p0 = par.pack(s.start.sensitivity, s.start.offset)
    var = np.full(len(s.ws), 1e-6)
    clean = fit_extended(par, s.ws, p0, var)
    where = sys.argv[1]
    if where == "mean":
        s.ws.mean[len(s.ws) // 2, 1] = np.nan
    else:  # the supply voltage, a covariate of the term
        s.ws.aux[len(s.ws) // 3, :] = np.nan
    f = fit_extended(par, s.ws, p0, var)
    print(int(clean.converged), int(f.converged), f.iterations)
""")


@pytest.mark.parametrize("where", ["mean", "covariate"])
def test_a_nan_window_ends_the_fit_unconverged_instead_of_hanging(where):
    stdout = run_child(CHILD, where, timeout=60, what="fit_extended on a NaN window (the least-squares solver looped)")
    clean_converged, converged, iterations = map(int, stdout.split())
    assert clean_converged == 1  # the same windows without the NaN fit
    assert converged == 0 and iterations == 1


BATCH_CHILD = textwrap.dedent("""
    import sys
    import numpy as np
    from gravcal.core.diagnosis.synthetic import PLANT, window_session
    from gravcal.core.estimators.lotters import LottersBatch
    from gravcal.core.model.terms import CALIBRATION_TERMS, calibration_view

    covariate = sys.argv[1]
    term = next(t for t in CALIBRATION_TERMS if calibration_view(t).covariate == covariate)
    s = window_session(4, {term: PLANT[term]})
    col = ["temp", "vsupply"].index(covariate)
    clean = LottersBatch(f"6+{term}").fit(s.ws, s.start)
    bad = np.arange(5, len(s.ws), 17)
    s.ws.aux[bad, col] = np.nan
    try:
        LottersBatch(f"6+{term}").fit(s.ws, s.start)
        print(int(clean.converged), len(bad), "no error")
    except ValueError as exc:
        print(int(clean.converged), len(bad), exc)
""")


@pytest.mark.parametrize("covariate", ["temp", "vsupply"])
def test_the_batch_fit_of_an_extended_model_names_windows_without_its_covariate(covariate):
    """LottersBatch on windows some of which carry no value of the covariate its model needs: a ValueError
    that says how many, not LAPACK's "Eigenvalues did not converge" (or a hang) on a NaN Jacobian."""
    stdout = run_child(BATCH_CHILD, covariate, timeout=120, what="LottersBatch on windows with a NaN covariate")
    converged, n_bad, message = stdout.strip().split(" ", 2)
    assert converged == "1"  # the same windows with every covariate value fit
    label = {"temp": "temperature", "vsupply": "supply voltage"}[covariate]
    assert f"{n_bad} of 200 windows carry no {label} value" in message, message
