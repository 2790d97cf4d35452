"""The diagnose procedure: what the baseline simulation gets wrong on a recording, the cause, the extension, the gain.

    a. windows (core.pipeline.calibrate_recording's detector and screening), baseline = the
       simulator's default terms at calibration level (6 parameters; offsets only when the
       sensitivities are not observable: order.select_order's rule), held-out error;
    b. window-level re-simulation with the fitted baseline and the measured noise; statistics
       compared (compare.py); Allan deviation of static stretches vs white noise;
    c. catalogue terms tested (terms.py: observable, ΔBIC > 10, held-out lower); colored_noise and
       quantization on the static samples (noise.py);
    d. extended model = base + found terms, refit, held-out gain, re-simulated comparison;
    e. a JSON-able result (Diagnosis.to_json_dict).
"""
from __future__ import annotations

import dataclasses

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gravcal.core.calibration import Calibration
from gravcal.core.estimators.extended import EXTRA_TERMS, extended_residuals_g
from gravcal.core.estimators.consider import HELD_KEY
from gravcal.core.estimators.lotters import LottersBatch
from gravcal.core.estimators.observability import TOL_G, coverage, held_note, is_observable
from gravcal.core.estimators.order import select_order
from gravcal.core.estimators.parameterization import PARAMETERIZATIONS
from gravcal.core.model.terms import CATALOGUE as TERM_CATALOGUE
from gravcal.core.model.terms import CALIBRATION_TERMS, REGISTRY, calibration_view, term_spec
from gravcal.core.windows import WindowSet

from .compare import Comparison, simulate_compare
from .noise import AllanResult, flat_stretches
from .held import channel_slopes, held_contributions, one_posture_magnitude, one_posture_partner, scale_rel_std
from .one_pose import one_pose_temperature
from .sample_tests import SAMPLE_TESTS
from .standin import stand_ins
from .structure import residual_structure
from .terms import TermSelector, TermTest, evaluate_term, select_terms
from .verdict import group_text, inseparable, unearned, unexplained

log = logging.getLogger(__name__)

CATALOGUE: tuple[str, ...] = tuple(sorted(TERM_CATALOGUE, key=lambda c: (
    CALIBRATION_TERMS.index(TERM_CATALOGUE[c]) if TERM_CATALOGUE[c] in CALIBRATION_TERMS else len(CALIBRATION_TERMS))))
"""The effects diagnose tests (the registry's catalogue): window-mean terms in canonical order, then noise."""
OUTLIER_SIGMA = 6.0  # robust (MAD) std of the baseline residual beyond which a window is excluded
DOMINANT_POSTURE_DEG = 20.0  # offsets-only baseline: term tests on windows this close to the dominant posture
MIN_WINDOWS = 8  # fewer quasi-static windows: nothing can be tested
SINGLE_POSE_DEG = 3.0  # windows within this of one direction: one pose, each channel's slope is the term's


