"""What diagnose may say with confidence: a cause that earns its place on data the selection never saw, a
group when the session cannot separate two causes, and "unexplained" when the model leaves structure.

1. Earned: a term the selection chose is named only when the procedure gains by naming it on folds the
   selection never saw (NestedHeldout.term_gain_mg > 0), and only when the whole procedure gains
   (NestedHeldout.gain_mg > 0). Otherwise it is withdrawn, with its nested gain as the reason.
2. Separable: a chosen term A and a candidate B the session cannot tell apart (B in A's place explains most of
   what A explains, and either fits within ΔBIC 10 of A, or adds nothing once A is in the model: its columns
   lie in the model's span, so the split between A and B is not determined, or the selection takes B instead
   of A on at least two outer training sets) are named as a group, "A or B", with their joint
   held-out gain and the correlation of their covariates over the session; A's magnitude is given as
   conditional (its value if A alone were the cause).
3. Explained: the extended model's residual must show no structure (structure.py). When it does, or when the
   selection's nested held-out error is above the baseline's, the verdict is "unexplained" with the
   residual's structure and its size against the simulated (or the window noise); terms found are then
   reported as explaining part of the residual, not as the cause.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from gravcal.core.model.terms import calibration_view

from .noise import DELTA_BIC
from .terms import LAG_GRID_POINTS
from .structure import describe

# structure is a remainder of an explained residual when its held-out gain is below both shares: of what the named
# terms gain, and of the residual's RMS
REMAINDER_FRACTION = 0.2
RESIDUAL_FRACTION = 0.15
WORSE_FRACTION = 0.05
MIN_SWAPS = 2  # outer training sets taking a candidate instead of a chosen term: an alternative the data allow  # a nested held-out error this far above the baseline's: the selection misleads


def unearned(outer: Any, chosen: tuple[str, ...]) -> dict[str, str]:
    """Chosen terms the nested held-out error does not support -> why (rule 1)."""
    if outer is None or not chosen:
        return {}
    if not outer.gain_mg > 0:
        why = (f"withdrawn: the selection's nested held-out error is {outer.extended_mg:.3f} mg against "
               f"{outer.baseline_mg:.3f} mg for the baseline (gain {outer.gain_mg:.3f} mg <= 0 on folds it never saw)")
        return {t: why for t in chosen}
    out = {}
    for t in chosen:
        g = outer.term_gain_mg(t)
        if not g > 0:
            out[t] = (f"withdrawn: naming it gains {g:.3f} mg <= 0 on folds the selection never saw "
                      f"(selected on {sum(t in s for s in outer.selected)} of {outer.folds} outer training sets)")
    return out


def _covariate_values(ws: Any, term: str) -> np.ndarray | None:
    cov = calibration_view(term).covariate
    if cov in (None, "accel"):
        return None
    return ws.t if cov == "time" else ws.covariate(cov)


def _correlation(ws: Any, a: str, b: str) -> float | None:
    x, y = _covariate_values(ws, a), _covariate_values(ws, b)
    if x is None or y is None or np.ptp(x) == 0 or np.ptp(y) == 0:
        return None
    return float(np.corrcoef(x, y)[0, 1])


def inseparable(sel: Any, chosen: tuple[str, ...], held: dict[str, list[int]], tests: list[Any],
                outer: Any = None) -> dict[str, dict[str, Any]]:
    """Per chosen term, the candidates this session cannot tell from it (rule 2): {term: {"with": [..],
    "correlation": {other: r}}}. ``outer`` (NestedHeldout): a candidate the selection takes instead of a chosen
    term on some outer training sets is an alternative the data do not rule out."""
    out: dict[str, dict[str, Any]] = {}
    by_name = {t.effect: t for t in tests}
    for a in chosen:
        swaps = [b for s in ([] if outer is None else outer.selected) if a not in s for b in s if b not in chosen]
        instead = {b for b in swaps if swaps.count(b) >= MIN_SWAPS}
        rest = tuple(c for c in chosen if c != a)
        held_rest = {k: v for k, v in held.items() if k in rest}
        chi_without = sel.fit(rest, held_rest)[1].chi2
        chi_with = sel.fit(chosen, held)[1].chi2
        explained = chi_without - chi_with
        for b, tb in by_name.items():
            # a candidate the chosen model already spans ("indistinguishable from ...") is the plainest case
            spanned = tb.status == "untestable" and tb.why.startswith("indistinguishable from")
            if b in chosen or (tb.status == "untestable" and not spanned):
                continue
            hb = [] if spanned else ["xyz".index(x) for x in tb.undetermined_axes]
            if len(hb) == 3:
                continue
            try:
                chi_b = sel.fit(rest + (b,), {**held_rest, b: hb})[1].chi2
            except (ValueError, np.linalg.LinAlgError):
                continue
            k_b = 3 - len(hb)
            # spanned: with A in the model B adds nothing, so how much is A's and how much B's is not determined
            # a profiled term (a lag) contains simpler terms as limits and pays for its time constant: compared
            # with that price, and never grouped for being spanned (parsimony decides between nested models)
            profiled = calibration_view(b).profiled is not None
            if profiled and calibration_view(b).covariate == calibration_view(a).covariate:
                continue  # b contains a (a lag at short tau): the selection's penalised choice of a stands
            price = math.log(sel.m) + 2 * math.log(LAG_GRID_POINTS) if profiled else 0.0
            close = (spanned and not profiled) or b in instead or chi_b + price - chi_with < DELTA_BIC
            if close and chi_without - chi_b > DELTA_BIC + k_b * math.log(sel.m) and chi_without - chi_b > 0.5 * explained:
                entry = out.setdefault(a, {"with": [], "correlation": {}})
                entry["with"].append(b)
                entry["correlation"][b] = _correlation(sel.ws, a, b)
    return out


def group_text(a: str, group: dict[str, Any], joint_gain_mg: float | None) -> str:
    names = " or ".join([a] + group["with"])
    rs = [f"r = {r:.4f}" for r in group["correlation"].values() if r is not None]
    why = f"correlation {', '.join(rs)} over the session" if rs else "their columns are nearly the same here"
    gain = "" if joint_gain_mg is None else f", together they gain {joint_gain_mg:.3f} mg on held-out folds"
    return f"{names}: not separable in this session ({why}){gain}"


def unexplained(structures: list[dict[str, Any]], resid_mg: float, reference_mg: float | None, reference: str,
                outer: Any, had_findings: bool, gain_mg: float | None) -> dict[str, Any]:
    """The verdict (rule 3): {"status": "explained" | "unexplained" | "nothing found", "text", "structure",
    "ratio", "reference"}. ``gain_mg``: the delivered model's held-out gain over the baseline (None: not
    measured). Structure whose held-out gain is below REMAINDER_FRACTION of what the named terms gain and below
    RESIDUAL_FRACTION of the residual's RMS is a remainder of an explained residual (said, with its size), not a
    verdict against them."""
    present = [s for s in structures if s["present"]]
    material = [s for s in present if s.get("replaces") or not (gain_mg and gain_mg > 0)
                or s["heldout_gain_mg"] >= REMAINDER_FRACTION * gain_mg or s["heldout_gain_mg"] >= RESIDUAL_FRACTION * resid_mg]
    worse = outer is not None and had_findings and outer.extended_mg > (1 + WORSE_FRACTION) * outer.baseline_mg
    ratio = None if not reference_mg else resid_mg / reference_mg
    out: dict[str, Any] = {"structure": structures, "residual_rms_mg": round(resid_mg, 4),
                           "reference_rms_mg": None if reference_mg is None else round(reference_mg, 4),
                           "reference": reference, "ratio": None if ratio is None else round(ratio, 2)}
    size = "" if ratio is None else f", {ratio:.1f}× the {reference}"
    if material or worse:
        parts = [describe(s) for s in material[:2]]
        if worse:
            parts.append(f"the extended model is worse than the baseline on folds the selection never saw "
                         f"({outer.extended_mg:.3f} vs {outer.baseline_mg:.3f} mg)")
        out.update(status="unexplained", text=f"unexplained: {'; '.join(parts)}{size}")
    else:
        rest = "; ".join(f"{describe(s)} ({s['structure_rms_mg']:.3g} mg RMS, held-out gain {s['heldout_gain_mg']:.3g} mg)"
                         for s in present)
        out.update(status="explained" if had_findings else "nothing found",
                   text=(f"remainder: {rest}{size}" if rest else f"no structure left in the residual{size}"))
    return out
