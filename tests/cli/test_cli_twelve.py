"""`gravcal calibrate` and issue 3: --model auto (the default) reports the order and why; --model 9 / 12
(with --lab-calibration), --lab (six faces, all 12); bad input gives exit 2 naming what is missing."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from gravcal.core.calibration import Calibration
from gravcal.core.estimators.inuse12 import frame_of, rotation_angle_deg
from gravcal.cli.main import main

K_SYN = np.array([[0.0400, 0.0006, -0.0004], [-0.0003, 0.0410, 0.0005], [0.0008, -0.0006, 0.0390]])  # raw/g
O_SYN = np.array([0.50, 0.48, 0.51])  # raw


def run_cli(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.startswith("gravcal: error: ")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def postures_csv(path, directions, *, hold_s=20.0, move_s=3.0, fs=100.0, noise_g=0.004, seed=0):
    """A recording that holds each direction [g] (sensor frame) for hold_s, turning between them in move_s
    with a 0.3 g bump (a hand moving the box), through raw = K_SYN a + O_SYN + noise."""
    rng = np.random.default_rng(seed)
    rots = [Rotation.align_vectors([d], [[0, 0, 1.0]])[0] for d in np.asarray(directions, dtype=float)]
    parts = []
    for k, r in enumerate(rots):
        parts.append(np.tile(r.apply([0, 0, 1.0]), (int(hold_s * fs), 1)))
        if k + 1 < len(rots):
            n = int(move_s * fs)
            s = np.linspace(0, 1, n)
            turn = Slerp([0, 1], Rotation.concatenate([r, rots[k + 1]]))(s).apply([0, 0, 1.0])
            parts.append(turn * (1 + 0.3 * np.sin(np.pi * s))[:, None])
    a = np.vstack(parts) + rng.normal(0, noise_g, (sum(len(p) for p in parts), 3))
    raw = a @ K_SYN.T + O_SYN
    t = np.arange(len(raw)) / fs
    np.savetxt(path, np.column_stack([t, raw]), delimiter=",", header="t,ax,ay,az", comments="", fmt="%.10g")
    return path


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    """One misaligned sensor (seed 11): a rich in-use session (Lötters orientation 2, theta <= 120°, 30 min),
    its six-position lab session, and an aligned sensor's six-position session."""
    d = tmp_path_factory.mktemp("twelve")
    assert main(["simulate", "--scenario", "loetters", "--set", "orientation=2", "--set", "theta_max_deg=120",
                 "--misalignment", "--seed", "11", "--duration", "1800", "--out", str(d / "rich.csv")]) == 0
    assert main(["simulate", "--scenario", "six_position", "--misalignment", "--seed", "11", "--duration", "600",
                 "--out", str(d / "lab.csv")]) == 0
    assert main(["simulate", "--scenario", "six_position", "--seed", "5", "--duration", "600",
                 "--out", str(d / "six.csv")]) == 0
    return d


def test_auto_is_the_default_and_says_which_order_and_why(capsys, sessions):
    code, out, _ = run_cli(capsys, "calibrate", sessions / "rich.csv", "--json")
    d = json.loads(out)
    assert code == 0 and d["model"] == "9" and d["order"]["model"] == "9"
    assert "9 observable (predicted error" in d["order"]["reason"] and "cross-axis terms chosen (BIC" in d["order"]["reason"]
    assert set(d["std"]) == {"s_xx", "s_yy", "s_zz", "s_xy", "s_xz", "s_yz", "o_x", "o_y", "o_z"}
    # the human summary carries the same decision
    code, out, _ = run_cli(capsys, "calibrate", sessions / "rich.csv")
    assert code == 0 and "order       9: auto: " in out and "cross-axis terms chosen" in out
    # an aligned sensor on six faces: 6 (six faces cannot show cross-axis terms in use: the reason says so)
    code, out, _ = run_cli(capsys, "calibrate", sessions / "six.csv", "--json")
    d6 = json.loads(out)
    assert code == 0 and d6["model"] == "6" and "not observable: 9: predicted error" in d6["order"]["reason"]


