"""What a finding's magnitude owes to what the fit held, and what one posture cannot separate.

A term is tested given the baseline (diagnose.given_held): with the sensitivities unobservable the
baseline holds them at the start's values, and parameters the windows do not determine (the offsets
across gravity in one posture) stay at the baseline's all-window values. The magnitude's statistical
std ignores both. Here each held quantity is moved by its own std (the start's stated held covariance;
the all-window fit's std of a held base parameter) and the whole chain refitted: baseline on all
windows, then the selected terms. Half the difference of the +/- refits is that quantity's
contribution to the magnitude (report units, which also carry the unobservable counts-per-g scale);
the stated std is the root sum of squares with the statistical one (a consider / uncertain-parameter
analysis, done by finite differences so it includes the scale conversion).
"""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from gravcal.core.calibration import Calibration
from gravcal.core.estimators.lotters import LottersBatch
from gravcal.core.estimators.parameterization import PARAMETERIZATIONS
from gravcal.core.estimators.single_pose import channel_slopes, held_gain_rel_std
from gravcal.core.model.terms import CALIBRATION_TERMS, COVARIATES, calibration_view
from gravcal.core.windows import WindowSet

from .terms import TermSelector


def scale_rel_std(held_meta: dict[str, Any] | None, start: Calibration) -> np.ndarray:
    """(3,) relative std of the held sensitivities (the start's stated held covariance; 0 where none)."""
    return held_gain_rel_std(start, held_meta)


def _magnitudes(sel: TermSelector, base_cal: Calibration, chosen: tuple[str, ...], held: dict[str, list[int]]
                ) -> dict[str, np.ndarray]:
    """Per chosen term: (report values (3,), raw values (3,)) refitted with ``base_cal`` as the held baseline."""
    k_sel = TermSelector(sel.ws, sel.base, base_cal, has_temp=sel.has_temp, folds=sel.folds, t_ref_c=sel.t_ref_c,
                         t0_s=sel.t0_s, held_base=sel.held_base, lag_history=sel.lag_history)
    k_sel.var = sel.var
    par, f = k_sel.fit(chosen, held)
    mags = par.magnitudes(f.p)
    out, k = {}, par.base.n_params
    for term in par.terms:
        out[term] = np.concatenate([[mags[term]["value"][key] for key in calibration_view(term).keys], f.p[k:k + 3]])
        k += 3
    return out


def _perturbed_base(base: str, cal: Calibration, j: int, step: float) -> Calibration:
    par = PARAMETERIZATIONS[base](cal.sensitivity, cal.offset)
    p = par.pack(cal.sensitivity, cal.offset)
    p[j] += step
    K, o = par.unpack(p)
    return dataclasses.replace(cal, offset=o, sensitivity=K)