@dataclass
class Diagnosis:
    base_model: str
    extended_model: str
    n_windows: int
    baseline_heldout_mg: float | None
    extended_heldout_mg: float | None
    baseline_insample_mg: float
    extended_insample_mg: float
    findings: list[dict[str, Any]]
    untestable: list[dict[str, str]]
    tests: list[TermTest]
    baseline_cal: Calibration
    extended_cal: Calibration
    compare_baseline: Comparison | None
    compare_extended: Comparison | None
    allan: AllanResult | None
    coverage: dict[str, Any]
    floor_mg: float
    notes: list[str] = field(default_factory=list)
    windows: WindowSet | None = None
    resid_baseline_g: np.ndarray | None = None
    resid_extended_g: np.ndarray | None = None
    has_temp: bool = False
    white_g: np.ndarray | None = None
    observability: dict[str, Any] | None = None  # the offsets by order.is_observable, as `gravcal calibrate` judges them
    nested: "NestedHeldout | None" = None  # the held-out errors above: folds the selection never saw
    selection_heldout_mg: tuple[float | None, float | None] | None = None  # the selection's own inner folds
    verdict: dict[str, Any] = field(default_factory=dict)  # explained / unexplained / nothing found (verdict.py)
    partial: list[dict[str, Any]] = field(default_factory=list)  # terms that explain part of an unexplained residual
    undetermined: dict[str, str] = field(default_factory=dict)  # calibration quantities these windows do not determine
    structure_curves: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # for the report's plot

    @property
    def heldout_gain_mg(self) -> float | None:
        if self.baseline_heldout_mg is None or self.extended_heldout_mg is None:
            return None
        return self.baseline_heldout_mg - self.extended_heldout_mg

    def _calibration_dict(self) -> dict[str, Any]:
        return _withheld(self.extended_cal.to_dict(), self.undetermined)

    def to_json_dict(self) -> dict[str, Any]:
        r = lambda x: None if x is None or not math.isfinite(x) else round(float(x), 4)  # noqa: E731
        return {
            "verdict": self.verdict,
            "findings": self.findings,
            "partial": self.partial,
            "observability": self.observability,
            "baseline": {"model": self.base_model, "heldout_rms_mg": r(self.baseline_heldout_mg),
                         "insample_rms_mg": r(self.baseline_insample_mg),
                         "simulation": None if self.compare_baseline is None else self.compare_baseline.to_dict()},
            "extended": {"model": self.extended_model, "heldout_rms_mg": r(self.extended_heldout_mg),
                         "insample_rms_mg": r(self.extended_insample_mg),
                         "heldout_gain_mg": r(self.heldout_gain_mg),
                         "heldout_scheme": None if self.nested is None else self.nested.to_dict(),
                         "selection_heldout_rms_mg": None if self.selection_heldout_mg is None else
                         [r(x) for x in self.selection_heldout_mg],
                         "calibration": self._calibration_dict(),
                         "simulation": None if self.compare_extended is None else self.compare_extended.to_dict()},
            "untestable": self.untestable,
            "undetermined": self.undetermined,
            "not_found": [{"effect": t.effect, "why": t.why, "evidence": t.evidence()} for t in self.tests
                          if t.status == "not_found"],
            "n_windows": self.n_windows,
            "coverage": self.coverage,
            "quasi_static_floor_mg": r(self.floor_mg),
            "allan": None if self.allan is None else self.allan.to_dict(),
            "notes": self.notes,
        }


def _withheld(cal_dict: dict[str, Any], undetermined: dict[str, str]) -> dict[str, Any]:
    """A calibration's dict with the std of every quantity the windows do not determine withheld (null)."""
    std = cal_dict.get("std")
    if isinstance(std, dict):
        cal_dict["std"] = {k: (None if k in undetermined else v) for k, v in std.items()}
    cal_dict["undetermined"] = dict(undetermined)
    return cal_dict


def sensor_model_term(effect: str, magnitude: dict[str, Any]) -> dict[str, Any] | None:
    """The finding as a term of the sensor model (core/model; channels ax, ay, az, ax2 = x, y, z, x);
    None for a term whose view has no forward counterpart."""
    spec = term_spec(effect)
    return None if spec.sensor_term is None else spec.sensor_term(magnitude.get("value", {}))


def offsets_observability(ws: WindowSet, start: Calibration) -> dict[str, Any]:
    """The offsets judged by THE observability rule (order.is_observable at the start with its held
    uncertainty), as `gravcal calibrate --model auto` judges them: determined absolutely, or only given
    the held sensitivities (what the term tests are relative to), with the numbers and why."""
    ok, obs = is_observable(ws, start, "offsets")
    out = {"determined": ok, "predicted_mg": obs["predicted_mg"], "given_held_mg": obs["predicted_given_held_mg"],
           "reason": ""}
    if not ok:
        pred = "unbounded" if obs["predicted_mg"] is None else f"{obs['predicted_mg']:.3g} mg"
        out["reason"] = (f"the absolute offsets are not determined (predicted error {pred} > "
                         f"{TOL_G * 1e3:.0f} mg; {held_note(obs) or 'too few postures'}): `gravcal calibrate` does not "
                         f"fit them (in one pose it returns each channel's temperature slope, else it refuses); given the held sensitivities the offsets are determined to "
                         f"{obs['predicted_given_held_mg']} mg, and the terms here are judged relative to them")
    return out


