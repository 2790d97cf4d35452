"""Gyro samples holding NaN/inf (a float recording read through the API; the drivers decode integers) never
reach the bias fit's least squares nor a pose change's integration: offline the calibration stops with a
ValueError naming the count, online (the service's rule, ``feed``) the window or pair is skipped and the
calibration keeps finite values (run in a child process, so a hang in LAPACK fails by timeout). Scapellato's
step-height search (bounded, it cannot hang) refuses a placement holding a NaN sample."""
from __future__ import annotations

import json
import textwrap

import pytest

from tests.support.child import run_child

CHILD = textwrap.dedent("""
    import json, sys
    import numpy as np
    from gravcal.core.detectors import QuasiStaticDetector, detect
    from gravcal.core.gyro import OnlineGyroCalibrator, calibrate_gyro
    from gravcal.core.gyro.footmotion import foot_poses, simulate_foot

    FS, NOMINAL, RANGE = 100.0, 357.36, np.radians(300.0)
    where = sys.argv[1]
    s = simulate_foot(foot_poses(np.random.default_rng(1011), n_poses=20), 11)  # pitch changes within range
    acc, g = s.acc_calibration, s.gyro.astype(float)
    ws = detect(s.t, s.acc_raw, fs=FS, to_g=acc)
    bad = g.copy()
    if where == "window":
        spots = (ws.start[1:] + ws.end[1:]) // 2  # inside every window but the first
    else:
        spots = (ws.end[:-1] + ws.start[1:]) // 2  # inside every pose change
    bad[spots] = np.nan

    def offline(y):
        try:
            cal = calibrate_gyro(s.t, y, ws, acc, fs=FS, hp_hz=0.3, axis=(0.0, 1.0, 0.0), range_rad_s=RANGE,
                                 rails=(0, 4095), start=NOMINAL, folds=0)
            return "ok " + str(cal.n_pairs)
        except ValueError as exc:
            return str(exc)

    def online(y):
        det = QuasiStaticDetector(FS, to_g=acc)
        on = OnlineGyroCalibrator(FS, k=1, axis=(0.0, 1.0, 0.0), hp_hz=0.3, start_sensitivity=NOMINAL,
                                  range_rad_s=RANGE, rails=(0, 4095))
        for i in range(0, y.shape[0], 50):
            on.push(y[i:i + 50])
            for w in det.update(s.t[i:i + 50], s.acc_raw[i:i + 50]):
                on.feed(w, acc)
        c = on.calibration
        return {"bias": c.bias.tolist(), "n_windows": c.n_windows, "n_pairs": c.n_pairs,
                "sensitivity": None if c.sensitivity is None else c.sensitivity.ravel().tolist()}

    print(json.dumps({"n_bad": int(len(spots)), "offline_clean": offline(g), "offline": offline(bad),
                      "online_clean": online(g), "online": online(bad)}))
""")


@pytest.mark.parametrize("where", ["window", "pose_change"])
def test_nan_gyro_samples_stop_the_offline_fit_with_a_message_and_are_skipped_online(where):
    stdout = run_child(CHILD, where, timeout=240, what="the gyro calibration on NaN samples")
    r = json.loads(stdout)
    assert r["offline_clean"].startswith("ok ") and int(r["offline_clean"].split()[1]) > 0
    assert "gyro values" in r["offline"] and "are NaN/inf" in r["offline"], r["offline"]
    assert r["offline"].startswith("1 of the "), r["offline"]  # one NaN per window / pose change
    clean, on = r["online_clean"], r["online"]
    assert clean["n_pairs"] > 0
    values = on["bias"] + (on["sensitivity"] or [])
    assert all(v == v and abs(v) < float("inf") for v in values), on  # finite: nothing NaN got in
    if where == "window":  # every window but the first skipped: one bias, no pair
        assert on["n_windows"] == 1 and on["n_pairs"] == 0
    else:  # the windows count (their bias is the clean one, bit for bit), the pairs across a NaN do not
        assert on["n_windows"] == clean["n_windows"] and on["bias"] == clean["bias"] and on["n_pairs"] == 0


@pytest.mark.parametrize("channel", ["gyro", "acc"])
def test_the_step_height_search_refuses_a_placement_with_a_nan_sample(channel):
    """A NaN in one swing makes that placement's height NaN and the bounded search's cost NaN: it ended at
    an arbitrary sensitivity (12 % off here) with a NaN std. Refused naming the placement instead."""
    import numpy as np

    from gravcal.core.gyro.footmotion import simulate_foot, stair_climb
    from gravcal.core.gyro.scapellato import placements, step_height_search

    sc = stair_climb(np.random.default_rng(2000), n_steps=6, step_height_m=0.17)
    s = simulate_foot(sc.motion, 0)
    gyro, acc = s.gyro.astype(float), s.acc_raw.astype(float)

    def search(g, a):
        pl = placements(g, a, s.acc_calibration, sc.stances, bias=s.truth["bias_counts"], fs=100.0,
                        hp_hz=s.truth["hp_hz"])
        return step_height_search(pl, 0.17, start=357.36)

    assert np.isfinite(search(gyro, acc).std)  # the intact climb gives an estimate
    swing = sc.stances[2][1] + 20  # a sample in the swing after the third stance: placement 2
    if channel == "gyro":
        gyro[swing] = np.nan
    else:
        acc[swing, 0] = np.nan
    with pytest.raises(ValueError, match=r"foot placement\(s\) \[2\] hold NaN/inf"):
        search(gyro, acc)
