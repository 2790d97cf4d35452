"""The std of a named term's magnitude: the fit's full covariance, widened for an estimated floor (Student t)
and, for axes held at 0, taken from the fit with those axes free (a consider analysis). ``sel`` is the diagnosis's terms.TermSelector."""
from __future__ import annotations

import numpy as np

from gravcal.core.estimators.lotters import floor_t_factor


def t_widened_cov(sel, terms: tuple[str, ...], held: dict[str, list[int]], f) -> np.ndarray:
    """The covariance of fit ``f`` of base + ``terms`` with each parameter's std widened for the quasi-static
    floor estimated from ``sel.floor_dof`` residuals (Student t; lotters.floor_t_factor, as the batch fit)."""
    floor2, dof = getattr(sel, "floor_g", 0.0) ** 2, getattr(sel, "floor_dof", 0)
    if floor2 <= 0 or dof <= 2 or not np.all(np.isfinite(f.cov)):
        return f.cov
    free = sel.free_mask(sel.par(terms), held)
    _, B, _ = sel.bound(terms).norm_and_jacobian(f.p, sel.ws.mean)
    t = np.ones(len(f.p))
    t[free] = floor_t_factor(B[:, free], sel.var, f.cov[np.ix_(free, free)], floor2, dof)
    return f.cov * np.outer(t, t)


def held_axes_considered(sel, terms: tuple[str, ...], held: dict[str, list[int]], f, cov: np.ndarray,
                         *, k: int, axes: list[int]) -> np.ndarray:
    """``cov`` of the fit with the term's ``axes`` held at 0, where the parameters estimated beside them take the
    covariance of the fit with those axes free (a consider analysis with the held axes' own std: their
    uncertainty reaches what correlates with them). Unchanged when the free fit fails or does not converge."""
    try:
        _, f_free = sel.fit(terms, held)
    except (ValueError, np.linalg.LinAlgError):
        return cov
    if not f_free.converged or not np.all(np.isfinite(f_free.cov)):
        return cov
    free_cov = t_widened_cov(sel, terms, held, f_free)
    est = np.flatnonzero(np.diag(cov) > 0)  # the parameters this fit estimated
    out = cov.copy()
    out[np.ix_(est, est)] = free_cov[np.ix_(est, est)]
    held_idx = [k + i for i in axes]
    out[held_idx, :] = 0.0
    out[:, held_idx] = 0.0
    return out