def _static_stretches(ws: WindowSet, max_gap: int) -> list[tuple[int, int]]:
    """Consecutive windows (gap <= max_gap samples) merged into static stretches (start, end)."""
    order = np.argsort(ws.start)
    out: list[list[int]] = []
    for i in order:
        s, e = int(ws.start[i]), int(ws.end[i])
        if out and s - out[-1][1] <= max_gap:
            out[-1][1] = max(out[-1][1], e)
        else:
            out.append([s, e])
    return [(a, b) for a, b in out]


GIVEN_HELD_NOTE = ("terms judged given the start's sensitivities; the absolute offsets also carry the "
                   "sensitivities' uncertainty (see gravcal calibrate)")


def given_held(start: Calibration) -> Calibration:
    """``start`` without its held-parameter uncertainty.

    Diagnosis asks whether a baseline's residuals follow a term (temperature, time, ...): a question
    relative to the baseline. The held sensitivities' absolute uncertainty (the consider term of the
    calibration's own std) is common to every model compared, so order and terms are judged given
    them, as Lötters' offsets-only mode takes the sensitivities as known."""
    return dataclasses.replace(start, metadata={k: v for k, v in start.metadata.items() if k != HELD_KEY})


def diagnose_windows(ws: WindowSet, start: Calibration, *, has_temp: bool, candidates: tuple[str, ...] = CATALOGUE,
                     replicas: int = 40, folds: int = 5, seed: int = 0, base: str | None = None,
                     simulate: bool = True, nested: bool = True,
                     held_uncertainty: dict[str, Any] | None = None) -> Diagnosis:
    """Steps a-e on quasi-static windows alone (no sample-level noise tests: colored_noise and
    quantization are reported untestable). ``nested`` False skips the held-out gain on folds the
    selection never saw (the selection itself is unchanged; for repeated statistical runs).
    ``held_uncertainty``: the held covariance (consider.HELD_KEY) of the start's held sensitivities when
    ``start`` no longer states it; it widens the findings' std (held.py), never the tests."""
    notes: list[str] = []
    held_meta = start.metadata.get(HELD_KEY, held_uncertainty) if isinstance(start.metadata, dict) else held_uncertainty
    if HELD_KEY in start.metadata:
        start = given_held(start)
        notes.append(GIVEN_HELD_NOTE)
    no_temp = int(np.sum(~np.isfinite(ws.aux[:, 0]))) if has_temp and ws.aux.ndim == 2 and ws.aux.shape[1] else 0
    if no_temp:  # a NaN temperature would reach the covariate regressions' least squares (LAPACK)
        has_temp = False
        notes.append(f"{no_temp} of {len(ws)} windows carry no temperature (the temp channel read no value): "
                     f"temperature terms untestable")
    # a lagged covariate runs over every window's input, excluded or held out alike
    history = (ws.t.copy(), ws.aux[:, 0].copy()) if has_temp else None
    if len(ws) < MIN_WINDOWS:
        raise ValueError(f"only {len(ws)} quasi-static window(s): need at least {MIN_WINDOWS} to fit a baseline and "
                         f"test any term (record longer, with still moments)")
    if base is None:
        dec = select_order(ws, start=start, candidates=("offsets", "6"), compare=False)
        base = "6" if dec.model == "6" else "offsets"
        if dec.model == "none":
            raise ValueError(f"not even the offsets are determined by these windows: {dec.reason}")
        if base == "offsets":
            notes.append(f"baseline: offsets only ({dec.reason})")
    base_cal = LottersBatch(base).fit(ws, start)
    if not base_cal.converged:
        raise ValueError(f"the baseline fit ({base}) did not converge: {base_cal.message}")
    # windows the baseline misses by far more than the rest (handling, a posture change inside the window,
    # unobservable sensitivities at a rare posture) would dominate every chi² and held-out fold: excluded
    r0 = 1.0 - np.linalg.norm(base_cal.apply(ws.mean), axis=1)
    mad = 1.4826 * float(np.median(np.abs(r0 - np.median(r0))))
    out = np.abs(r0 - np.median(r0)) > OUTLIER_SIGMA * max(mad, 1e-6)
    if out.any() and len(ws) - int(out.sum()) >= MIN_WINDOWS:
        notes.append(f"excluded {int(out.sum())} of {len(ws)} window(s) whose baseline norm error exceeds "
                     f"{OUTLIER_SIGMA:g} robust std ({OUTLIER_SIGMA * mad * 1e3:.3g} mg) from the term tests")
        ws = ws.subset(np.flatnonzero(~out))
        base_cal = LottersBatch(base).fit(ws, base_cal)
    ws_base = ws
    if base == "offsets":
        # sensitivities unobservable: windows at rare postures carry the scale error of the held K, which no
        # offset-type term can explain; test the terms where an offsets-only baseline is valid
        a = base_cal.apply(ws.mean)
        u = a / np.linalg.norm(a, axis=1, keepdims=True)
        c = np.median(u, axis=0)
        c /= np.linalg.norm(c)
        near = np.degrees(np.arccos(np.clip(u @ c, -1, 1))) <= DOMINANT_POSTURE_DEG
        if (~near).any() and int(near.sum()) >= MIN_WINDOWS:
            notes.append(f"sensitivities unobservable: terms tested on the {int(near.sum())} windows within "
                         f"{DOMINANT_POSTURE_DEG:g}° of the dominant posture ({int((~near).sum())} others excluded)")
            ws = ws.subset(np.flatnonzero(near))  # base_cal stays the fit on all windows (offsets determined)
    cov = coverage(ws, base_cal)
    sel = TermSelector(ws, base, base_cal, has_temp=has_temp, folds=folds, lag_history=history)
    chosen, held, tests = select_terms(sel, tuple(c for c in candidates if c in EXTRA_TERMS), cov["spread_deg"])
    p_max = sel.par(tuple(t.effect for t in tests if t.status != "untestable")).n_params
    selected_all = chosen
    sel_ho = (sel.heldout_mg((), {}, p_max), sel.heldout_mg(chosen, held, p_max) if chosen else None)
    outer = nested_heldout(ws, base, base_cal, has_temp=has_temp, candidates=candidates,
                           spread_deg=cov["spread_deg"], folds=folds, held_base=sel.held_base,
                           lag_history=history) if nested else None
    withdrawn = unearned(outer, chosen)
    a0 = base_cal.apply(ws.mean)
    replaced, stood_in = stand_ins(sel, tuple(c for c in chosen if c not in withdrawn), held,
                                   a0 / np.linalg.norm(a0, axis=1, keepdims=True))
    withdrawn.update(stood_in)  # a shape outside the catalogue fits better in their place (standin.py)
    if withdrawn:  # named only what earns its place on folds the selection never saw (verdict.py, rule 1)
        chosen = tuple(c for c in chosen if c not in withdrawn)
        held = {k: v for k, v in held.items() if k in chosen}
        for i, t in enumerate(tests):
            if t.effect in withdrawn:
                t.status, t.why = "not_found", withdrawn[t.effect]
            elif t.effect in chosen:  # its magnitude given the terms still named
                others, held_o = tuple(c for c in chosen if c != t.effect), {k: v for k, v in held.items() if k != t.effect}
                tests[i] = evaluate_term(sel, others, held_o, t.effect, ["xyz".index(x) for x in t.undetermined_axes],
                                         p_max)
                tests[i].status, tests[i].why = "found", ""
    if outer is None:
        ho_b = ho_e = None
        if nested:
            notes.append(f"{len(ws)} windows are too few for a held-out gain on folds the selection never saw")
    else:
        ho_b, ho_e = outer.baseline_mg, (outer.extended_without(withdrawn) if withdrawn else outer.extended_mg)
    groups = inseparable(sel, chosen, held, tests, outer)
    par_b, fit_b = sel.fit((), {})
    par_e, fit_e = sel.fit(chosen, held)
    res_b = extended_residuals_g(par_b, fit_b.p, ws)
    res_e = extended_residuals_g(par_e, fit_e.p, ws)
    cmp_b = cmp_e = None
    if simulate:
        cmp_b = simulate_compare(par_b, fit_b.p, ws, sel.var0 + 0.0, res_b, has_temp=has_temp, replicas=replicas, seed=seed)
        cmp_e = simulate_compare(par_e, fit_e.p, ws, sel.var0 + 0.0, res_e, has_temp=has_temp, replicas=replicas,
                                 seed=seed + 1, free=sel.free_mask(sel.par(chosen), held)) if chosen else cmp_b
    ext_cal = fit_e.calibration(len(ws))
    a = ext_cal.apply_reference(ws.mean)
    u = a / np.linalg.norm(a, axis=1, keepdims=True)
    structures, curves = residual_structure(ws, res_e, u, sel.var, has_temp=has_temp)
    for s in replaced[::-1]:
        curves[s["covariate"]] = s.pop("curve")
    structures = replaced + [s for s in structures if s["covariate"] not in {r["covariate"] for r in replaced}]
    rms_e = float(np.sqrt(np.mean(res_e**2)) * 1e3)
    ref_mg, ref_name = ((cmp_e.simulated_mean["rms_mg"], "simulated") if cmp_e is not None else
                        (float(np.sqrt(np.mean(sel.var0)) * 1e3), "window noise"))
    verdict = unexplained(structures, rms_e, ref_mg, ref_name, outer, bool(selected_all),
                          None if ho_b is None or ho_e is None else ho_b - ho_e)
    verdict["withdrawn"] = [{"effect": k, "why": v} for k, v in withdrawn.items()]
    # every tested magnitude carries what the fit held, named or not (its std does not depend on the selection)
    scored = {t.effect: ["xyz".index(a) for a in t.undetermined_axes] for t in tests
              if t.status == "not_found" and t.magnitude.get("std")}
    held_sd, held_sources = held_contributions(sel, chosen, held, base=base, base_cal=base_cal, ws_base=ws_base,
                                               start=start, held_meta=held_meta, also=scored)
    findings, partial = [], []
    for t in tests:
        if t.effect in scored:
            fold_held_std(t.magnitude, held_sd.get(t.effect), held_sources)
        if t.status == "found":
            honest_magnitude(t, held_sd.get(t.effect), held_sources, one_posture=base == "offsets", ws=ws,
                             scale=np.abs(np.diag(base_cal.sensitivity)), scale_rel_std=scale_rel_std(held_meta, start),
                             spread_deg=cov["spread_deg"])
            ev = t.evidence()
            if outer is not None:
                ev["nested_heldout_gain_mg"] = round(outer.term_gain_mg(t.effect), 4)
            term = sensor_model_term(t.effect, t.magnitude)
            if term:
                ev["sensor_model_term"] = term
            f = {"effect": t.effect, "magnitude": t.magnitude, "evidence": ev}
            if t.effect in groups:
                name_group(f, groups[t.effect], ev.get("nested_heldout_gain_mg"))
            (partial if verdict["status"] == "unexplained" else findings).append(f)
            for partner in t.magnitude.get("confounded_with", []):
                notes.append(f"{t.effect} and {partner} cannot be told apart on this recording (one posture): "
                             f"{t.effect} is reported, the change along gravity may be either")
    if partial:
        notes.append(f"{verdict['text']}: {', '.join(f['effect'] for f in partial)} explain(s) part of the residual "
                     f"and is not named as its cause (its value is the best fit of an effect the catalogue does not "
                     f"describe)")
    untestable = [{"effect": t.effect, "why": t.why} for t in tests if t.status == "untestable"]
    d = Diagnosis(base, ext_cal.model, len(ws), ho_b, ho_e, float(np.sqrt(np.mean(res_b**2)) * 1e3),
                  rms_e, findings, untestable, tests, base_cal, ext_cal,
                  cmp_b, cmp_e, None, cov, sel.floor_g * 1e3, notes, ws, res_b, res_e, has_temp)
    d.verdict, d.partial = verdict, partial
    d.structure_curves = curves
    base_names = PARAMETERIZATIONS[base](base_cal.sensitivity, base_cal.offset).names
    d.undetermined = {base_names[j]: "held at the all-window baseline: these windows do not determine it (one "
                      "posture: an offset across gravity does not change the norm to first order)" for j in sel.held_base}
    if base == "offsets":
        d.undetermined.update({f"s_{a}": "held at the start: the sensitivities need several postures" for a in "xyz"})
    for term, axes in held.items():  # a named term's axes the windows do not determine: held at 0 in the model
        names = calibration_view(term).param_names()
        d.undetermined.update({names[i]: f"{term} {'xyz'[i]}: held at 0 in the extended calibration (not determined "
                                         f"by these windows; the finding states what is known)" for i in axes})
    d.nested = outer
    d.selection_heldout_mg = sel_ho
    return d