def held_contributions(sel: TermSelector, chosen: tuple[str, ...], held: dict[str, list[int]], *, base: str,
                       base_cal: Calibration, ws_base: WindowSet, start: Calibration,
                       held_meta: dict[str, Any] | None, also: dict[str, list[int]] | None = None
                       ) -> tuple[dict[str, np.ndarray], list[str]]:
    """Per chosen term the (6,) std contribution (report units x3, raw units x3) of everything held, and the
    list of what was propagated. ``ws_base``: the windows the baseline is fitted on; ``held_meta``: the start's
    stated held covariance (consider.HELD_KEY), None when it states none. ``also`` {term: axes held at 0}: terms
    not chosen whose magnitude is evaluated in the model chosen + term (a test's estimate, named or not):
    each gets its contribution from that model, so its std does not depend on the selection."""
    models = [(chosen, held)] + [(chosen + (t,), {**held, t: list(h)}) for t, h in (also or {}).items()
                                 if t not in chosen]
    models = [m for m in models if m[0]]
    if not models:
        return {}, []
    var: dict[str, np.ndarray] = {t: np.zeros(6) for t in chosen + tuple(also or ())}
    sources: list[str] = []

    def mags(bc: Calibration) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {}
        for i, (terms, h) in enumerate(models):
            m = _magnitudes(sel, bc, terms, h)
            out.update(m if i == 0 and terms == chosen else {terms[-1]: m[terms[-1]]})
        return out

    def add(label: str, plus: dict[str, np.ndarray], minus: dict[str, np.ndarray]) -> None:
        sources.append(label)
        for t in var:
            var[t] += ((plus[t] - minus[t]) / 2.0) ** 2

    if held_meta and base == "offsets":  # the sensitivities the baseline holds, as uncertain as the start says
        names, cov = held_meta.get("names", []), np.asarray(held_meta.get("cov", []), dtype=float)
        for n, name in enumerate(names):
            if name not in ("s_x", "s_y", "s_z"):
                continue
            i, sd = "xyz".index(name[2]), float(np.sqrt(cov[n, n]))
            fits = []
            for sign in (1.0, -1.0):
                K = start.sensitivity.copy()
                K[i, i] += sign * sd
                bc = LottersBatch(base).fit(ws_base, dataclasses.replace(start, sensitivity=K))
                fits.append(mags(bc))
            add(f"{name} ± {sd:.4g} raw/g ({held_meta.get('source', 'stated held uncertainty')})", *fits)
    names = PARAMETERIZATIONS[base](base_cal.sensitivity, base_cal.offset).names
    for j in sel.held_base:  # base parameters these windows do not determine, held at the all-window fit
        sd = float(np.sqrt(max(base_cal.covariance[j, j], 0.0))) if base_cal.covariance.shape[0] > j else 0.0
        if sd > 0:
            add(f"{names[j]} ± {sd:.4g} (held at the all-window baseline)",
                mags(_perturbed_base(base, base_cal, j, sd)), mags(_perturbed_base(base, base_cal, j, -sd)))
    return {t: np.sqrt(v) for t, v in var.items()}, sources


def one_posture_partner(term: str) -> str | None:
    """The term one posture cannot tell ``term`` from: an offset term and the sensitivity term on the same
    covariate change the reading along gravity alike (o(c) vs s(c) x 1 g)."""
    view = calibration_view(term)
    if view.acts_on != "offset" or view.covariate not in COVARIATES or view.covariate == "accel":
        return None
    return next((t for t in CALIBRATION_TERMS if calibration_view(t).acts_on == "sensitivity"
                 and calibration_view(t).covariate == view.covariate), None)


def one_posture_magnitude(tt: Any, ws: WindowSet, scale: np.ndarray, scale_rel_std: np.ndarray) -> None:
    """In one posture an offset term's magnitude is each channel's slope on the covariate: determined for
    every channel (the pose does not move), converted at the held sensitivity with its relative std. What
    one pose does not determine is said instead of printed: along gravity whether the change is the offset's or
    the sensitivity's, and the absolute offsets across gravity (the norm does not see them)."""
    mag = tt.magnitude
    view = calibration_view(tt.effect)
    partner = one_posture_partner(tt.effect)
    slopes = channel_slopes(ws, view.covariate)
    mag["confounded_with"] = [partner]
    if slopes is None:
        return
    conv = np.abs(view.report_factor(scale))
    raw = np.array([slopes["value"][a] for a in "xyz"])
    raw_sd = np.array([slopes["std"][a] for a in "xyz"])
    value = raw * conv
    stat = raw_sd * conv
    sd = np.hypot(stat, value * scale_rel_std)
    mag.update({"value": dict(zip("xyz", value.tolist())), "std": dict(zip("xyz", sd.tolist())),
                "std_statistical": dict(zip("xyz", stat.tolist())),
                "std_scale": dict(zip("xyz", (np.abs(value) * scale_rel_std).tolist())),
                "raw_value": slopes["value"], "raw_std": slopes["std"], "raw_unit": slopes["unit"],
                "raw_channel_slopes": slopes, "method": "per-channel least squares of the window means on the "
                "covariate; std: the slope's under the windows' covariance (white, or white plus a slow wander, "
                "widened for its few degrees of freedom), with the held sensitivity's relative std"})
    for key in ("undetermined", "std_noise", "std_held", "held"):
        mag.pop(key, None)
    mag.setdefault("notes", []).append(
        f"one posture: each channel's reading slope is determined; along gravity an offset change and a "
        f"sensitivity change ({partner}) read alike, so the gravity channel's slope may be either; the absolute "
        f"offsets across gravity are not determined")
