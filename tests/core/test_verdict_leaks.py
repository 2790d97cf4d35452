"""What the verdict's held-out figures may not see, on sessions gravcal's simulator did not make
(tests/support/independent_sessions.py and test_verdict's logger recordings).

* An offsets-only fit from a start the bootstrap drew from the same windows: a held-out fold's error must
  not depend on the fold's own windows except through the window scored (core.pipeline.chosen_heldout).
* A start of unknown origin scored as "no calibration" on every window may be in-sample: the reason says so.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from gravcal.core.estimators.lotters import LottersBatch
from gravcal.core.estimators.order_fit import Fitted
from gravcal.core.estimators.start import device_start
from gravcal.core.fold_bootstrap import fold_bootstrap
from gravcal.core.heldout import HeldoutResult, fold_indices
from gravcal.core.pipeline import calibrate_recording, chosen_heldout
from gravcal.core.verdict import Candidate, judge, lower_models, uncalibrated

from tests.core.test_verdict import logger_recording
from tests.support.independent_sessions import session

FOLDS = 5


def offsets_heldout_from_data_start(ws) -> np.ndarray:
    """The per-window held-out errors [mg] of the offsets-only procedure whose start (held sensitivities) is
    drawn from every window, as the bootstrap draws it."""
    start = fold_bootstrap(ws)
    est = LottersBatch("offsets")
    fitted = Fitted("offsets", est.fit(ws, start), est, start, 3, {"model": "offsets"})
    return chosen_heldout(ws, fitted, FOLDS, data_start=True).window_errors_mg


@pytest.mark.parametrize("kind", ["six", "offsets_held"])
def test_a_held_out_window_shapes_no_other_windows_error(kind):
    """Push one window of a fold 3 % off the sphere: the other windows of that fold keep their held-out errors
    (their fold's fit, start included, never saw it). With the held sensitivities bootstrapped from every
    window they move by ~0.1-1 mg."""
    moved = []
    for seed in range(4):
        ws = session(kind, seed).windows
        e0 = offsets_heldout_from_data_start(ws)
        centre = LottersBatch("offsets").fit(ws, fold_bootstrap(ws)).offset
        for test in fold_indices(ws.t, "contiguous", FOLDS):
            j, rest = test[0], test[1:]
            mean = ws.mean.copy()
            mean[j] = centre + 1.03 * (mean[j] - centre)
            e1 = offsets_heldout_from_data_start(replace(ws, mean=mean))
            assert np.all(np.isfinite(e0[rest])) and np.all(np.isfinite(e1[rest]))
            moved.append(float(np.max(np.abs(e1[rest] - e0[rest]))))
            assert abs(e1[j] - e0[j]) > 1.0, "the pushed window's own error must move (the perturbation is real)"
    assert max(moved) < 1e-6, f"held-out errors moved by up to {max(moved):.3g} mg when another held-out window moved"


def test_a_start_of_unknown_origin_is_said_to_be_possibly_in_sample():
    """A start fitted to this very recording scores "no calibration" on windows it was fitted to: the verdict's
    reason says the start's origin is unknown and its figure possibly in-sample; a device's nominal scale is
    no such start."""
    t, raw, _ = logger_recording(np.random.default_rng(3001))
    first = calibrate_recording(t, raw, start=device_start(1.0, "test logger", "g"))
    assert "origin is unknown" not in first.verdict.reason
    assert "uncalibrated_origin" not in first.verdict.evidence
    again = calibrate_recording(t, raw, start=first.calibration)  # a --start produced from the same data
    assert again.verdict.evidence.get("uncalibrated_origin") == "unknown"
    assert "origin is unknown" in again.verdict.reason and "in-sample" in again.verdict.reason


def test_an_offsets_only_fit_from_the_bootstrap_is_said_not_compared():
    """Without a start the offsets-only alternative would hold the bootstrap's sensitivities (fitted to the
    same windows): it is no lower order, and the verdict's evidence says why it was not compared."""
    t, raw, _ = logger_recording(np.random.default_rng(3002))
    rep = calibrate_recording(t, raw)
    assert "offsets" not in rep.verdict.evidence["heldout_by_order"]
    if "offsets" in lower_models(rep.order["model"]):
        assert "bootstrap" in rep.verdict.evidence["not_compared"]["offsets"]


def test_judge_states_the_caveat_for_every_status_that_quotes_the_start():
    ws = session("six", 0).windows
    cal = LottersBatch("6").fit(ws)
    base = uncalibrated(cal, ws)
    for held in (0.5 * base.heldout_mg, 2.0 * base.heldout_mg):  # ok, then not_improved
        cand = Candidate("6", cal, HeldoutResult(held, 0.9 * held, "contiguous", FOLDS))
        v = judge(cand, baseline=base, baseline_name="the start", guard_note="", auto=True, baseline_origin_unknown=True)
        assert "origin is unknown" in v.reason, v.reason
        plain = judge(cand, baseline=base, baseline_name="the start", guard_note="", auto=True)
        assert plain.status == v.status and "origin is unknown" not in plain.reason
