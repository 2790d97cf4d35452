"""Diagnose on a recording held in one pose: each channel's temperature dependence, tested on the channels.

The term selection judges a term through the norm |a|. In one pose the norm sees a temperature change only
along gravity, through a direction that the undetermined offsets across gravity tilt: it may call
temperature_offset untestable ("indistinguishable from the base parameters") or read a projection. Each raw
channel's slope against the temperature is determined all the same (the sensor does not move), and
`gravcal calibrate` reports it (core/estimators/single_pose.py). Here diagnose asks the same question of the
same windows, so the two commands agree: the slopes with their std, kept only when each channel's reading
in contiguous held-out time folds is predicted better by a line in the temperature than by a constant (and
the slopes' chi² against none is beyond chance); what one pose does not determine is named, not printed.
"""
from __future__ import annotations

from typing import Any

from gravcal.core.calibration import Calibration
from gravcal.core.estimators.single_pose import TERM, single_pose
from gravcal.core.windows import WindowSet

from .held import one_posture_partner

PER_CHANNEL_RULE = ("one pose, per channel: found = the line in the temperature predicts each channel's reading in "
                    "held-out contiguous time folds better than a constant, and the slopes' chi² against none "
                    "exceeds chi²(3) at 0.999")


def one_pose_temperature(d: Any, ws: WindowSet, start: Calibration) -> None:
    """Where ``ws`` hold one pose and the norm-based selection did not test temperature_offset (untestable, or
    not found through the norm), test it per channel and update ``d`` (diagnose.Diagnosis) in place: a finding with the per-channel
    slopes [mg/°C] (std: statistical under the windows' covariance and the held gains' stated relative std), or
    not_found with the reason; the quantities one pose does not determine join ``d.undetermined``.
    ``start``: the calibration the slopes are converted through, with its held covariance (the gains' std)."""
    if not d.has_temp:
        return
    test = next((t for t in d.tests if t.effect == TERM), None)
    if test is None:
        return
    sp = single_pose(ws, start)
    if sp is None:
        return
    d.undetermined.update({k: v for k, v in sp.undetermined.items()
                           if k not in ("norm fit", "temperature slopes") and k not in d.undetermined})
    mag = sp.determined.get("temperature_slopes")
    if test.status == "found":  # found through the norm (its magnitude per channel already): the channels' own test
        f = next((f for f in d.findings + d.partial if f["effect"] == TERM), None)
        if f is not None:
            f["evidence"]["one_pose_per_channel"] = (
                _evidence(mag["test"]) if mag is not None else
                {"test": PER_CHANNEL_RULE, "result": sp.undetermined.get("temperature slopes", sp.reason)})
        return
    d.untestable = [u for u in d.untestable if u["effect"] != TERM]
    if mag is None:  # no span, or the slopes do not hold out better than a constant
        test.status = "not_found" if "not told from none" in sp.undetermined.get("temperature slopes", "") else "untestable"
        test.why = f"one pose, per channel: {sp.undetermined.get('temperature slopes', sp.reason)}"
        if test.status == "untestable":
            d.untestable.append({"effect": TERM, "why": test.why})
        return
    partner = one_posture_partner(TERM)
    raw = mag["raw_channel_slopes"]
    magnitude: dict[str, Any] = {
        "unit": mag["unit"], "value": mag["value"], "std": mag["std"], "std_statistical": mag["std_statistical"],
        "std_scale": mag["std_gain"], "raw_value": raw["value"], "raw_std": raw["std"], "raw_unit": raw["unit"],
        "raw_channel_slopes": raw, "method": mag["method"], "confounded_with": [partner] if partner else [],
        "notes": [f"one pose ({len(sp.windows)} windows): each channel's reading slope is determined; along gravity "
                  f"an offset change and a sensitivity change ({partner}) read alike, so the gravity channel's slope "
                  f"may be either; the absolute offsets across gravity and the sensitivities are not determined "
                  f"(named under undetermined)"]}
    ho = mag["test"]
    evidence = {**_evidence(ho), "delta_bic": None}
    test.status, test.why, test.magnitude = "found", "", magnitude
    d.findings.append({"effect": TERM, "magnitude": magnitude, "evidence": evidence})
    d.notes.append(f"one pose: {TERM} tested on each channel's reading, not through the norm (which sees it only "
                   f"along a gravity direction the undetermined offsets across gravity tilt); held-out per channel "
                   f"{ho['heldout_rms_mg_without']:.3g} → {ho['heldout_rms_mg_with']:.3g} mg; the norm-based verdict "
                   f"and extended model above do not include it")


def _evidence(ho: dict[str, Any]) -> dict[str, Any]:
    """The per-channel test's figures (single_pose's ``temperature_slopes["test"]``) as a finding's evidence."""
    return {"test": PER_CHANNEL_RULE, **{k: ho[k] for k in (
        "heldout_rms_mg_without", "heldout_rms_mg_with", "heldout_gain_mg", "heldout_scheme", "folds", "fold_rms_mg",
        "chi2", "chi2_threshold")}}
