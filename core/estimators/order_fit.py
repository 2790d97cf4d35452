"""The fit of one recording's quasi-static windows with model auto's choice or a requested model.

Auto: the order by order.select_order (observability, then 6 against the full set by BIC and held-out
error), then the registry's calibration terms on top of it where testable, observable and warranted
(the online calibrator's rule, core/estimators/online.py). Each fit is the Lötters batch fit
(lotters.LottersBatch). core/pipeline.py calls ``fit_order`` between detection and the held-out folds.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..calibration import Calibration
from ..model.terms import CALIBRATION_TERMS, calibration_view
from ..windows import WindowSet
from .extended import model_name
from .inuse12 import FRAME_CONVENTION, frame_of, rotation_angle_deg, with_frame
from .lotters import LottersBatch, resolve_parameterization
from .observability import N_PARAMS, SIGMA_FLOOR_G, TOL_G, check_observable
from .order import (compare_extended, extended_base, extended_terms, is_observable_extended, reference_start,
                    select_order, term_testability)

AUTO_MIN_WINDOWS = 3  # auto needs at least the offsets' 3 windows (6 for sensitivities)
# extended terms auto may add on top of the chosen order: every registered calibration term except the
# cross-axis one (the order rule's 6-vs-full comparison decides that), judged by the online path's rule
# (order.term_testability, order.is_observable_extended, order.compare_extended)
AUTO_EXTENDED_TERMS = tuple(t for t in CALIBRATION_TERMS  # linear ones: a profiled time constant is diagnose's
                            if calibration_view(t).acts_on != "cross" and calibration_view(t).profiled is None)


class OrderNotDetermined(ValueError):
    """model="auto" found that the windows determine nothing (order "none"); the message says why."""


@dataclass
class Fitted:
    model: str  # the order fitted
    calibration: Calibration
    estimator: LottersBatch  # for the held-out folds
    fold_start: Calibration  # start (and held values: frame, cross-axis terms) of every fold fit
    n_params: int
    order: dict[str, Any]
    extended_terms: dict[str, dict[str, Any]] | None = None  # auto only: AUTO_EXTENDED_TERMS' verdicts


def fit_order(ws: WindowSet, model: Any, start: Calibration, lab: Calibration | None,
              sigma_floor_g: float | None, folds: int) -> Fitted:
    """Choose (auto) or check (explicit) the model order, then fit it (docs/twelve-parameters.md)."""
    m = len(ws)
    if model == "auto":
        if m < AUTO_MIN_WINDOWS:
            raise OrderNotDetermined(
                f"only {m} quasi-static window(s) found: model auto needs at least {AUTO_MIN_WINDOWS} for the offsets; "
                f"need at least 6, in different postures, for sensitivities")
        d = select_order(ws, start=start, lab=lab, sigma_floor_g=SIGMA_FLOOR_G, folds=folds)
        if d.model == "none":
            why = d.reason.replace("; holding the current calibration", "")
            given = (d.evidence.get("orders") or {}).get("offsets", {}).get("predicted_given_held_mg")
            if given is not None and given <= TOL_G * 1e3:
                why += (f"; given the held sensitivities the offsets would be determined to {given:.3g} mg (the question "
                        f"`gravcal diagnose` answers, relative to them)")
            device = start.metadata.get("method") == "device_nominal" if isinstance(start.metadata, dict) else False
            advice = ("" if device else "; with little variety give a --start calibration (the sensor's nominal scale, "
                                        "or a lab calibration) so the windows are seen in g")
            raise OrderNotDetermined(f"model auto: the windows determine nothing: {why}. Record several "
                                     f"still postures (sitting, lying, bending){advice}")
        chosen = d.model
        fit_start = start if chosen == "offsets" else reference_start(chosen, start, lab)
        order = {"model": chosen, "reason": f"auto: {d.reason}", "evidence": d.evidence}
    else:
        chosen = model
        if model == "12" and lab is None:
            raise ValueError("model 12 holds the frame of a lab calibration: give lab= (gravcal calibrate --lab "
                             "--json output, --lab-calibration FILE.json), or use model 9 (frame convention R0 = I)")
        fit_start = with_frame(start, lab if model == "12" else None) if model in ("9", "12") else start
        n_params = resolve_parameterization(model, fit_start).n_params
        if m < n_params:
            raise ValueError(f"only {m} quasi-static window(s) found, need at least {n_params} for model {model!r}")
        if model in N_PARAMS:  # refused beyond Lötters' 3 % (30 mg), with what is missing; flagged beyond 10 mg
            obs = check_observable(ws, model, fit_start)
            ev = {k: v for k, v in obs.items() if not k.startswith("_")}
            reason = (f"requested (--model {model}); predicted error {obs['predicted_mg']} mg "
                      f"(amplification {obs['amplification']})")
        else:
            ev, reason = {}, f"requested (--model {model})"
        order = {"model": model, "reason": reason, "evidence": ev}
    estimator = LottersBatch(chosen, sigma_floor_g=sigma_floor_g)
    if model == "auto" and d.calibration is not None and sigma_floor_g is None:
        cal = d.calibration  # select_order's comparison fitted this order from fit_start with the same estimator
    else:
        cal = estimator.fit(ws, fit_start)
    extended_status = None
    if model == "auto":
        chosen, cal, extended_status = _auto_extended(ws, chosen, cal, lab, sigma_floor_g, folds)
        if chosen != order["model"]:
            order["reason"] += f"; {chosen[len(order['model']) + 1:]} added (" + "; ".join(
                f"{t}: {v['reason']}" for t, v in extended_status.items() if v["status"] == "chosen") + ")"
            order["model"] = chosen
            # the folds start where the base order's did (fit_start: not the full fit), terms from 0
            estimator = LottersBatch(chosen, sigma_floor_g=sigma_floor_g)
    if extended_base(chosen) in ("9", "12"):

        cal.metadata.update({"frame": frame_of(cal).tolist(), "frame_angle_deg": rotation_angle_deg(frame_of(cal)),
                             "frame_source": "lab calibration" if extended_base(chosen) == "12" else FRAME_CONVENTION})
    return Fitted(chosen, cal, estimator, fit_start, resolve_parameterization(chosen, fit_start).n_params, order,
                   extended_status)


def _extended_start(model: str, cal: Calibration, lab: Calibration | None) -> Calibration:
    """Linearisation point and held values for a fit of ``model`` (a base order or an extended one on it),
    as the online calibrator takes them: ``cal`` itself when it is a fit on the same base order, else the
    base order's reference start (order.reference_start)."""

    base = extended_base(model)
    if extended_base(cal.model) == base or base == "offsets":
        return cal
    return reference_start(base, cal, lab)


