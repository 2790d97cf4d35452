"""The verdict on one recording's calibration: a status and the reason, always.

Statuses (``STATUSES``):

* ok — the calibration is returned as good: converged, observable, its held-out error (contiguous
  folds, core.heldout) no worse than every lower order the windows determine and than no calibration;
* partial — as ok, but only the offsets are updated (the sensitivities are held at the start): what
  the data determine;
* not_improved — no fitted order holds out better than no calibration (the start, when it did not
  come from these data): the start is returned, unchanged;
* unreliable — a calibration was fitted but is not to be trusted: not converged, not observable, its
  held-out error far above its in-sample error (an overfit), or (an order the user asked for) a lower
  order holds out better;
* refused — the windows determine nothing (no stillness, too few windows, one posture): the start is
  returned, unchanged.

Model auto never returns as good an order whose held-out error is worse than a lower order's
(offsets < 6 < 9 / 12; an order with extended terms against its base): ``guard`` falls back to the
order with the lowest held-out error, and says so.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .calibration import Calibration
from .estimators.observability import ORDER_LADDER, TOL_G
from .heldout import HeldoutResult, norm_error_mg
from .windows import WindowSet

STATUSES = ("ok", "partial", "not_improved", "unreliable", "refused")
TRUSTED = ("ok", "partial")  # exit 0; every other status exits 3 with the JSON
# held-out error "far above" in-sample: more than this ratio AND above the auto tolerance (10 mg). A sound
# fit holds out at ~1-2x its in-sample error (sqrt(m / (m - P)) and fold-to-fold posture changes); a fit
# that extrapolates to postures its folds never saw holds out at 10-20x.
OVERFIT_RATIO = 3.0
OVERFIT_MIN_MG = TOL_G * 1e3


@dataclass
class Verdict:
    status: str
    reason: str
    evidence: dict[str, Any] = field(default_factory=dict)

    @property
    def trusted(self) -> bool:
        return self.status in TRUSTED

    def to_dict(self) -> dict[str, Any]:
        return {"status": self.status, "reason": self.reason, **({"evidence": self.evidence} if self.evidence else {})}


@dataclass
class Candidate:
    """One order's full fit and its held-out error on the same contiguous folds."""

    model: str
    calibration: Calibration
    heldout: HeldoutResult
    fitted: Any = None  # order_fit.Fitted when it is the pipeline's own fit

    @property
    def heldout_mg(self) -> float:
        return float(self.heldout.heldout_rms_mg)


def lower_models(model: str) -> list[str]:
    """The orders below ``model`` that the guard compares it with: the plain orders of its ladder below its
    base order, and (an extended model) the base order without its terms."""
    base = model.split("+", 1)[0]
    lower = [o for o in ORDER_LADDER.get(base, ()) if o != base]
    if "+" in model:
        lower.append(base)
    return lower


def _mg(x: float) -> str:
    return f"{x:.3g} mg" if np.isfinite(x) else "n/a"


def choose(chosen: Candidate, lower: list[Candidate], *, auto: bool) -> tuple[Candidate, str]:
    """The candidate returned and the sentence saying why: auto falls back to the lower order with the lowest
    held-out error when it holds out better than the chosen one (the rule select_order applies to the
    cross-axis terms); an order the user asked for is kept, and the sentence names the better one."""
    if not np.isfinite(chosen.heldout_mg):
        return chosen, ""
    better = [c for c in lower if np.isfinite(c.heldout_mg) and c.heldout_mg < chosen.heldout_mg]
    if not better:
        return chosen, ""
    best = min(better, key=lambda c: c.heldout_mg)  # ``lower`` runs from the lowest order up: ties keep it
    cmp = (f"{chosen.model} holds out at {_mg(chosen.heldout_mg)} (in-sample {_mg(chosen.heldout.insample_rms_mg)}), "
           f"{best.model} at {_mg(best.heldout_mg)}")
    if auto:
        return best, f"held-out guard: {cmp}: {best.model} returned"
    return chosen, f"held-out guard: {cmp}: the lower order {best.model} generalises better than the requested one (--model {best.model})"


def judge(cand: Candidate, *, baseline: Candidate | None, baseline_name: str, guard_note: str, auto: bool) -> Verdict:
    """The verdict on ``cand`` (the calibration returned unless not_improved), given no calibration
    (``baseline``: the start scored on every window, uncalibrated(); None when the start came from these
    data) and the guard's sentence. Not improved: no calibration is off by less than the fit holds out."""
    cal, ho = cand.calibration, cand.heldout
    held, ins = float(ho.heldout_rms_mg), float(ho.insample_rms_mg)
    ev: dict[str, Any] = {"heldout_rms_mg": held if np.isfinite(held) else None,
                          "insample_rms_mg": ins if np.isfinite(ins) else None}
    baseline_mg = None if baseline is None else baseline.heldout_mg
    if baseline_mg is not None:
        ev["uncalibrated_rms_mg"] = baseline_mg
    lead = f"{guard_note}; " if guard_note else ""
    if baseline is not None and np.isfinite(held) and held >= baseline.heldout_mg:
        return Verdict("not_improved", f"{lead}no calibration ({baseline_name}) is off by {_mg(baseline_mg)}, "
                                       f"the {cand.model} fit holds out at {_mg(held)}: the start is returned unchanged", ev)
    if not cal.converged:
        return Verdict("unreliable", f"{lead}the fit did not converge: {cal.message or 'no reason given'}", ev)
    if not cal.observable:
        return Verdict("unreliable", f"{lead}not observable: {cal.message or 'the windows do not determine it'}", ev)
    if np.isfinite(held) and held > OVERFIT_RATIO * ins and held > OVERFIT_MIN_MG:
        return Verdict("unreliable", f"{lead}held-out error {_mg(held)} is far above the in-sample {_mg(ins)} "
                                     f"(> {OVERFIT_RATIO:g}x and > {OVERFIT_MIN_MG:g} mg): the fit does not "
                                     f"generalise to the postures it did not see (a contiguous fold holds postures "
                                     f"the others lack: record each posture more than once, or calibrate a six-face "
                                     f"session with --lab)", ev)
    if not np.isfinite(held):
        return Verdict("unreliable", f"{lead}no held-out error could be computed (every fold's fit failed)", ev)
    if guard_note and not auto:
        return Verdict("unreliable", guard_note, ev)
    gain = "" if baseline_mg is None else f", against {_mg(baseline_mg)} uncalibrated ({baseline_name})"
    if cand.model.split("+", 1)[0] == "offsets":
        what = "" if guard_note else ", what the windows determine"
        return Verdict("partial", f"{lead}offsets only{what}: the sensitivities are held at the start; held-out "
                                  f"{_mg(held)}{gain}", ev)
    return Verdict("ok", f"{lead}{cand.model}: held-out {_mg(held)} (in-sample {_mg(ins)}){gain}", ev)


def refused(reason: str) -> Verdict:
    return Verdict("refused", reason)


def uncalibrated(start: Calibration, ws: WindowSet) -> Candidate:
    """No calibration: the start scored on every window (nothing is fitted, so every window is held out)."""
    e = norm_error_mg(start, ws)
    rms = float(np.sqrt(np.mean(e ** 2))) if e.size else float("nan")
    return Candidate("none", start, HeldoutResult(rms, rms, "none", 0, window_errors_mg=e))