def test_model_9_12_and_lab(capsys, sessions, tmp_path):
    code, out, _ = run_cli(capsys, "calibrate", sessions / "rich.csv", "--model", "9", "--json")
    d9 = json.loads(out)
    assert code == 0 and d9["model"] == "9" and d9["order"]["reason"].startswith("requested (--model 9)")
    K9 = np.array(d9["sensitivity"])
    np.testing.assert_allclose(K9, K9.T, atol=1e-15)  # frame convention R0 = I
    # 12 without a lab frame: exit 2 with fit_inuse's message
    code, out, err = run_cli(capsys, "calibrate", sessions / "rich.csv", "--model", "12")
    assert code == 2 and out == ""
    assert "model 12 holds the frame of a lab calibration" in one_error_line(err)
    # the lab session: faces found, all 12, same keys as in use
    code, out, _ = run_cli(capsys, "calibrate", sessions / "lab.csv", "--lab", "--json", "--save", tmp_path / "lab.json")
    lab = json.loads(out)
    assert code == 0 and lab["model"] == "12" and lab["order"]["model"] == "12"
    assert set(lab["faces"]) == {"+x", "-x", "+y", "-y", "+z", "-z"}
    assert {"offset", "sensitivity", "std", "n_windows", "heldout_rms_mg", "converged", "observable", "order"} <= set(lab)
    (tmp_path / "lab_report.json").write_text(out)
    truth = Calibration.from_dict(json.loads((sessions / "lab.truth.json").read_text())["calibration"])
    lab_cal = Calibration.from_json((tmp_path / "lab.json").read_text())
    # the lab finds the frame (to the simulator's hand placement of the faces, ~0.5°)
    assert rotation_angle_deg(frame_of(lab_cal) @ frame_of(truth).T) < 1.0
    # 12 with the lab frame (from --save, or from the --json report): the frame held, K = S R0 = K9 R0
    for lab_file in (tmp_path / "lab.json", tmp_path / "lab_report.json"):
        code, out, _ = run_cli(capsys, "calibrate", sessions / "rich.csv", "--model", "12", "--lab-calibration", lab_file,
                               "--json")
        d12 = json.loads(out)
        assert code == 0 and d12["model"] == "12"
        K12 = np.array(d12["sensitivity"])
        assert rotation_angle_deg(frame_of(Calibration("12", d12["offset"], K12)) @ frame_of(lab_cal).T) < 1e-6
        # the same estimate in the lab's frame (the lab start may shift window edges by a sample: << std)
        tol = 0.1 * min(d12["std"][n] for n in ("s_xx", "s_yy", "s_zz"))
        np.testing.assert_allclose(K12, K9 @ frame_of(lab_cal), rtol=0, atol=tol)
    # its identifiable part is the truth's (S = (K K^T)^1/2, frame-free) to 0.1 % of 1 g
    from gravcal.core.estimators.parameterization import polar_frame
    err = np.abs(polar_frame(K12)[0] - polar_frame(truth.sensitivity)[0]).max() / np.mean(np.diag(truth.sensitivity))
    assert err < 1e-3, err
    # auto with a lab frame: the full order is called 12
    code, out, _ = run_cli(capsys, "calibrate", sessions / "rich.csv", "--lab-calibration", tmp_path / "lab.json", "--json")
    assert code == 0 and json.loads(out)["order"]["model"] in ("6", "12")
    # a model-6 calibration carries no frame
    (tmp_path / "six_cal.json").write_text(Calibration("6", O_SYN, np.diag(np.diag(K_SYN))).to_json())
    code, _, err = run_cli(capsys, "calibrate", sessions / "rich.csv", "--model", "12", "--lab-calibration",
                           tmp_path / "six_cal.json")
    assert code == 2 and "carries no frame" in one_error_line(err)