def honest_magnitude(tt: TermTest, held_sd: np.ndarray | None, sources: list[str], *, one_posture: bool,
                     ws: WindowSet, scale: np.ndarray | None = None, scale_rel_std: np.ndarray | None = None,
                     spread_deg: float = 180.0) -> None:
    """Fold the held quantities' contribution into a found term's stated std (report and raw units). With an
    offsets-only baseline: in one pose (every window within ``spread_deg`` <= SINGLE_POSE_DEG of one direction)
    the magnitude is each channel's own slope (held.one_posture_magnitude: ``scale`` [raw/g] and its relative
    std convert it); with tilts about one dominant posture the norm's change along gravity, the partner named."""
    mag = tt.magnitude
    fold_held_std(mag, held_sd, sources)
    partner = one_posture_partner(tt.effect) if one_posture else None
    if partner is None:
        return
    if spread_deg <= SINGLE_POSE_DEG:
        one_posture_magnitude(tt, ws, scale, scale_rel_std)
        return
    # one dominant posture with tilts: a channel across gravity moves with the tilt, so its slope is not the
    # term's; the value is the norm's change along gravity, and the axes across gravity are not determined
    mag["confounded_with"] = [partner]
    slopes = channel_slopes(ws, calibration_view(tt.effect).covariate)
    if slopes is not None:
        mag["raw_channel_slopes"] = slopes
    across = sorted(mag.get("undetermined", {}))
    mag.setdefault("notes", []).append(
        f"one dominant posture: an offset change and a sensitivity change along gravity ({partner}) read alike; "
        f"the value along gravity is their sum; " + (f"{', '.join(across)} not determined (across gravity)" if across
                                                    else "the axes across gravity are determined through the tilts "
                                                         "about the posture"))


