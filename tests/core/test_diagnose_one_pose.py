"""diagnose in one pose, where its norm-based selection cannot test temperature_offset: the term is tested on
each channel's reading (core/diagnosis/one_pose.py), as `gravcal calibrate` does, on chamber sessions from the
tests' own generator (tests/support/single_pose_sessions.py, not gravcal's simulator)."""
from __future__ import annotations

import numpy as np

from gravcal.core.diagnosis import diagnose_windows  # the package binds its functions over the submodule
from gravcal.core.diagnosis.one_pose import one_pose_temperature
from gravcal.core.estimators.single_pose import single_pose
from gravcal.core.estimators.start import device_calibration_start
from tests.support.single_pose_sessions import window_session


def _norm_untestable(seed: int, remove_effect: bool):
    """A diagnosis of one chamber session whose norm-based test of temperature_offset is set to what the
    observability screen says when the norm cannot see it (untestable), the start with its held gains."""
    # held gains exact where the effect is removed (the removal at the held gains is then the truth's)
    S = window_session(seed, kind="offset", held_rel_std=0.0 if remove_effect else 0.03, wander_g=3e-4, m=120)
    start = device_calibration_start(S.held_K, S.held_o, "test logger", "its own calibration")
    if remove_effect:  # the temperature's effect taken out of every window: nothing to find
        S.windows.mean[:] -= np.outer(S.windows.aux[:, 0] - 25.0, S.truth_mg_per_c * np.diag(S.held_K) / 1e3)
    d = diagnose_windows(S.windows, start, has_temp=True, simulate=False, nested=False)
    test = next(t for t in d.tests if t.effect == "temperature_offset")
    test.status, test.why = "untestable", "indistinguishable from the base parameters with these windows"
    d.findings = [f for f in d.findings if f["effect"] != "temperature_offset"]
    d.partial = [f for f in d.partial if f["effect"] != "temperature_offset"]
    d.untestable.append({"effect": "temperature_offset", "why": test.why})
    return S, start, d


def test_untestable_through_the_norm_is_tested_per_channel_as_calibrate_does():
    S, start, d = _norm_untestable(5, remove_effect=False)
    one_pose_temperature(d, S.windows, start)
    assert "temperature_offset" not in {u["effect"] for u in d.untestable}
    (f,) = [f for f in d.findings if f["effect"] == "temperature_offset"]
    ev, mag = f["evidence"], f["magnitude"]
    assert ev["heldout_rms_mg_with"] < ev["heldout_rms_mg_without"] and ev["chi2"] > ev["chi2_threshold"], ev
    assert ev["folds"] >= 2 and len(ev["fold_rms_mg"]) == ev["folds"]
    sp = single_pose(S.windows, start)  # what `gravcal calibrate` states for the same windows and start
    cal = sp.determined["temperature_slopes"]
    assert mag["value"] == cal["value"] and mag["std"] == cal["std"]
    z = [(mag["value"][a] - S.truth_mg_per_c[i]) / mag["std"][a] for i, a in enumerate("xyz")]
    assert max(abs(v) for v in z) < 4, (z, mag["value"], S.truth_mg_per_c)
    gravity = "xyz"[int(np.argmax(np.abs(S.g_dir)))]
    assert mag["confounded_with"] == ["temperature_sensitivity"]
    for name in ["s_x", "s_y", "s_z", "offset along gravity", "cross-axis terms"] + [
            f"o_{a}" for a in "xyz" if a != gravity]:
        assert name in d.undetermined, (name, sorted(d.undetermined))


def test_no_temperature_effect_is_not_found_per_channel():
    S, start, d = _norm_untestable(6, remove_effect=True)
    one_pose_temperature(d, S.windows, start)
    test = next(t for t in d.tests if t.effect == "temperature_offset")
    assert test.status == "not_found" and "not told from none" in test.why, (test.status, test.why)
    assert not [f for f in d.findings if f["effect"] == "temperature_offset"]
    assert "temperature_offset" not in {u["effect"] for u in d.untestable}
