"""One pose: each channel's temperature slope with a std that covers the truth, and what the pose does not
determine named instead of printed.

The sessions come from tests/support/single_pose_sessions.py (the physics written anew, its own streams): a
chamber stepping the temperature between levels with a lag, each channel's zero-g level following it (and,
in one kind, its gain), a few handling windows in other postures, and the device's own calibration of the
gains held exact or off by its stated 3 %; each kind with and without a slow wander shared by neighbouring
windows (0.3 mg, AR(1) of 10 min), the two regimes of the slope's std (white; white plus a wander whose
covariance is estimated from the session). Tolerances from the count: n independent standard normal z have
their RMS within sqrt(chi²_n quantiles / n) and the count beyond 2σ within the binomial (n, 4.55 %)
quantiles, each at 1e-3 two-sided over all the checks (coverage_runs.rms_bounds / beyond_2sigma_bounds):
per corner (n = 180) the RMS must lie in [0.80, 1.21], pooled (n = 720) in [0.90, 1.10]; a std scaled by 0.7
puts it near 1.43, by 1.4 near 0.71 (both measured red). The 150-session corners are in
bench/bench_single_pose_coverage.py (docs/sensor-model.md).
"""
from __future__ import annotations

import numpy as np
import pytest

from gravcal.core.estimators.single_pose import HELD_KEY, single_pose
from gravcal.core.estimators.start import device_calibration_start
from gravcal.core.pipeline import calibrate_recording
from seed_pool import pmap
from tests.support.coverage_runs import beyond_2sigma_bounds, rms_bounds
from tests.support.single_pose_sessions import sample_session, window_session

SEEDS = range(60)
# (kind, held gains' relative std: exact and stated as such, or off by 3 %, wander [g])
CASES = tuple((kind, rel, wander) for kind, rel in (("offset", 0.0), ("offset_and_gain", 0.03))
              for wander in (0.0, 3e-4))
ALPHA = 1e-3 / (2 * (len(CASES) + 2))  # RMS and beyond-2σ, per corner, pooled and the norm, share the level


def _start(S):
    start = device_calibration_start(S.held_K, S.held_o, "test logger", "its own calibration")
    if S.held_rel_std == 0:  # the gains are the truth: nothing held is uncertain
        start.metadata.pop(HELD_KEY)
    return start


def _norm_truth(S, sp) -> float:
    """|a| - 1 g [mg] of the pose's noise-free window means under the held calibration, as the estimate takes
    it: the least-squares line in the temperature over the pose's windows, at their mean temperature."""
    idx = np.array([np.flatnonzero(S.windows.t == t)[0] for t in sp.windows.t])  # the pose's windows
    norm = (np.linalg.norm(np.linalg.solve(S.held_K, (S.clean_mean[idx] - S.held_o).T), axis=0) - 1.0) * 1e3
    return float(np.mean(norm))  # the line's value at the mean temperature is the mean of its fitted values


def _z(kind: str, rel: float, wander: float, seed: int) -> tuple[str, list[float], float]:
    S = window_session(seed, kind=kind, held_rel_std=rel, wander_g=wander)
    sp = single_pose(S.windows, _start(S))
    if sp is None or sp.status != "partial":
        return "none" if sp is None else sp.status, [], np.nan
    mag = sp.determined["temperature_slopes"]
    along = sp.determined["norm_along_gravity_mg"]
    return (sp.status, [(mag["value"][a] - S.truth_mg_per_c[i]) / mag["std"][a] for i, a in enumerate("xyz")],
            (along["value"] - _norm_truth(S, sp)) / along["std"])


@pytest.fixture(scope="module")
def scored():
    return {c: pmap(_z, [(*c, s) for s in SEEDS]) for c in CASES}


def test_every_session_is_a_partial_calibration(scored):
    for case, runs in scored.items():
        assert [r[0] for r in runs].count("partial") == len(SEEDS), (case, [r[0] for r in runs])


def _covers(z: np.ndarray, label) -> None:
    n = z.size
    lo, hi = rms_bounds(n, ALPHA)
    rms = float(np.sqrt(np.mean(z * z)))
    assert lo <= rms <= hi, (label, rms, lo, hi, n)
    blo, bhi = beyond_2sigma_bounds(n, ALPHA)
    assert blo <= int(np.sum(np.abs(z) > 2)) <= bhi, (label, int(np.sum(np.abs(z) > 2)), blo, bhi, n)


