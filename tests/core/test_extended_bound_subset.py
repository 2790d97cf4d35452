"""A binding's subset (``_Bound.subset``: the all-window rows sliced for a fold) against the plain form it
replaces, kept here as the oracle: the parameterization bound to the fold's windows anew. Same numbers, bit
for bit, for every registered term, with and without the recording's history for a lagged term."""
from __future__ import annotations

import numpy as np
import pytest

from gravcal.core.diagnosis.synthetic import PLANT, window_session
from gravcal.core.estimators.extended import extended_residuals_g, fit_extended, model_name, parameterization
from gravcal.core.model.terms import CALIBRATION_TERMS, calibration_view

SUPPLY = next(t for t in CALIBRATION_TERMS if calibration_view(t).covariate == "vsupply")


def session(seed: int):
    return window_session(seed, {SUPPLY: PLANT[SUPPLY]})


def extended(s, terms, history: bool):
    kw = {"lag_history": (s.ws.t, s.ws.aux[:, 0])} if history else {}
    return parameterization(model_name("6", terms), s.start.sensitivity, s.start.offset, **kw)


def same_binding(a, b) -> bool:
    p = np.linspace(-0.01, 0.01, len(a.names)) + a.parent.pack(a.K0, a.o0)
    aa, ab = a.accel_and_jacobian(p, a._ws.mean), b.accel_and_jacobian(p, b._ws.mean)
    return (a.n_rows == b.n_rows and np.array_equal(a.values, b.values) and np.array_equal(a.entries, b.entries)
            and np.array_equal(a.const_rows, b.const_rows) and np.array_equal(a.dK_rows, b.dK_rows)
            and np.array_equal(a.do_rows, b.do_rows) and np.array_equal(a.dK, b.dK) and np.array_equal(a.do, b.do)
            and all(np.array_equal(x, y) for x, y in zip(aa, ab)))


def fold_indices(m: int, k: int, rng) -> list[np.ndarray]:
    order = np.arange(m)
    out = []
    for test in np.array_split(order, k):
        out += [np.setdiff1d(order, test), test]
    return out + [np.sort(rng.choice(m, 7, replace=False)), np.array([m // 3])]


@pytest.mark.parametrize("term", CALIBRATION_TERMS)
@pytest.mark.parametrize("history", [True, False])
def test_subset_equals_binding_the_subset_bit_for_bit(term, history):
    s = session(31)
    other = next(t for t in CALIBRATION_TERMS if t != term and calibration_view(t).acts_on != "cross")
    rng = np.random.default_rng(5)
    for terms in ((term,), tuple(sorted({term, other}, key=CALIBRATION_TERMS.index))):
        par = extended(s, terms, history)
        whole = par.at_windows(s.ws)
        assert whole.dK_rows.shape[0] == len(s.ws)  # its full rows built: a subset must not serve them
        for idx in fold_indices(len(s.ws), 5, rng):
            sub = s.ws.subset(idx)
            if len(idx) == 1 and not history and any(calibration_view(t).profiled is not None for t in terms):
                for bind in (lambda: whole.subset(idx, sub), lambda: par.at_windows(sub)):
                    with pytest.raises(ValueError, match="history"):  # a lag restarted on one window: refused
                        bind()
                continue
            fast, plain = whole.subset(idx, sub), par.at_windows(sub)
            assert same_binding(fast, plain), (terms, idx[:3])
            assert same_binding(whole.subset(idx), plain)  # the windows sliced by the binding itself


def test_fits_and_residuals_on_a_subset_equal_the_plain_ones():
    """fit_extended on a sliced binding and extended_residuals_g taking it as bound: the fit and the held-out
    residuals the diagnosis computes per fold, as with the windows bound anew."""
    s = session(32)
    lagged = next(t for t in CALIBRATION_TERMS if calibration_view(t).profiled is not None)
    for terms in ((SUPPLY,), (lagged,), (SUPPLY, lagged)):
        par = extended(s, tuple(sorted(terms, key=CALIBRATION_TERMS.index)), True)
        whole = par.at_windows(s.ws)
        var = np.full(len(s.ws), 1e-6)
        p0 = par.pack(s.start.sensitivity, s.start.offset)
        for train, test in zip(*[iter(fold_indices(len(s.ws), 4, np.random.default_rng(0))[:8])] * 2):
            wtr, wte = s.ws.subset(train), s.ws.subset(test)
            f, g = fit_extended(whole.subset(train, wtr), wtr, p0, var[train]), fit_extended(par, wtr, p0, var[train])
            assert (np.array_equal(f.p, g.p) and np.array_equal(f.cov, g.cov) and f.chi2 == g.chi2
                    and f.iterations == g.iterations and np.array_equal(f.resid_g, g.resid_g))
            r = extended_residuals_g(whole.subset(test, wte), f.p, wte)
            assert np.array_equal(r, extended_residuals_g(par, g.p, wte)) and np.all(np.abs(r) < 0.05)
    # a binding to other windows is not taken as bound: the windows are bound anew
    assert np.array_equal(extended_residuals_g(whole, f.p, wte), extended_residuals_g(par, f.p, wte))