def fold_held_std(mag: dict[str, Any], held_sd: np.ndarray | None, sources: list[str]) -> None:
    """Root-sum-square the held quantities' (6,) contribution ``held_sd`` (report x3, raw x3) into a magnitude's
    std and raw std, keeping the fit's own as ``std_noise``."""
    if held_sd is None or not sources:
        return
    keys = list(mag.get("value", {}))
    mag["std_noise"] = dict(mag.get("std", {}))
    mag["std_held"] = {k: (None if mag["value"][k] is None else float(held_sd[i])) for i, k in enumerate(keys)}
    for std_key, off in (("std", 0), ("raw_std", 3)):
        d = mag.get(std_key, {})
        for i, k in enumerate(keys):
            if d.get(k) is not None:
                d[k] = float(np.hypot(d[k], held_sd[off + i]))
    mag["held"] = list(sources)


def name_group(f: dict[str, Any], group: dict[str, Any], joint_gain_mg: float | None) -> None:
    """A finding the session cannot separate from other candidates: named as the group; its magnitude is what
    it would be if it alone were the cause (said so: the session cannot apportion the effect)."""
    text = group_text(f["effect"], group, joint_gain_mg)
    f["group"] = {"effects": [f["effect"]] + group["with"], "correlation": group["correlation"],
                  "joint_heldout_gain_mg": joint_gain_mg, "text": text}
    f["magnitude"]["conditional"] = (f"the value if {f['effect']} alone were the cause: this session cannot apportion "
                                     f"the effect between {' and '.join(f['group']['effects'])}")


