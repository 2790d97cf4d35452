"""Parameterizations extended by the registry's calibration terms, whose effect depends on per-window covariates.

Each registered term with a calibration view (``core/model/terms``, one module per effect) adds three
parameters to a base order; at a window with covariates c (temperature, supply voltage, mid time, or the
window's own reference acceleration) the triad reads

    raw = K(c) a + o(c),   K(c) = K_ref + sum_p p dK_p(c),   o(c) = o_ref + sum_p p do_p(c)

with the rows dK_p, do_p the term's view declares (``core/model/spec.py``, ``core/model/effect.py``).
Every extra parameter enters linearly, with derivatives that depend on the window's covariates
instead of being constant. So an extended parameterization is a Parameterization whose
``at_windows(ws)`` returns the same thing bound to those windows' covariates (per-row dK, do); at the
references (T_ref, V_ref, t0) it reduces to its base ("offsets", "6", "9"), which is what ``unpack``
returns. ``LottersRecursive`` uses it window by window (it passes each window's aux and time),
``LottersBatch`` and ``fit_extended`` below in batch. Every estimator stores :func:`extended_metadata`
with its Calibration (``params``, ``extended``): its K, o hold at the references only, and
``Calibration.apply`` / :func:`apply_windows` (the held-out error) need the terms to correct at each
sample's or window's covariates.

Names are ``"<base>+<term>+<term>..."`` (e.g. ``"6+temperature_offset"``); :func:`extended_class`
builds and registers the class in PARAMETERIZATIONS on first use. The covariates are the windows'
``aux`` columns by name (``core/model/spec.AUX_COLUMNS``: temperature, supply voltage) and ``t``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from gravcal.core.accelerator import kernels
from gravcal.core.calibration import Calibration
from gravcal.core.estimators.parameterization import (PARAMETERIZATIONS, Parameterization, h_variance,
                                                      norm_and_projection)
from gravcal.core.model.effect import (LAG_KEY, constant_rows, covariate_deviation, default_lag_tau_s,
                                       lagged_deviations, needed_covariates, references, term_entries, term_rows)
from gravcal.core.model.spec import CROSS_PAIRS
from gravcal.core.model.terms import CALIBRATION_TERMS, COVARIATES, calibration_view
from gravcal.core.windows import WindowSet

_fitsums = kernels("gravcal.core._fitsums")
_jacobians = kernels("gravcal.core.estimators._jacobians")

EXTRA_TERMS: tuple[str, ...] = CALIBRATION_TERMS
"""Registered terms with a calibration-level (window-mean) effect, in canonical order."""

T_REF_C = COVARIATES["temp"].default_ref  # reference temperature [°C] of the extended K, o (the model's t0_c)


class ExtendedParameterization(Parameterization):
    """Base parameterization (``base_model``) plus the extra terms (``terms``); see module docstring.

    Class attributes set by :func:`extended_class`; instances are built like any parameterization,
    ``cls(K0, o0)``, with optional keyword ``t_ref_c`` [°C], ``t0_s`` [s], ``temp_column``, ``lag_tau_s``
    [s] (time constant of a lagged term: fixed here, profiled by diagnosis), ``lag_history`` (the
    recording's window times and temperatures, so that held-out folds keep the lag's earlier history).
    """

    base_model: ClassVar[str] = "6"
    terms: ClassVar[tuple[str, ...]] = ()
    covariates: ClassVar[tuple[str, ...]] = ()

    def __init__(self, K0: np.ndarray, o0: np.ndarray, *, t_ref_c: float = T_REF_C, t0_s: float = 0.0,
                 temp_column: int = 0, v_ref: float = COVARIATES["vsupply"].default_ref,
                 lag_tau_s: float | None = None, lag_history: tuple[np.ndarray, np.ndarray] | None = None):
        super().__init__(K0, o0)
        self.lag_history = lag_history  # (t [s], temperature [°C]) of the whole recording, for subsets
        self.lag_tau_s = default_lag_tau_s() if lag_tau_s is None else float(lag_tau_s)
        self.base = PARAMETERIZATIONS[self.base_model](K0, o0)
        self.t_ref_c, self.t0_s, self.temp_column = float(t_ref_c), float(t0_s), int(temp_column)
        self.v_ref = float(v_ref)
        nb = self.base.n_params
        self.extra_names = [n for term in self.terms for n in calibration_view(term).param_names()]
        self.names = list(self.base.names) + self.extra_names
        P = len(self.names)
        # at the reference (T = T_ref, t = t0, a0² = 0): the base, extras without effect, except the
        # cross-axis terms, whose derivative is constant
        self.dK, self.do = constant_rows(self.terms, nb, P)
        self.dK[:nb], self.do[:nb] = self.base.dK, self.base.do
        self.K_const, self.o_const = self.base.K_const, self.base.o_const
        self._K0inv = np.linalg.inv(self.K0)
        self._diagK0 = np.abs(np.diag(self.K0))

    def pack(self, K: np.ndarray, o: np.ndarray) -> np.ndarray:
        """Base parameters of (K, o) (the base's own pack), extras 0 (no term effect)."""
        return np.concatenate([self.base.pack(K, o), np.zeros(len(self.extra_names))])

    # -- covariates ------------------------------------------------------------------------------
    @property
    def refs(self) -> dict[str, float]:
        """Covariate references: temperature [°C], supply [V], time [s]."""
        return {"temp": self.t_ref_c, "vsupply": self.v_ref, "time": self.t0_s, LAG_KEY: self.lag_tau_s}

    def aux_column(self, covariate: str) -> int:
        return self.temp_column if covariate == "temp" else int(COVARIATES[covariate].aux_column)

    def window_covariates(self, ws: WindowSet) -> dict[str, np.ndarray]:
        """Per covariate the terms need: its (M, 3) deviation from the reference per window (module docstring)."""
        values: dict[str, np.ndarray | None] = {"time": ws.t}
        for cov in needed_covariates(self.terms):
            if cov == "time":
                continue
            col = self.aux_column(cov)
            if ws.aux.ndim != 2 or ws.aux.shape[1] <= col:
                users = [t for t in self.terms if calibration_view(t).covariate == cov]
                raise ValueError(f"{'/'.join(users)} needs the windows' {COVARIATES[cov].label} (aux column {col}); the windows have none")
            values[cov] = ws.aux[:, col]
        accel_sq = None
        if any(calibration_view(t).covariate == "accel" for t in self.terms):
            a0 = (ws.mean - self.o0) @ self._K0inv.T
            accel_sq = self._diagK0 * a0 * a0
        covs = {calibration_view(t).covariate for t in self.terms} - {None}
        out = {c: covariate_deviation(c, values, self.refs, accel_sq, len(ws)) for c in covs}
        out.update(lagged_deviations(self.terms, values, self.refs, len(ws), self.lag_history))
        return out

    def at_windows(self, ws: WindowSet) -> "Parameterization":
        """This parameterization bound to the windows' covariates (per-row derivatives)."""
        return _Bound(self, ws)

    def row_derivatives(self, ws: WindowSet) -> tuple[np.ndarray, np.ndarray]:
        """Per-window dK (M, P, 3, 3) and do (M, P, 3)."""
        M = len(ws)
        dK = np.broadcast_to(self.dK, (M,) + self.dK.shape).copy()
        do = np.broadcast_to(self.do, (M,) + self.do.shape).copy()
        term_rows(self.terms, self.base.n_params, dK, do, self.window_covariates(ws))
        return dK, do

    # -- physical magnitudes ---------------------------------------------------------------------
    def report_values(self, p: np.ndarray) -> dict[str, np.ndarray]:
        """Each extra term in its report units (per axis, in ``view.keys`` order) at parameters p. A cross-axis
        term is the exact misalignment of the calibrated axes (:func:`axis_misalignment_deg` of K at the
        references), the others the view's ``report_factor`` of the diagonal sensitivities."""
        K, _ = self.unpack(p)
        s = np.abs(np.diag(K))
        out: dict[str, np.ndarray] = {}
        k = self.base.n_params
        for term in self.terms:
            view = calibration_view(term)
            if view.acts_on == "cross":
                out[term] = axis_misalignment_deg(K)
            else:
                out[term] = np.asarray(p[k:k + 3], dtype=float) * view.report_factor(s)
            k += 3
        return out

    def magnitudes(self, p: np.ndarray, std: np.ndarray | None = None, *,
                   cov: np.ndarray | None = None) -> dict[str, dict[str, Any]]:
        """Each extra term in its report units (per axis), with std when ``cov`` (the parameters' covariance,
        propagated through the report conversion: the sensitivities' uncertainty and their correlation with
        the terms included) or ``std`` (taken as independent) is given."""
        p = np.asarray(p, dtype=float)
        values = self.report_values(p)
        if cov is None and std is not None:
            cov = np.diag(np.square(np.asarray(std, dtype=float)))
        rep_std = None if cov is None else _propagated_std(self.report_values, p, np.asarray(cov, dtype=float))
        out: dict[str, dict[str, Any]] = {}
        for n, term in enumerate(self.terms):
            view = calibration_view(term)
            d: dict[str, Any] = {"unit": view.unit, "value": dict(zip(view.keys, values[term].tolist()))}
            if rep_std is not None:
                d["std"] = dict(zip(view.keys, rep_std[3 * n:3 * n + 3].tolist()))
            out[term] = d
        return out


def axis_misalignment_deg(K: np.ndarray) -> np.ndarray:
    """90° minus the angle between the calibrated axes i and j, pairs xy, xz, yz [deg]: channel i senses
    along row i of K, so the angle is that between the rows (exact; it depends on K K^T alone, which the
    gravity norm determines whatever frame K carries). Positive when the axes are closer than 90°."""
    u = np.asarray(K, dtype=float) / np.linalg.norm(K, axis=1, keepdims=True)
    return np.degrees(np.arcsin(np.clip([u[i] @ u[j] for i, j in CROSS_PAIRS], -1.0, 1.0)))


def axis_angles(par: Parameterization, p: np.ndarray, cov: np.ndarray) -> dict[str, Any]:
    """The calibrated axes' misalignment (:func:`axis_misalignment_deg` of K at p) with its std from the
    parameters' covariance ``cov``: {"unit", "value": {xy, xz, yz}, "std": {...}} [deg from orthogonal]."""
    def f(q: np.ndarray) -> dict[str, np.ndarray]:
        return {"angles": axis_misalignment_deg(par.unpack(q)[0])}

    p = np.asarray(p, dtype=float)
    keys = [f"{'xyz'[i]}{'xyz'[j]}" for i, j in CROSS_PAIRS]
    std = _propagated_std(f, p, np.asarray(cov, dtype=float))
    return {"unit": "deg_from_orthogonal", "value": dict(zip(keys, f(p)["angles"].tolist())),
            "std": dict(zip(keys, std.tolist()))}


def _propagated_std(f, p: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """sqrt(diag(J C J^T)) of the concatenated values of f (a dict of arrays) at p, J by central differences
    with steps of 1e-4 of each parameter's std (the conversions are smooth on that scale)."""
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    h = np.where(sd > 0, 1e-4 * sd, 1e-7 * np.maximum(np.abs(p), 1.0))
    cols = []
    for k in range(len(p)):
        e = np.zeros(len(p))
        e[k] = h[k]
        hi, lo = f(p + e), f(p - e)
        cols.append(np.concatenate([hi[t] - lo[t] for t in hi]) / (2 * h[k]))
    J = np.stack(cols, axis=1) if cols else np.zeros((0, 0))
    C = np.where(np.isfinite(cov), cov, 0.0)
    var = np.einsum("ij,jk,ik->i", J, C, J)
    bad = ~np.all(np.isfinite(cov), axis=1)  # a parameter without a finite variance: no finite std either
    var = np.where((np.abs(J[:, bad]) > 0).any(axis=1), np.nan, var) if bad.any() else var
    return np.sqrt(np.clip(var, 0, None))


class _Bound(Parameterization):
    """An ExtendedParameterization bound to M windows: per-row derivatives (for the batch fit);
    with M == 1 also exposes them as ``dK``/``do`` (for the recursive estimator's per-window step)."""

    def __init__(self, par: ExtendedParameterization, ws: WindowSet):
        super().__init__(par.K0, par.o0)
        self.parent = par
        self.model = par.model
        self.names = list(par.names)
        self.K_const, self.o_const = par.K_const, par.o_const
        self.n_rows = len(ws)
        self._ws = ws
        self._rows: tuple[np.ndarray, np.ndarray] | None = None
        # for the kernel: the constant rows (dK_q | do_q) and the entries term_rows fills per window, with values
        covs = par.window_covariates(ws)
        entries = list(term_entries(par.terms, par.base.n_params, covs))
        self._missing = {c: ~np.isfinite(z).all(axis=1) for c, z in covs.items()}  # per covariate: rows without it
        self.const_rows = np.ascontiguousarray(np.concatenate([par.dK.reshape(-1, 9), par.do], axis=1))
        self.entries = np.array([(q, 9 + i if on_offset else 4 * i) for q, on_offset, i, _ in entries],
                                dtype=float).reshape(-1, 2)
        self.values = np.ascontiguousarray(np.column_stack([z for *_, z in entries]) if entries
                                           else np.zeros((len(ws), 0)), dtype=float)
        self.dK, self.do = (self.dK_rows[0], self.do_rows[0]) if len(ws) == 1 else (par.dK, par.do)

    def unusable_windows(self) -> str:
        """A covariate a term needs that some windows lack (NaN/inf: a channel that read no value): a fit would
        hand LAPACK a NaN Jacobian (it raises on some systems and loops forever on others)."""
        label = {c: v.label for c, v in COVARIATES.items()}
        label.update({v.deviation_key: f"lagged {COVARIATES[v.covariate].label}"
                      for v in map(calibration_view, self.parent.terms) if v.lagged})
        bad = [f"{int(m.sum())} of {self.n_rows} windows carry no {label.get(c, c)} value"
               for c, m in self._missing.items() if m.any()]
        return f"model {self.model} cannot be fitted: {'; '.join(bad)}" if bad else ""

    def subset(self, idx: np.ndarray, ws: WindowSet | None = None) -> "_Bound":
        """This binding restricted to the windows ``idx`` (``ws``: this binding's windows' ``subset(idx)`` when the
        caller has it). Every covariate value is an elementwise function of its own window (a lag runs over
        the recording's history), so the rows are sliced, equal bit for bit to binding the subset; a lag
        without a history and the reference acceleration (a matrix product) are bound anew."""
        par = self.parent
        lag_restarts = par.lag_history is None and any(calibration_view(t).lagged for t in par.terms)
        idx = np.asarray(idx)
        ws = self._ws.subset(idx) if ws is None else ws
        if lag_restarts or any(calibration_view(t).covariate == "accel" for t in par.terms):
            return _Bound(par, ws)
        out = object.__new__(_Bound)
        out.__dict__.update(self.__dict__)
        out.n_rows, out._ws, out._rows = len(ws), ws, None
        out.values = np.ascontiguousarray(self.values[idx])
        out._missing = {c: m[idx] for c, m in self._missing.items()}
        out.dK, out.do = (out.dK_rows[0], out.do_rows[0]) if len(ws) == 1 else (par.dK, par.do)
        return out

    @property
    def dK_rows(self) -> np.ndarray:
        """Per-window dK (M, P, 3, 3) (row_derivatives; built on first use)."""
        return self._full_rows()[0]

    @property
    def do_rows(self) -> np.ndarray:
        """Per-window do (M, P, 3)."""
        return self._full_rows()[1]

    def _full_rows(self) -> tuple[np.ndarray, np.ndarray]:
        if self._rows is None:
            self._rows = self.parent.row_derivatives(self._ws)
        return self._rows

    def pack(self, K, o):
        return self.parent.pack(K, o)

    def rows_K_o(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """K (M, 3, 3), o (M, 3) of every bound window at p."""
        return self.K_const[None] + combine_rows(p, self.dK_rows), self.o_const[None] + combine_rows(p, self.do_rows)

    def norm_jacobian_variance(self, p: np.ndarray, raw: np.ndarray, cov_mean: np.ndarray | None = None
                               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """As Parameterization's, with each window's own K(c), o(c) for a and dh/dp; the variance of h uses
        K^-1 at the references (``unpack``), as the batch fit weighs the windows."""
        a, J = self.accel_and_jacobian(p, raw)
        h, B = norm_and_projection(a, J)
        if cov_mean is None:
            return h, B, a, None
        return h, B, a, h_variance(a, np.linalg.inv(self.unpack(p)[0]), cov_mean, h)

    def accel_and_jacobian(self, p: np.ndarray, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raw = np.ascontiguousarray(raw, dtype=float).reshape(-1, 3)
        if raw.shape[0] != self.n_rows:
            raise ValueError(f"bound to {self.n_rows} windows, got {raw.shape[0]} means: bind with at_windows(ws)")
        m, P, n = self.n_rows, len(self.names), len(self.entries)
        a, J = np.empty((m, 3)), np.empty((m, 3, P))
        # K(c), o(c), K(c)^-1, a and J = -K^-1 (dK_p a + do_p) in one compiled pass over the windows
        _jacobians.extended_accel_jacobian(np.ascontiguousarray(self.K_const, dtype=float),
                                           np.ascontiguousarray(self.o_const, dtype=float),
                                           np.ascontiguousarray(p, dtype=float), self.const_rows, self.entries,
                                           self.values, raw, a, J, m, P, n)
        return a, J


def combine_rows(p: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """sum_p p[p] rows[:, p] for rows (M, P, ...): numpy's einsum("p,mp...->m..."), compiled."""
    M, P = rows.shape[:2]
    out = np.empty((M,) + rows.shape[2:])
    _fitsums.combine(np.ascontiguousarray(p, dtype=float), np.ascontiguousarray(rows, dtype=float), out, M, P,
                     int(np.prod(rows.shape[2:], dtype=np.int64)))
    return out


def extended_class(name: str) -> type[ExtendedParameterization]:
    """The class for ``"<base>+<term>+..."``, created and registered in PARAMETERIZATIONS on first use."""
    if name in PARAMETERIZATIONS:
        cls = PARAMETERIZATIONS[name]
        if not (isinstance(cls, type) and issubclass(cls, ExtendedParameterization)):
            raise ValueError(f"{name!r} is not an extended parameterization")
        return cls
    base, *terms = name.split("+")
    if base not in PARAMETERIZATIONS or not terms:
        raise ValueError(f"extended model {name!r}: expected '<base>+<term>[+<term>...]' with base in "
                         f"{sorted(k for k in PARAMETERIZATIONS if '+' not in k)} and terms in {list(EXTRA_TERMS)}")
    bad = [t for t in terms if t not in EXTRA_TERMS]
    if bad:
        raise ValueError(f"extended model {name!r}: unknown term(s) {bad}; known: {list(EXTRA_TERMS)}")
    cross = [t for t in terms if calibration_view(t).acts_on == "cross"]
    if cross and base in ("9", "12"):
        raise ValueError(f"extended model {name!r}: base {base} already has the cross-axis terms ({cross[0]})")
    terms = sorted(set(terms), key=EXTRA_TERMS.index)
    canonical = "+".join([base, *terms])
    if canonical in PARAMETERIZATIONS:
        return PARAMETERIZATIONS[canonical]  # type: ignore[return-value]
    covs = tuple(sorted({calibration_view(t).covariate for t in terms} - {None}))
    cls = type(f"Extended_{canonical.replace('+', '_')}", (ExtendedParameterization,),
               {"model": canonical, "base_model": base, "terms": tuple(terms), "covariates": covs,
                "__doc__": f"{base} parameters + {', '.join(terms)} (calibration-level view of those model terms)."})
    PARAMETERIZATIONS[canonical] = cls
    if canonical != name:
        PARAMETERIZATIONS[name] = cls
    return cls


def model_name(base: str, terms: tuple[str, ...] | list[str]) -> str:
    """Canonical name of base + terms (the base itself when there are no terms)."""
    terms = sorted(set(terms), key=EXTRA_TERMS.index)
    return "+".join([base, *terms]) if terms else base


def parameterization(model: str, K0: np.ndarray, o0: np.ndarray, **kw: Any) -> Parameterization:
    """An instance of a base or extended model by name."""
    if "+" in model:
        return extended_class(model)(K0, o0, **kw)
    return PARAMETERIZATIONS[model](K0, o0)


# -- what a calibration must carry -----------------------------------------------------------------
def extended_metadata(par: Parameterization, p: np.ndarray, std: np.ndarray | None = None, *,
                      cov: np.ndarray | None = None) -> dict[str, Any]:
    """Calibration metadata every estimator stores with its result: ``params`` (the parameter vector by
    name) and, for an extended parameterization, ``extended`` (terms, reference T_ref / t0, temperature
    column, per-term magnitudes with ``std``), which :func:`apply_extended` needs to correct at each
    sample's temperature and time. ``par`` may be bound to windows (``at_windows``). ``cov``: the parameters'
    covariance, propagated in full into the magnitudes' std (``std`` alone: taken as independent)."""
    par = getattr(par, "parent", par)  # unbind
    p = np.asarray(p, dtype=float)
    meta: dict[str, Any] = {"params": dict(zip(par.names, p.tolist()))}
    if isinstance(par, ExtendedParameterization):
        meta["extended"] = {"terms": list(par.terms), "t_ref_c": par.t_ref_c, "t0_s": par.t0_s, "v_ref": par.v_ref,
                            "temp_column": par.temp_column, LAG_KEY: par.lag_tau_s,
                            "magnitudes": par.magnitudes(p, std, cov=cov)}
    return meta


# -- batch fit with fixed weights ------------------------------------------------------------------
@dataclass
class ExtendedFit:
    """Result of :func:`fit_extended`: parameter vector p and covariance (raw units), residuals 1 - |a| [g]."""

    par: Parameterization
    p: np.ndarray
    cov: np.ndarray
    resid_g: np.ndarray
    chi2: float
    converged: bool
    iterations: int

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov), 0, None))

    def calibration(self, n_windows: int) -> Calibration:
        K, o = self.par.unpack(self.p)
        par = getattr(self.par, "parent", self.par)
        meta: dict[str, Any] = {"estimator": "fit_extended", **extended_metadata(par, self.p, cov=self.cov)}
        return Calibration(model=par.model, offset=o, sensitivity=K, covariance=self.cov, param_names=list(par.names),
                           n_windows=n_windows, converged=self.converged, observable=True, metadata=meta)


def fit_extended(par: Parameterization, ws: WindowSet, p0: np.ndarray, var_g2: np.ndarray, *,
                 free: np.ndarray | None = None, max_iter: int = 30, tol: float = 1e-12) -> ExtendedFit:
    """Iterated eq. 11a (Gauss-Newton on 1 - |a|) with FIXED per-window variances ``var_g2`` [g²].

    Fixed weights (the same for every candidate model of one recording) make the chi² of
    different models comparable, which the information criterion needs; LottersBatch re-derives
    its floor per fit. ``par`` is bound to ``ws`` here when it has covariates. ``free`` (P,) bool:
    parameters estimated; the others stay at p0 (axes of a term the windows do not determine).
    """
    free = np.ones(len(p0), dtype=bool) if free is None else np.asarray(free, dtype=bool)
    bound = par.at_windows(ws) if isinstance(par, ExtendedParameterization) else par
    w = 1.0 / np.asarray(var_g2, dtype=float)
    p = np.array(p0, dtype=float)
    mean = ws.mean

    def cost_at(q):
        h, B, _ = bound.norm_and_jacobian(q, mean)
        xi = 1.0 - h
        return xi, B, float(np.sum(w * xi * xi))

    xi, B, cost = cost_at(p)
    if not free.any():
        return ExtendedFit(bound, p, np.zeros((len(p), len(p))), xi, cost, True, 0)
    B = B[:, free]
    converged, it = False, 0
    for it in range(1, max_iter + 1):
        Bw = B.T * w
        F = Bw @ B
        scale = np.sqrt(np.maximum(np.diag(F), 1e-300))
        Fn = F / np.outer(scale, scale)
        rhs = (Bw @ xi) / scale
        if not (np.isfinite(Fn).all() and np.isfinite(rhs).all()):
            break  # LAPACK's dgelsd (np.linalg.lstsq) can loop forever on a NaN: the fit ends unconverged
        step = np.zeros(len(p))
        step[free] = np.linalg.lstsq(Fn, rhs, rcond=1e-12)[0] / scale
        lam = 1.0
        while lam > 1e-6:
            try:
                xt, Bt, ct = cost_at(p + lam * step)
            except np.linalg.LinAlgError:
                ct = math.inf
            if math.isfinite(ct) and ct <= cost * (1 + 1e-12):
                break
            lam *= 0.5
        else:
            break
        p = p + lam * step
        done = abs(cost - ct) <= tol * max(cost, 1e-300) or np.max(np.abs(lam * step[free]) * scale) < 1e-8
        xi, B, cost = xt, Bt[:, free], ct
        if done:
            converged = True
            break
    cov = np.zeros((len(p), len(p)))
    F = (B.T * w) @ B
    if not np.isfinite(F).all():  # a non-finite window or covariate: no covariance either (eigh refuses NaN)
        cov[np.ix_(free, free)] = np.nan
        return ExtendedFit(bound, p, cov, xi, cost, False, it)
    d = np.sqrt(np.maximum(np.diag(F), 1e-300))
    lam, V = np.linalg.eigh(F / np.outer(d, d))
    lam = np.maximum(lam, 1e-12 * max(float(lam[-1]), 1e-300))  # a void direction gets a huge, finite variance
    cov[np.ix_(free, free)] = ((V / lam) @ V.T) / np.outer(d, d)
    return ExtendedFit(bound, p, cov, xi, cost, converged, it)


def extended_residuals_g(par: Parameterization, p: np.ndarray, ws: WindowSet) -> np.ndarray:
    """1 - |a| [g] of windows ``ws`` under parameters p (covariates of ``ws``); ``par`` bound to ``ws`` itself
    (``at_windows(ws)`` or a ``subset``) is used as it is."""
    if isinstance(par, _Bound) and par._ws is ws:
        bound = par  # already bound to these windows
    else:
        par = getattr(par, "parent", par)  # unbind
        bound = par.at_windows(ws) if isinstance(par, ExtendedParameterization) else par
    a, _ = bound.accel_and_jacobian(p, ws.mean)
    return 1.0 - np.linalg.norm(a, axis=1)


def _extended_parameters(cal: Calibration) -> tuple[ExtendedParameterization, np.ndarray] | None:
    """The parameterization and parameter vector of an extended calibration; None for a plain one.
    Raises ValueError for a calibration named after an extended model that lacks what apply needs
    (applying its reference K, o alone would silently drop the terms)."""
    ext = cal.extended_metadata
    if ext is None:
        return None
    params = cal.metadata.get("params")
    refs = references(ext)
    par = extended_class(cal.model)(cal.sensitivity, cal.offset, t_ref_c=refs["temp"], t0_s=refs["time"],
                                    v_ref=refs["vsupply"], temp_column=ext.get("temp_column", 0),
                                    lag_tau_s=refs[LAG_KEY])
    missing = [n for n in par.names if not isinstance(params, dict) or n not in params]
    if missing:
        raise ValueError(f"calibration {cal.model!r}: metadata['params'] lacks {missing}: cannot apply its terms")
    return par, np.array([float(params[n]) for n in par.names])


def apply_extended(cal: Calibration, raw: np.ndarray, *, temp: np.ndarray | None = None,
                   t: np.ndarray | None = None, vsupply: np.ndarray | None = None) -> np.ndarray:
    """Calibrated acceleration [g] of raw samples (N, 3) at each sample's temperature [°C], time [s] and
    supply [V]: ``Calibration.apply`` with its covariates (kept for the estimators' callers)."""
    return cal.apply(raw, temp=temp, t=t, vsupply=vsupply)


def apply_windows(cal: Calibration, ws: WindowSet) -> np.ndarray:
    """Calibrated acceleration [g] of the window means of ``ws`` at the windows' own temperature
    (``aux``) and mid time; a plain calibration is applied as is."""
    found = _extended_parameters(cal)
    if found is None:
        return cal.apply(ws.mean)
    par, p = found
    a, _ = par.at_windows(ws).accel_and_jacobian(p, ws.mean)
    return a


__all__ = ["EXTRA_TERMS", "ExtendedParameterization", "ExtendedFit", "extended_class", "model_name", "parameterization",
           "fit_extended", "extended_residuals_g", "extended_metadata", "apply_extended", "apply_windows",
           "axis_angles", "axis_misalignment_deg",
           "T_REF_C"]