def _auto_extended(ws: WindowSet, base: str, base_cal: Calibration, lab: Calibration | None,
                   sigma_floor_g: float | None, folds: int) -> tuple[str, Calibration, dict[str, dict[str, Any]]]:
    """Model auto: add AUTO_EXTENDED_TERMS on top of the chosen order ``base`` (fitted: ``base_cal``) by the
    rule the online calibrator applies (core/estimators/online.py): testable (order.term_testability: the
    term's covariate present with its spread), observable (order.is_observable_extended: predicted error
    over orientations and the session's covariates <= 10 mg) and warranted (order.compare_extended: BIC
    *and* held-out error better than the model without it). Forward selection: each round tries every
    remaining term on top of the current model and adds the one with the lowest BIC among the warranted.
    Returns (model, its fit, {term: {"status", "reason", ...}}); status is one of "chosen", "untestable",
    "not observable", "not warranted", "not tried"."""

    status: dict[str, dict[str, Any]] = {}
    model, cal = base, base_cal
    remaining = []
    for term in AUTO_EXTENDED_TERMS:
        ok, why = term_testability(ws, term)
        if ok:
            remaining.append(term)
        else:
            status[term] = {"status": "untestable", "reason": why}
    while remaining:
        if "+" in model and lab is not None:
            # compare_extended's reference start for an extended base is the diagonal one: it would drop the
            # lab frame / lab cross-axis terms the base holds
            for term in remaining:
                status[term] = {"status": "not tried", "reason": f"with a lab calibration {term} is not compared on "
                                                                 f"top of {model} (the comparison would drop the lab frame)"}
            break
        at = _extended_start(model, cal, lab)
        round_: dict[str, dict[str, Any]] = {}
        compare = functools.partial(compare_extended, shared={})  # the round's candidates share the base's fits
        for term in remaining:
            cand = model_name(base, (*extended_terms(model), term))
            round_[term] = _judge_extended(ws, model, cand, at, lab, sigma_floor_g, folds,
                                           SIGMA_FLOOR_G, compare, is_observable_extended)
        warranted = [t for t in remaining if round_[t]["status"] == "chosen"]
        status.update({t: v for t, v in round_.items()})
        best = None
        for term in sorted(warranted, key=lambda t: round_[t]["comparison"][model_name(
                base, (*extended_terms(model), t))]["bic"]):
            cand = model_name(base, (*extended_terms(model), term))
            try:
                fit = LottersBatch(cand, sigma_floor_g=sigma_floor_g).fit(ws, _extended_start(cand, cal, lab))
            except (ValueError, np.linalg.LinAlgError) as exc:
                status[term] = {**status[term], "status": "not warranted", "reason": f"{status[term]['reason']}; "
                                                                                     f"fit failed ({exc})"}
                continue
            if not fit.converged:
                status[term] = {**status[term], "status": "not warranted",
                                "reason": f"{status[term]['reason']}; fit did not converge"}
                continue
            best = term
            model, cal = cand, fit
            break
        for term in warranted:
            if term != best and status[term]["status"] == "chosen":
                status[term] = {**status[term], "status": "not warranted",
                                "reason": f"{status[term]['reason']}; {best} explained more (lower BIC)"}
        if best is None:
            break
        remaining = [t for t in remaining if t != best and round_[t]["status"] in ("chosen", "not warranted")
                     and "fit failed" not in status[t]["reason"]]
    return model, cal, status


