"""Why a candidate term, or one of its axes, cannot be tested on a diagnosis's windows (terms.TermSelector
``sel``), and the raw unit its parameters are stated in."""
from __future__ import annotations

from gravcal.core.estimators.observability import TOL_G
from gravcal.core.estimators.order import term_testability
from gravcal.core.model.terms import COVARIATES, calibration_view


def untestable_reason(term: str, sel, spread_deg: float) -> str | None:
    """Why ``term`` cannot be tested on these windows (None: it can): the one testability rule
    (order.term_testability), then what the base model leaves for it to act on."""
    view = calibration_view(term)
    if view.covariate == "temp" and not sel.has_temp:
        return "no temperature column in the recording"
    ok, why = term_testability(sel.ws, term)
    if not ok:
        return why
    if view.through_sensitivity and sel.base == "offsets":
        return (f"sensitivities are not observable (all {len(sel.ws)} windows within {spread_deg:.0f}° of one "
                f"direction), so a term acting through the sensitivity cannot be separated from the offsets")
    if view.acts_on == "cross" and sel.base in ("9", "12"):
        return "the base model already estimates the cross-axis terms"
    return None


def axis_reasons(sel, chosen: tuple[str, ...], term: str, unobservable: list[int],
                 confounded: list[int]) -> dict[str, str]:
    """Why each undetermined axis of ``term`` is not estimated (what it is held at: no effect)."""
    view = calibration_view(term)
    what = COVARIATES[view.covariate].label if view.covariate in COVARIATES else "these windows"
    out = {}
    keys = view.keys
    for i in unobservable:
        out[keys[i]] = (f"not observable: its effect std exceeds {TOL_G * 1e3:.0f} mg over the covered {what} range "
                        f"(for one posture: the norm does not depend on an axis across gravity to first order)")
    for i in confounded:
        if keys[i] not in out:
            out[keys[i]] = ("indistinguishable from " + (", ".join(chosen) if chosen else "the base parameters")
                            + " with these windows (orientations / covariates)")
    return out


def raw_unit(term: str) -> str:
    view = calibration_view(term)
    if view.acts_on == "cross":
        return "raw/g"
    per = {"temp": "°C", "vsupply": "V", "time": "h", "accel": "g²"}.get(view.covariate or "", "")
    return f"raw{'/g' if view.acts_on == 'sensitivity' else ''}/{per}" if per else "raw"