def verdict_of(capsys, *argv) -> tuple[int, dict, str]:
    code, out, err = run_cli(capsys, *argv, "--json")
    assert "Traceback" not in err and "gravcal: error:" not in err, err
    return code, json.loads(out), err


def test_windows_that_determine_nothing_are_refused_with_what_is_missing(capsys, tmp_path):
    """Readable recordings whose windows determine nothing: status "refused", exit 3, the JSON with the reason."""
    # one posture: fewer windows than parameters / nothing determined
    one = postures_csv(tmp_path / "one.csv", [[0, 0, 1]], hold_s=40)
    code, d, err = verdict_of(capsys, "calibrate", one)
    assert code == 3 and d["status"] == "refused", d["reason"]
    assert "quasi-static window" in d["reason"] and "need at least" in d["reason"]
    assert "gravcal: calibration refused: " in err
    # repeated single posture: many windows, nothing determined
    rep = postures_csv(tmp_path / "rep.csv", [[0.1, 0, 1]] * 8, hold_s=15)
    code, d, _ = verdict_of(capsys, "calibrate", rep)
    assert code == 3 and d["status"] == "refused" and "determine nothing" in d["reason"]
    assert "not even the offsets" in d["reason"]
    # collinear postures: upright and upside down, repeated
    col = postures_csv(tmp_path / "col.csv", [[0, 0, 1], [0, 0, -1]] * 5, hold_s=15)
    code, d, _ = verdict_of(capsys, "calibrate", col)
    assert code == 3 and d["status"] == "refused" and "determine nothing" in d["reason"]
    # (a datasheet start: two postures give a scale-free bootstrap no scale for x and y)
    (tmp_path / "nominal.json").write_text(Calibration("nominal", O_SYN + 0.002, np.diag(np.diag(K_SYN)) * 1.03).to_json())
    code, d, _ = verdict_of(capsys, "calibrate", col, "--model", "6", "--start", tmp_path / "nominal.json")
    assert code == 3 and d["status"] == "refused"
    assert "do not determine the sensitivities" in d["reason"] and "distinct posture" in d["reason"], d["reason"]
    np.testing.assert_allclose(d["offset"], O_SYN + 0.002)  # the start, returned unchanged
    # fewer windows than parameters for an explicit order
    few = postures_csv(tmp_path / "few.csv", [[1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0]], hold_s=15)
    code, d, _ = verdict_of(capsys, "calibrate", few, "--model", "9")
    assert code == 3 and d["status"] == "refused" and "need at least 9" in d["reason"], d["reason"]


def test_lab_session_with_a_face_missing_or_held_twice(capsys, tmp_path):
    faces = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
    good = postures_csv(tmp_path / "good.csv", faces, seed=1)
    code, out, _ = run_cli(capsys, "calibrate", good, "--lab", "--json")
    d = json.loads(out)
    assert code == 0 and d["model"] == "12"
    # no placement error in this synthetic session: all 12 within 5 std of the truth
    std = np.array([d["std"][n] for n in d["calibration"]["param_names"]])
    est = np.r_[np.array(d["sensitivity"]).ravel(order="F"), d["offset"]]
    assert np.all(np.abs(est - np.r_[K_SYN.ravel(order="F"), O_SYN]) < 5 * std)
    missing = postures_csv(tmp_path / "missing.csv", faces[:5], seed=2)
    code, out, err = run_cli(capsys, "calibrate", missing, "--lab")
    assert code == 2 and out == "" and "face -z missing" in one_error_line(err)
    tilted = Rotation.from_rotvec([0, 0.2, 0]).apply([1.0, 0, 0])  # +x again, 11° off
    twice = postures_csv(tmp_path / "twice.csv", faces + [tilted], seed=3)
    code, _, err = run_cli(capsys, "calibrate", twice, "--lab")
    line = one_error_line(err)
    assert code == 2 and "face +x held in 2 separate window clusters" in line, line
    code, _, err = run_cli(capsys, "calibrate", good, "--lab", "--model", "6")
    assert code == 2 and "--model 6 does not apply" in one_error_line(err)