def _judge_extended(ws: WindowSet, model: str, cand: str, at: Calibration, lab: Calibration | None,
                    sigma_floor_g: float | None, folds: int, default_floor: float, compare_extended: Any,
                    is_observable_extended: Any) -> dict[str, Any]:
    """One candidate's verdict on top of ``model``: observable, then warranted (BIC and held-out)."""
    try:
        ok, obs = is_observable_extended(ws, at, cand)
    except (ValueError, np.linalg.LinAlgError) as exc:
        ok, obs = False, {"reason": f"observability not computable ({exc})", "predicted_mg": None}
    if not ok:
        return {"status": "untestable" if "untestable" in obs else "not observable", "reason": obs["reason"],
                "predicted_mg": obs.get("predicted_mg")}
    try:
        sc = compare_extended(ws, model, cand, at, lab=lab,
                              sigma_floor_g=sigma_floor_g if sigma_floor_g is not None else default_floor, folds=folds)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return {"status": "not warranted", "reason": f"comparison failed ({exc})", "predicted_mg": obs.get("predicted_mg")}
    sb, se = sc[model], sc[cand]
    hb, he = sb["heldout_rms_mg"], se["heldout_rms_mg"]
    better = se["bic"] < sb["bic"] and (hb is None or he is None or he < hb)
    cmp = (f"BIC {cand} {se['bic']:.1f} vs {model} {sb['bic']:.1f}" +
           ("" if hb is None or he is None else f", held-out {he:.4g} vs {hb:.4g} mg"))
    return {"status": "chosen" if better else "not warranted", "reason": cmp, "predicted_mg": obs.get("predicted_mg"),
            "comparison": sc}
