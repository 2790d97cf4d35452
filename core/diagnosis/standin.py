"""A chosen term that a residual shape outside the catalogue replaces: a stand-in, not a cause.

Each catalogue term follows one recorded covariate (temperature, time, supply, ...). An effect the catalogue
has no term for (a lag behind the temperature, a curvature, a wandering bias) can be absorbed by several terms
that each follow part of it: each then gains on held-out folds, and the residual they leave shows no
structure, because they took it. So every chosen term A is also compared with the shapes no catalogue term
has (structure.py's offset-type shapes along gravity: curvature in temperature, the temperature's rate of
change, time beyond a linear trend) put in its place. A is a stand-in for shape S when the model with S
instead of A

1. is preferred by BIC by more than ΔBIC 10 at its own number of parameters, and
2. predicts time-contiguous held-out folds better than the model with A.

A shape along an offset term's own covariate (a curvature in temperature beside temperature_offset) contains
the term: there the term is the right covariate with a shape the catalogue lacks, which the residual's structure
test (structure.py) reports; the comparison is between covariates.

Both models are fitted as a linear regression at the fit without A (its residual and Jacobian, with A's
columns or S's added): the two are scored alike. A true term is not replaced: a shape can match it at best
within the noise, and pays for its extra columns. The verdict is then "unexplained" with S's structure
(verdict.unexplained), and the terms found are reported as explaining part of the residual.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from gravcal.core.model.terms import calibration_view

from .noise import DELTA_BIC
from .structure import FOLDS, SHAPES, _covariate, design

CATALOGUE_SHAPE_DEGREE = {"temperature": 1, "time": 1, "supply": 1}
"""Per covariate, the highest degree a catalogue term already has along gravity (temperature_offset,
offset_drift, supply_offset): shapes up to it are the selection's business, not a shape outside it."""


OWN_SHAPE = {"temp": "temperature", "time": "time", "vsupply": "supply"}
"""An offset term's covariate -> the structure shape that contains the term's own (its first degree)."""


def outside_shapes(ws: Any, has_temp: bool) -> list[tuple[str, int, str, np.ndarray]]:
    """(covariate, degree, words, values) of every shape structure.SHAPES describes that no catalogue term has."""
    out = []
    for name, top, first_words, curved_words in SHAPES:
        c = _covariate(ws, name, has_temp)
        if c is None or np.ptp(c) == 0:
            continue
        for deg in range(CATALOGUE_SHAPE_DEGREE.get(name, 0) + 1, top + 1):
            out.append((name, deg, first_words if deg == 1 else curved_words, c))
    return out


def _rss(Z: np.ndarray, y: np.ndarray) -> float:
    coef = np.linalg.lstsq(Z, y, rcond=None)[0]
    r = y - Z @ coef
    return float(r @ r)


def _heldout_mg(Z: np.ndarray, y: np.ndarray, w: np.ndarray, order: np.ndarray) -> float:
    """RMS [mg] of the residual on time-contiguous folds, each predicted by the regression on the others
    (``Z``, ``y`` weighted by ``w``; the RMS unweighted, as every held-out figure of diagnose)."""
    res = np.empty(len(y))
    for test in np.array_split(order, FOLDS):
        train = np.setdiff1d(order, test)
        coef = np.linalg.lstsq(Z[train], y[train], rcond=None)[0]
        res[test] = (y[test] - Z[test] @ coef) / w[test]
    return float(np.sqrt(np.mean(res * res)) * 1e3)


