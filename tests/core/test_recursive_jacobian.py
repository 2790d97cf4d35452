"""The recursive estimator's hand-unrolled linearisation equals the generic one exactly.

LottersRecursive._h_B_R spells out h = |K^-1 (m - o)| (eq. 8), dh/dp (eq. 13a generalised) and the
window variance g C g^T + floor in plain floats for speed; the batch estimators use the
parameterizations' vectorised ``norm_and_jacobian``. Any slip (a sign, a factor, a missing term's
row) in either shows here as a mismatch far above rounding, for every order and every extended term.
"""
from __future__ import annotations

import numpy as np
import pytest

from gravcal.core.calibration import Calibration
from gravcal.core.estimators.extended import EXTRA_TERMS, model_name, parameterization
from gravcal.core.estimators.recursive import LottersRecursive
from gravcal.core.model.terms import calibration_view
from gravcal.core.windows import WindowSet

BASES = ("offsets", "6", "9", "12")
RECURSIVE_TERMS = tuple(t for t in EXTRA_TERMS if calibration_view(t).per_window)  # the others are offline only
MODELS = list(BASES) + [model_name("6", (t,)) for t in RECURSIVE_TERMS] + [
    model_name("offsets", tuple(t for t in RECURSIVE_TERMS if not calibration_view(t).through_sensitivity))]


def _start(rng: np.random.Generator) -> Calibration:
    K = np.diag(rng.uniform(0.035, 0.045, 3)) + rng.normal(0, 5e-4, (3, 3))
    return Calibration("start", 0.5 + rng.normal(0, 0.01, 3), K)


@pytest.mark.parametrize("model", MODELS)
def test_recursive_linearisation_equals_generic(model):
    rng = np.random.default_rng(sum(map(ord, model)))
    start = _start(rng)
    rec = LottersRecursive(start, model, sigma_floor_g=2e-3)
    par = rec.par  # the same parameterization (references, terms), through its generic vectorised path
    for _ in range(20):
        p = rec.p + rng.normal(0, 1e-3, rec.p.size)  # away from the start: every row of dK, do matters
        u = rng.normal(size=3)
        mean = start.offset + start.sensitivity @ (u / np.linalg.norm(u)) + rng.normal(0, 1e-3, 3)
        A = rng.normal(0, 1e-4, (3, 3))
        cov = A @ A.T
        t, aux = float(rng.uniform(0, 7200)), np.array([rng.uniform(15, 40), rng.uniform(3.0, 3.4)])
        rec._bind(mean, t, aux)
        h, B, R = rec._h_B_R(p, tuple(mean), list(cov.ravel()))
        ws = WindowSet(mean[None], cov[None], np.ones(1), np.array([t]), aux[None], np.zeros(1, dtype=np.int64),
                       np.ones(1, dtype=np.int64))
        bound = par.at_windows(ws) if hasattr(par, "at_windows") else par
        h_ref, B_ref, a = bound.norm_and_jacobian(p, mean[None])
        assert h == pytest.approx(float(h_ref[0]), rel=1e-12)
        np.testing.assert_allclose(B, B_ref[0], rtol=1e-9, atol=1e-12 * np.abs(B_ref).max())
        g = (a[0] / h_ref[0]) @ np.linalg.inv(bound.rows_K_o(p)[0][0] if hasattr(bound, "rows_K_o")
                                               else par.unpack(p)[0])
        assert R == pytest.approx(float(g @ cov @ g) + 4e-6, rel=1e-12)


def test_jacobian_matches_finite_differences():
    """The generic Jacobian itself against central differences of h (so the two cannot share a slip)."""
    rng = np.random.default_rng(3)
    start = _start(rng)
    for model in ("12", model_name("6", EXTRA_TERMS[2:4])):
        par = parameterization(model, start.sensitivity, start.offset, t_ref_c=25.0)
        u = rng.normal(size=(5, 3))
        mean = start.offset + (u / np.linalg.norm(u, axis=1, keepdims=True)) @ start.sensitivity.T
        ws = WindowSet(mean, np.zeros((5, 3, 3)), np.ones(5), rng.uniform(0, 3600, 5),
                       np.column_stack([rng.uniform(15, 40, 5), np.full(5, 3.3)]), np.zeros(5, dtype=np.int64),
                       np.ones(5, dtype=np.int64))
        bound = par.at_windows(ws) if hasattr(par, "at_windows") else par
        p = par.pack(start.sensitivity, start.offset) + rng.normal(0, 1e-3, par.n_params)
        _, B, _ = bound.norm_and_jacobian(p, mean)
        for k in range(par.n_params):
            e = np.zeros(par.n_params)
            e[k] = 1e-6
            fd = (bound.norm_and_jacobian(p + e, mean)[0] - bound.norm_and_jacobian(p - e, mean)[0]) / 2e-6
            np.testing.assert_allclose(B[:, k], fd, rtol=1e-5, atol=1e-6 * np.abs(B).max())
