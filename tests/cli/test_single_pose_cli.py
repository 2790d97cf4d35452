"""A one-pose chamber session from the tests' own generator (tests/support/single_pose_sessions.py, not
gravcal's simulator) through the file-level paths: `gravcal calibrate FILE --start DEVICE.json --json`, the
Python API and `gravcal diagnose FILE --json` give the same per-channel temperature slopes, a partial
calibration (exit 0) whose std covers the truth, and the quantities one pose does not determine named."""
from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest

from gravcal.cli.main import main
from gravcal.core.estimators.start import device_calibration_start
from tests.support.single_pose_sessions import sample_session


def _run(argv):
    so, se = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(so), contextlib.redirect_stderr(se):
        code = main(argv)
    return code, so.getvalue(), se.getvalue()


@pytest.fixture(scope="module")
def chamber(tmp_path_factory):
    d = tmp_path_factory.mktemp("chamber")
    t, raw, temp, S = sample_session(2)
    arr = np.zeros(len(t), dtype=[("t", "f8"), ("ax", "f8"), ("ay", "f8"), ("az", "f8"), ("temp", "f8")])
    arr["t"], arr["ax"], arr["ay"], arr["az"], arr["temp"] = t, raw[:, 0], raw[:, 1], raw[:, 2], temp
    path = d / "chamber.npy"
    np.save(path, arr)
    start = device_calibration_start(S.held_K, S.held_o, "test logger", "its own calibration")
    (d / "device.json").write_text(start.to_json())
    return path, d / "device.json", start, S


def test_calibrate_api_and_diagnose_agree_and_cover_the_truth(chamber):
    import gravcal

    path, device, start, S = chamber
    code, out, err = _run(["calibrate", str(path), "--start", str(device), "--json"])
    d = json.loads(out)
    assert (code, d["status"]) == (0, "partial"), (d["reason"], err)
    slopes = d["single_pose"]["determined"]["temperature_slopes"]
    z = [(slopes["value"][a] - S.truth_mg_per_c[i]) / slopes["std"][a] for i, a in enumerate("xyz")]
    assert max(abs(v) for v in z) < 4, (z, slopes, S.truth_mg_per_c)
    assert {"s_x", "s_y", "s_z", "offset along gravity"} <= set(d["undetermined"])
    assert set(d["std"]) == {"oT_x", "oT_y", "oT_z"}

    cal = gravcal.calibrate(path, start=start)
    assert (cal.status, cal.reason) == (d["status"], d["reason"])

    # diagnose (no device file: its own start from the data) tests temperature_offset on the same session: through
    # the norm or, where the norm cannot test it in one pose, on each channel's reading (core/diagnosis/one_pose.py);
    # either way the finding carries the channels' own held-out test and its raw slopes are calibrate's
    code, out, err = _run(["diagnose", str(path), "--json", "--replicas", "2"])
    assert code == 0, err
    g = json.loads(out)
    assert "temperature_offset" not in {u["effect"] for u in g["untestable"]}, g["untestable"]
    (f,) = [f for f in g["findings"] + g["partial"] if f["effect"] == "temperature_offset"]
    per_channel = f["evidence"].get("one_pose_per_channel", f["evidence"])
    assert per_channel["heldout_rms_mg_with"] < per_channel["heldout_rms_mg_without"], per_channel
    raw = slopes["raw_channel_slopes"]  # raw/°C: the same whatever scale each command holds
    for a in "xyz":
        assert abs(f["magnitude"]["raw_value"][a] - raw["value"][a]) <= 0.5 * raw["std"][a], (a, f["magnitude"], raw)
    z = [(f["magnitude"]["value"][a] - S.truth_mg_per_c[i]) / f["magnitude"]["std"][a] for i, a in enumerate("xyz")]
    assert max(abs(v) for v in z) < 4, (z, f["magnitude"]["value"], S.truth_mg_per_c)
    # named, not printed: every sensitivity (and, across gravity, the offsets) with its std withheld
    und = g["undetermined"]
    assert {"s_x", "s_y", "s_z"} <= set(und)
    std = g["extended"]["calibration"]["std"]
    assert all(std.get(k) is None for k in und if k in std), std