def test_temperature_slope_std_covers_the_truth_in_every_corner(scored):
    for case, runs in scored.items():
        _covers(np.array([v for _, zs, _ in runs for v in zs]), case)
    _covers(np.array([v for runs in scored.values() for _, zs, _ in runs for v in zs]), "pooled")


def test_norm_along_gravity_std_covers_the_noise_free_norm(scored):
    """|a| - 1 g of the pose under the held calibration (a measurement of it, not applied): its std, under the
    windows' covariance like the slopes', covers the noise-free windows' value (n = 240 over the corners: RMS in
    [0.82, 1.18]; measured 0.92, per corner 0.75-1.17, docs/sensor-model.md)."""
    _covers(np.array([zn for runs in scored.values() for _, _, zn in runs]), "norm along gravity")


def test_what_one_pose_does_not_determine_is_named_not_printed():
    S = window_session(3, kind="offset", held_rel_std=0.03)
    sp = single_pose(S.windows, _start(S))
    gravity = "xyz"[int(np.argmax(np.abs(S.g_dir)))]
    across = [a for a in "xyz" if a != gravity]
    for a in across:
        assert f"o_{a}" in sp.undetermined
    for a in "xyz":
        assert f"s_{a}" in sp.undetermined
    assert "offset along gravity" in sp.undetermined  # 3 % of 1 g > 10 mg: the pose cannot split offset and gain
    assert f"temperature slope along gravity ({gravity}): offset or gain" in sp.undetermined
    # the calibration states std only for what it determined: the slopes (raw/°C), nothing held
    assert set(sp.calibration.std) == {"oT_x", "oT_y", "oT_z"}
    assert len(sp.windows) == len(S.windows) - S.n_handling and sp.n_other_windows == S.n_handling


def test_slopes_that_do_not_hold_out_are_not_applied():
    """No temperature effect at all: the slopes are noise (their chi² against none below chi²(3) at 0.999, or a
    constant holds out as well) and nothing is applied: refused, the reason says why."""
    statuses = []
    for seed in range(6):
        S = window_session(seed, kind="offset", held_rel_std=0.0)
        ws = S.windows
        ws.mean[:] = ws.mean - np.outer(ws.aux[:, 0] - 25.0, S.truth_mg_per_c * np.diag(S.held_K) / 1e3)
        sp = single_pose(ws, _start(S))
        statuses.append(sp.status)
        if sp.status == "refused":
            assert "the per-channel slopes are not told from none" in sp.undetermined["temperature slopes"]
            assert sp.calibration.extended_terms == ()
    assert statuses.count("refused") >= 5, statuses


def test_many_postures_are_not_one_pose():
    from tests.support.independent_sessions import session

    s = session("six", 0)
    start = device_calibration_start(s.truth.K, s.truth.o, "test logger", "its own calibration")
    assert single_pose(s.windows, start) is None


def test_samples_through_the_pipeline_give_the_partial_calibration():
    """A chamber session as samples, through calibrate_recording with the device's own calibration as the start:
    the one-pose answer (the norm determines nothing), the slopes within 4 std of the truth, and the returned
    calibration removes the temperature's effect from the samples."""
    t, raw, temp, S = sample_session(1)
    start = device_calibration_start(S.held_K, S.held_o, "test logger", "its own calibration")
    rep = calibrate_recording(t, raw, temp=temp, start=start)
    assert rep.status == "partial" and rep.single_pose is not None, rep.verdict
    mag = rep.single_pose["determined"]["temperature_slopes"]
    z = [(mag["value"][a] - S.truth_mg_per_c[i]) / mag["std"][a] for i, a in enumerate("xyz")]
    assert max(abs(v) for v in z) < 4, z
    still = slice(int(len(t) * 0.1), int(len(t) * 0.9))
    before = start.apply_reference(raw[still])
    after = rep.calibration.apply(raw[still], temp=temp[still])

    def spread(a):  # of minute means [g]: the temperature's effect, the samples' noise averaged down
        m = a[: len(a) // 960 * 960].reshape(-1, 960, 3).mean(axis=1)
        return float(np.max(np.std(m, axis=0)))

    assert spread(after) < 0.5 * spread(before), (spread(after), spread(before))