def _replacements(sel: Any, chosen: tuple[str, ...], held: dict[str, list[int]], u: np.ndarray,
                  shapes: list[tuple[str, int, str, np.ndarray]]) -> list[dict[str, Any]]:
    """Every (chosen term A, shape S) where S in A's place passes both tests: A, S, ΔBIC, held-out errors."""
    ws, m = sel.ws, sel.m
    w = 1.0 / np.sqrt(sel.var)
    order = np.argsort(ws.t, kind="stable")
    par_c = sel.par(chosen)
    free_c = sel.free_mask(par_c, held)
    k0 = par_c.base.n_params
    out = []
    for a in chosen:
        own = OWN_SHAPE.get(calibration_view(a).covariate) if calibration_view(a).acts_on == "offset" else None
        ka = k0 + 3 * list(par_c.terms).index(a)
        cols_a = [j for j in range(ka, ka + 3) if free_c[j]]
        if not cols_a:
            continue
        rest = tuple(c for c in chosen if c != a)
        par_r, f_r = sel.fit(rest, {k: v for k, v in held.items() if k in rest})
        # the fit without A in the full model's parameters (A without effect): its residual and the Jacobian
        # of every column, A's included, at that point
        q = sel.start(chosen).copy()
        kr = par_r.base.n_params if rest else par_r.n_params
        q[:k0] = f_r.p[:kr]
        for n, term in enumerate(par_r.terms if rest else ()):  # the registry's order, not the selection's
            kc = k0 + 3 * list(par_c.terms).index(term)
            q[kc:kc + 3] = f_r.p[kr + 3 * n:kr + 3 * n + 3]
        h, B, _ = sel.bound(chosen).norm_and_jacobian(q, ws.mean)
        y = (1.0 - h) * w
        Jm = B[:, [j for j in np.flatnonzero(free_c) if j not in cols_a]] * w[:, None]
        Zc = np.column_stack([Jm, B[:, cols_a] * w[:, None]])
        chi_c, ho_c = _rss(Zc, y), None
        for name, deg, words, c in shapes:
            if name == own:  # A's own shape and more: curvature of A's covariate is the residual structure's test
                continue
            X = design(u, c, deg) * w[:, None]
            if m < 4 * (Jm.shape[1] + X.shape[1]):
                continue
            Zs = np.column_stack([Jm, X])
            d_bic = chi_c - _rss(Zs, y) - (X.shape[1] - len(cols_a)) * math.log(m)
            if not d_bic > DELTA_BIC:
                continue
            ho_c = _heldout_mg(Zc, y, w, order) if ho_c is None else ho_c
            ho_s = _heldout_mg(Zs, y, w, order)
            if not ho_s < ho_c:
                continue
            shape_g = X @ np.linalg.lstsq(Zs, y, rcond=None)[0][Jm.shape[1]:] / w  # what S explains in A's place [g]
            out.append({"term": a, "covariate": name, "degree": deg, "shape": words, "delta_bic": round(d_bic, 2),
                        "heldout_with_term_mg": round(ho_c, 4), "heldout_with_shape_mg": round(ho_s, 4),
                        "structure_rms_mg": round(float(np.sqrt(np.mean(shape_g ** 2)) * 1e3), 4),
                        "curve": (c, shape_g)})
    return out


def stand_ins(sel: Any, chosen: tuple[str, ...], held: dict[str, list[int]], u: np.ndarray
              ) -> tuple[list[dict[str, Any]], dict[str, str]]:
    """Backward, one at a time: the chosen term a shape replaces by the largest ΔBIC is withdrawn, and the
    rest are compared again without it. Returns the shapes (structure.py's entries, ``present`` True, one per
    covariate, strongest first), each with ``replaces`` (the terms it stands in for), its ΔBIC and held-out
    errors [mg] with the term and with the shape in its place, and ``curve`` (covariate values, the shape's
    part [g], for the report's plot); and the withdrawn terms -> why."""
    shapes = outside_shapes(sel.ws, sel.has_temp)
    found: dict[str, dict[str, Any]] = {}
    withdrawn: dict[str, str] = {}
    while chosen and shapes:
        cands = _replacements(sel, chosen, held, u, shapes)
        if not cands:
            break
        r = max(cands, key=lambda r: r["delta_bic"])
        a = r.pop("term")
        entry = found.get(r["covariate"])
        if entry is None or r["delta_bic"] > entry["delta_bic"]:
            found[r["covariate"]] = {**r, "present": True, "replaces": (entry or {}).get("replaces", []) + [a],
                                     "heldout_gain_mg": round(r["heldout_with_term_mg"] - r["heldout_with_shape_mg"], 4)}
        else:
            entry["replaces"].append(a)
        withdrawn[a] = (f"withdrawn: a shape outside the catalogue, residual {r['shape']} ({r['covariate']}, degree "
                        f"{r['degree']}), fits better in its place (ΔBIC {r['delta_bic']:.1f}, held-out "
                        f"{r['heldout_with_term_mg']:.3f} -> {r['heldout_with_shape_mg']:.3f} mg): a stand-in, not a cause")
        chosen = tuple(c for c in chosen if c != a)
        held = {k: v for k, v in held.items() if k in chosen}
    return sorted(found.values(), key=lambda s: -s["delta_bic"]), withdrawn