@dataclass
class NestedHeldout:
    """Held-out error on folds the selection never saw: per contiguous outer fold, the whole selection
    (forward and backward, its own inner folds) runs on the other folds; baseline and selected model are
    fitted there and scored on the outer fold."""

    baseline_mg: float
    extended_mg: float
    folds: int
    selected: list[list[str]]  # the terms selected on each outer training set
    runs: list[tuple] = field(default_factory=list, repr=False)  # per fold (selector, chosen, held, test windows)
    resid_extended: np.ndarray | None = field(default=None, repr=False)

    @property
    def gain_mg(self) -> float:
        return self.baseline_mg - self.extended_mg

    def extended_without(self, terms: set[str] | tuple[str, ...]) -> float:
        """The procedure's held-out RMS [mg] when it never names ``terms``: on each outer fold whose selection
        chose one of them, the rest of that selection refitted on the training folds and scored on the fold."""
        res = self.resid_extended.copy()
        for sel, chosen, held, test, wte in self.runs:
            if not set(chosen) & set(terms):
                continue
            keep = tuple(c for c in chosen if c not in terms)
            par, f = sel.fit(keep, {k: v for k, v in held.items() if k in keep})
            res[test] = extended_residuals_g(par, f.p, wte)
        return float(np.sqrt(np.mean(res * res)) * 1e3)

    def term_gain_mg(self, term: str) -> float:
        """What naming ``term`` gains on folds the selection never saw (0 when no outer selection names it)."""
        return self.extended_without((term,)) - self.extended_mg

    def to_dict(self) -> dict[str, Any]:
        return {"baseline_rms_mg": round(self.baseline_mg, 4), "extended_rms_mg": round(self.extended_mg, 4),
                "gain_mg": round(self.gain_mg, 4), "folds": self.folds, "selected_per_fold": self.selected,
                "scheme": "contiguous time blocks; selection re-run on each training set"}


def nested_heldout(ws: WindowSet, base: str, base_cal: Calibration, *, has_temp: bool, candidates: tuple[str, ...],
                   spread_deg: float, folds: int = 5, held_base: list[int] | None = None,
                   lag_history: tuple[np.ndarray, np.ndarray] | None = None) -> NestedHeldout | None:
    """The held-out gain of the selection procedure itself (NestedHeldout); None when the training sets are too
    small for the inner folds. The base parameters are refitted on each training set from ``base_cal``, except
    ``held_base``, the ones the whole recording does not determine (kept at base_cal's values, as in the
    selection: left free on a subset they would turn the direction and absorb a trend). ``lag_history``: every
    window's (t, temperature), which a lagged term runs over on training and held-out windows alike."""
    k = min(folds, len(ws) // MIN_WINDOWS)
    if k < 2:
        return None
    order = np.argsort(ws.t, kind="stable")
    res_b, res_e = np.empty(len(ws)), np.empty(len(ws))
    selected, runs = [], []
    for test in np.array_split(order, k):
        train = np.setdiff1d(order, test)
        wtr = ws.subset(train)
        try:
            sel = TermSelector(wtr, base, base_cal, has_temp=has_temp, folds=folds, held_base=held_base,
                               lag_history=lag_history)
            chosen, held, _ = select_terms(sel, tuple(c for c in candidates if c in EXTRA_TERMS), spread_deg,
                                           report=False)
            par_b, f_b = sel.fit((), {})
            par_e, f_e = sel.fit(chosen, held)
        except (ValueError, np.linalg.LinAlgError):
            return None
        wte = ws.subset(test)
        res_b[test] = extended_residuals_g(par_b, f_b.p, wte)
        res_e[test] = extended_residuals_g(par_e, f_e.p, wte)
        selected.append(list(chosen))
        runs.append((sel, chosen, held, test, wte))
    rms = lambda r: float(np.sqrt(np.mean(r * r)) * 1e3)  # noqa: E731
    return NestedHeldout(rms(res_b), rms(res_e), k, selected, runs, res_e)


def diagnose(t: np.ndarray, raw: np.ndarray, *, temp: np.ndarray | None = None, vsupply: np.ndarray | None = None,
             fs: float | None = None, candidates: tuple[str, ...] = CATALOGUE, replicas: int = 40, folds: int = 5,
             seed: int = 0, simulate: bool = True, start: Calibration | None = None) -> Diagnosis:
    """Diagnose a recording: t (N,) [s], raw (N, 3) [raw units], temp (N,) [°C] and vsupply (N,) [V] or None;
    ``start``: the device's own calibration or nominal scale (io.offline.device_start_of), else a bootstrap."""
    from gravcal.core.pipeline import calibrate_recording, data_start  # noqa: PLC0415

    t = np.asarray(t, dtype=float)
    raw = np.asarray(raw, dtype=float)
    if raw.ndim != 2 or raw.shape[1] != 3 or t.shape != (raw.shape[0],):
        raise ValueError(f"need t (N,) and raw (N, 3); got {t.shape} and {raw.shape}")
    notes: list[str] = []
    for i, name in enumerate(("ax", "ay", "az")):
        if np.ptp(raw[:, i]) == 0:
            raise ValueError(f"channel {name} is constant ({raw[0, i]:g} in every sample): a dead or disconnected "
                             f"channel; nothing can be calibrated or diagnosed")
    if temp is not None:
        temp = np.asarray(temp, dtype=float)
        if np.ptp(temp) == 0:
            notes.append(f"the temperature column is constant ({temp[0]:g} °C): temperature terms untestable")
    flats = flat_stretches(raw)
    fs = float(fs) if fs else 1.0 / float(np.median(np.diff(t[: 100_000])))
    if flats.runs:
        # idle-sleep / frozen output: zero variance that is not stillness (it would also fool the detector's
        # noise level); the rows are removed, time keeps its gap
        notes.append(f"{len(flats.runs)} stretch(es) of exactly repeated samples ({flats.n_samples} samples, longest "
                     f"{max(b - a for a, b in flats.runs)}, first at t = {t[flats.runs[0][0]]:.3f} s): idle-sleep / "
                     f"frozen output, not real stillness (chance repeat rate {flats.repeat_prob:.3g} per sample); "
                     f"removed before detection")
        keep = np.ones(raw.shape[0], dtype=bool)
        for a, b in flats.runs:
            keep[a + 1:b] = False  # the first sample of a run is a real one
        t, raw = t[keep], raw[keep]
        temp = None if temp is None else temp[keep]
        vsupply = None if vsupply is None else np.asarray(vsupply)[keep]
    held_start = start0 = start if start is not None else data_start(t, raw, fs)
    if HELD_KEY in start0.metadata:
        start0 = given_held(start0)
        notes.append(GIVEN_HELD_NOTE)
    rep = calibrate_recording(t, raw, temp=temp, vsupply=vsupply, model="offsets", fs=fs, start=start0)
    ws = rep.windows
    has_temp = temp is not None and bool(np.any(np.isfinite(temp))) and np.ptp(temp[np.isfinite(temp)]) > 0
    d = diagnose_windows(ws, rep.start or rep.calibration, has_temp=has_temp, candidates=candidates,
                         replicas=replicas, folds=folds, seed=seed, simulate=simulate,
                         held_uncertainty=held_start.metadata.get(HELD_KEY))
    d.observability = offsets_observability(ws, held_start)
    if not d.observability["determined"]:
        notes.append(d.observability["reason"])
    d.notes = notes + d.notes
    one_pose_temperature(d, ws, held_start)  # the norm cannot test it in one pose; each channel can
    # noise tests on static stretches, on the residual after the deterministic terms: each sample corrected by
    # the extended calibration at its own temperature, supply and time (a temperature or drift term left in
    # the samples would read as colored noise), the stretch mean removed
    scale = np.abs(np.diag(d.baseline_cal.sensitivity))
    stretches = _static_stretches(ws, max_gap=int(0.5 * fs))
    parts_raw = [raw[a:b] for a, b in stretches]
    parts_g = []
    for a, b in stretches:
        g = d.extended_cal.apply(raw[a:b], temp=None if temp is None else temp[a:b], t=t[a:b],
                                 vsupply=None if vsupply is None else np.asarray(vsupply)[a:b])
        parts_g.append(g - g.mean(axis=0))
    longest = max((p.shape[0] for p in parts_g), default=0) / fs
    extra_tests: list[TermTest] = []
    for spec in REGISTRY.values():
        if spec.sample_test is not None and spec.catalogue_name in candidates:
            tt = SAMPLE_TESTS[spec.sample_test](spec.catalogue_name, parts_raw, parts_g, scale, fs, longest)
            if getattr(tt, "_allan", None) is not None:
                d.allan = tt._allan  # type: ignore[attr-defined]  # the pooled Allan deviation, for the report
            extra_tests.append(tt)
    for tt in extra_tests:
        d.tests.append(tt)
        if tt.status == "found":
            ev = {"delta_bic": tt.delta_bic, "delta_bic_threshold": 10.0, **getattr(tt, "_extra", {})}
            # beside an unexplained slow residual, colored noise may be that residual: part of it, not a cause
            (d.partial if d.verdict.get("status") == "unexplained" else d.findings).append(
                {"effect": tt.effect, "magnitude": tt.magnitude, "evidence": ev})
        elif tt.status == "untestable":
            d.untestable.append({"effect": tt.effect, "why": tt.why})
    if d.allan is not None:
        d.white_g = d.allan.white_g
    return d
