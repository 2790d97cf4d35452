"""The gravcal command line: global options, exit codes, and every bad input of the issue's
list giving exit 2 (or a flagged exit 3) with one line naming the problem."""
from __future__ import annotations

import json
import re
import sys
from importlib.metadata import version

import numpy as np
import pytest

from gravcal.core.estimators.parameterization import PARAMETERIZATIONS
from gravcal.cli.main import main
from support.concurrent_runs import run_together


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_verdict_line(err: str, status: str, *fragments: str) -> None:
    """exit 3's one line on stderr: "gravcal: calibration <status>: <reason>", no error line, no traceback."""
    lines = [ln for ln in err.splitlines() if ln.startswith("gravcal: calibration ")]
    assert len(lines) == 1 and "gravcal: error:" not in err and "Traceback" not in err, err
    assert lines[0].startswith(f"gravcal: calibration {status.replace('_', ' ')}: "), lines[0]
    for f in fragments:
        assert f in lines[0], (f, lines[0])


def assert_one_error_line(err: str, *fragments: str) -> None:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("gravcal: error: ")]
    assert len(errors) == 1, err
    assert "Traceback" not in err
    for f in fragments:
        assert f in errors[0], (f, errors[0])


@pytest.fixture(scope="module")
def six(tmp_path_factory):
    """A 10-minute six-position session (seed 5) as CSV, with its truth."""
    d = tmp_path_factory.mktemp("six")
    assert main(["simulate", "--scenario", "six_position", "--seed", "5", "--duration", "600", "--out", str(d / "six.csv")]) == 0
    return d / "six.csv"


# -- global ----------------------------------------------------------------------------------------
def test_version_and_help_as_subprocess():
    r, h = run_together([["gravcal", "--version"], [sys.executable, "-m", "gravcal.cli.main", "--help"]])
    assert r.returncode == 0 and r.stdout.strip() == f"gravcal {version('gravcal')}"
    assert h.returncode == 0
    for cmd in ("simulate", "calibrate", "reproduce", "demo"):
        assert cmd in h.stdout


def test_no_command_prints_usage_and_exits_2(capsys):
    code, out, err = run_cli(capsys)
    assert code == 2 and "usage: gravcal" in err


def test_model_choices_come_from_the_parameterizations(capsys, six):
    from gravcal.cli.cmd_calibrate import model_choices

    assert set(PARAMETERIZATIONS) <= set(model_choices())
    code, _, err = run_cli(capsys, "calibrate", six, "--model", "no-such-model")
    assert code == 2
    orders = ", ".join(m for m in PARAMETERIZATIONS if "+" not in m)
    from gravcal.core.model.terms import CALIBRATION_TERMS

    assert_one_error_line(err, "unknown --model 'no-such-model'", orders, ", ".join(CALIBRATION_TERMS))
    code, _, err = run_cli(capsys, "calibrate", six, "--model", "6+bogus")  # an unknown term lists the registry's
    assert code == 2
    assert_one_error_line(err, "unknown term(s) ['bogus']", ", ".join(repr(t) for t in CALIBRATION_TERMS))
    code, _, err = run_cli(capsys, "calibrate", six, "--detector", "magic")
    assert code == 2
    assert_one_error_line(err, "unknown --detector 'magic'", "lotters")
    code, _, err = run_cli(capsys, "simulate", "--scenario", "moonwalk", "--out", six.with_name("x.csv"))
    assert code == 2
    assert_one_error_line(err, "unknown --scenario 'moonwalk'", "daily_living")


def test_verbose_logs_the_read(capsys, six):
    code, out, err = run_cli(capsys, "-v", "calibrate", six, "--json")
    assert code == 0 and "gravcal: INFO: read" in err and "60000 samples" in err
    json.loads(out)  # logging goes to stderr: stdout stays one JSON object


# -- bad input: exit 2, one line naming the problem ------------------------------------------------
def test_missing_file(capsys, tmp_path):
    code, out, err = run_cli(capsys, "calibrate", tmp_path / "nope.csv")
    assert code == 2 and out == ""
    assert_one_error_line(err, "nope.csv", "no such file")


def test_empty_input(capsys, tmp_path):
    (tmp_path / "e.csv").write_text("")
    code, _, err = run_cli(capsys, "calibrate", tmp_path / "e.csv")
    assert code == 2
    assert_one_error_line(err, "empty file")
    (tmp_path / "h.csv").write_text("t,ax,ay,az\n")
    code, _, err = run_cli(capsys, "calibrate", tmp_path / "h.csv")
    assert code == 2
    assert_one_error_line(err, "empty input")


def test_missing_columns(capsys, tmp_path, six):
    lines = six.read_text().splitlines()
    header = lines[0].split(",")
    header[header.index("ay")] = "y"
    (tmp_path / "m.csv").write_text("\n".join([",".join(header)] + lines[1:200]) + "\n")
    code, _, err = run_cli(capsys, "calibrate", tmp_path / "m.csv")
    assert code == 2
    assert_one_error_line(err, "missing column ay", "found: t, ax, y, az")


def test_text_in_numbers(capsys, tmp_path, six):
    lines = six.read_text().splitlines()[:3000]
    fields = lines[1234].split(",")
    fields[3] = "1.2.3"  # az
    lines[1234] = ",".join(fields)
    (tmp_path / "t.csv").write_text("\n".join(lines) + "\n")
    code, _, err = run_cli(capsys, "calibrate", tmp_path / "t.csv")
    assert code == 2
    assert_one_error_line(err, "line 1235", "'az'", "'1.2.3' is not a number")


def test_mostly_nan(capsys, tmp_path, six):
    lines = six.read_text().splitlines()[:3000]
    for i in range(1, len(lines), 3):
        if i % 2:
            continue
        lines[i] = ",".join(f if k != 1 else "nan" for k, f in enumerate(lines[i].split(",")))
    for i in range(1, len(lines)):
        if i % 3:
            lines[i] = ",".join(f if k != 2 else "inf" for k, f in enumerate(lines[i].split(",")))
    (tmp_path / "n.csv").write_text("\n".join(lines) + "\n")
    code, _, err = run_cli(capsys, "calibrate", tmp_path / "n.csv")
    assert code == 2
    assert_one_error_line(err, "hold NaN/inf", "too many to drop")


def test_plain_npy(capsys, tmp_path):
    np.save(tmp_path / "p.npy", np.zeros((1000, 4)))
    code, _, err = run_cli(capsys, "calibrate", tmp_path / "p.npy")
    assert code == 2
    assert_one_error_line(err, "plain float64 array", "structured array with fields t, ax, ay, az")


def test_single_window(capsys, tmp_path):
    # 30 s of one still posture: one quasi-static window at most
    out = tmp_path / "static.csv"
    assert main(["simulate", "--scenario", "static", "--duration", "30", "--out", str(out)]) == 0
    capsys.readouterr()
    code, stdout, err = run_cli(capsys, "calibrate", out, "--json")
    d = json.loads(stdout)  # a readable recording gets a verdict: refused, with the reason, exit 3
    assert code == 3 and d["status"] == "refused" and "quasi-static window" in d["reason"]
    assert "need at least 6" in d["reason"] and d["heldout_rms_mg"] is None and d["order"]["model"] == "none"
    assert_one_verdict_line(err, "refused", "quasi-static window", "need at least 6")


def test_saturated_samples(capsys, tmp_path, six):
    """az clipped just below +1 g: the '+z up' posture sits at the rail -> refused, not calibrated."""
    truth = json.loads(six.with_name("six.truth.json").read_text())["calibration"]
    rail = truth["offset"][2] + 0.9 * truth["sensitivity"][2][2]
    data = np.loadtxt(six, delimiter=",", skiprows=1, usecols=(0, 1, 2, 3))
    data[:, 3] = np.minimum(data[:, 3], rail)
    p = tmp_path / "sat.csv"
    np.savetxt(p, data, delimiter=",", header="t,ax,ay,az", comments="", fmt="%.10g")
    code, out, err = run_cli(capsys, "calibrate", p)
    assert code == 2 and out == ""
    assert_one_error_line(err, "saturated", "az sits at its maximum", "too many to drop")


def test_bad_options(capsys, six, tmp_path):
    code, _, err = run_cli(capsys, "calibrate", six, "--folds", "1")
    assert code == 2
    assert_one_error_line(err, "--folds must be at least 2")
    (tmp_path / "notcal.json").write_text('{"hello": 1}')
    code, _, err = run_cli(capsys, "calibrate", six, "--start", tmp_path / "notcal.json")
    assert code == 2
    assert_one_error_line(err, "notcal.json", "not a gravcal calibration")
    code, _, err = run_cli(capsys, "simulate", "--duration", "-5", "--out", tmp_path / "x.csv")
    assert code == 2
    assert_one_error_line(err, "--duration must be a positive number")
    code, _, err = run_cli(capsys, "simulate", "--out", tmp_path / "x.txt")
    assert code == 2
    assert_one_error_line(err, "extension must be .csv or .npy")
    code, out, err = run_cli(capsys, "demo", "--model", "12", "--speed", "0")
    assert code == 2 and out == ""  # refused before the session starts
    assert_one_error_line(err, "unknown --model '12'", "auto, offsets, 6, 9")
    code, out, err = run_cli(capsys, "demo", "--start-hour", "24", "--speed", "0")
    assert code == 2 and out == ""
    assert_one_error_line(err, "--start-hour must be in [0, 24)")


# -- refused / flagged by the observability rule (core/estimators/order.py) -----------------------------
def loetters_csv(tmp_path, theta_deg: float):
    """15 min of Lötters' orientation-1 protocol, postures within ``theta_deg`` of standing (seed 0)."""
    out = tmp_path / f"loetters_{theta_deg:g}.csv"
    assert main(["simulate", "--scenario", "loetters", "--set", f"theta_max_deg={theta_deg:g}", "--duration", "900",
                 "--out", str(out)]) == 0
    return out


def test_auto_determining_nothing_is_refused_with_the_reason(capsys, tmp_path):
    """Postures within 10° of standing: auto (the default) finds not even the offsets determined -> status
    "refused", exit 3 with the JSON, one line saying why (the predicted error against the 10 mg tolerance);
    the start is returned unchanged and --save writes nothing."""
    out = loetters_csv(tmp_path, 10)
    capsys.readouterr()
    code, stdout, err = run_cli(capsys, "calibrate", out, "--json", "--save", tmp_path / "cal.json")
    d = json.loads(stdout)
    assert code == 3 and d["status"] == "refused" and d["converged"] is False and d["observable"] is False
    assert "not even the offsets are determined" in d["reason"] and not (tmp_path / "cal.json").exists()
    assert_one_verdict_line(err, "refused", "model auto: the windows determine nothing",
                            "not even the offsets are determined", "Record several still postures", "not written")
    m = re.search(r"predicted error ([0-9.e+]+) mg > 10 mg", err)
    assert m and float(m.group(1)) > 10, err


def test_explicit_model_fitted_but_not_observable_exits_3_and_still_prints_the_json(capsys, tmp_path):
    """Postures within 75° of standing: --model 6 predicts ~18 mg, between the 10 mg rule and the 30 mg
    at which an explicit model is refused -> fitted, flagged not observable, exit 3 with the JSON printed.
    auto on the same recording fits the offsets only (exit 0) and says why not 6."""
    out = loetters_csv(tmp_path, 75)
    capsys.readouterr()
    code, stdout, err = run_cli(capsys, "calibrate", out, "--model", "6", "--json")
    assert code == 3
    d = json.loads(stdout)
    assert d["model"] == "6" and d["converged"] is True and d["observable"] is False
    predicted = d["order"]["evidence"]["predicted_mg"]
    assert 10 < predicted <= 30, d["order"]
    assert "sensitivities not observable" in d["message"] and "use --model offsets" in d["message"]
    assert set(d["std"]) == {"o_x", "o_y", "o_z", "s_x", "s_y", "s_z"}
    assert d["status"] == "unreliable" and "not observable" in d["reason"]
    assert_one_verdict_line(err, "unreliable", "not observable")

    code, stdout, err = run_cli(capsys, "calibrate", out, "--json")
    a = json.loads(stdout)
    assert code == 0 and a["model"] == "offsets" and a["observable"] is True and set(a["std"]) == {"o_x", "o_y", "o_z"}
    assert a["status"] == "partial" and "offsets only, what the windows determine" in a["reason"]
    m = re.search(r"not observable: 6: predicted error ([0-9.]+) mg", a["order"]["reason"])
    assert m and float(m.group(1)) == pytest.approx(predicted, rel=0.01), a["order"]["reason"]


def test_start_far_off_is_flagged_not_silently_used(capsys, tmp_path, six):
    """A start 1 g away (outside the paper's 5 %): the result is either flagged non-converged (exit 3),
    or it says the start was dropped and is right (within 4 reported std of the truth)."""
    from gravcal.core.calibration import Calibration

    truth = Calibration.from_dict(json.loads(six.with_name("six.truth.json").read_text())["calibration"])
    far = Calibration.nominal(truth.offset + 0.04, np.diag(truth.sensitivity) * 1.2)  # +1 g offsets, +20 % gain
    (tmp_path / "far.json").write_text(far.to_json())
    code, stdout, err = run_cli(capsys, "calibrate", six, "--start", tmp_path / "far.json", "--json")
    d = json.loads(stdout)
    if code == 3:
        assert not (d["converged"] and d["observable"])
    else:
        assert code == 0 and "too far off" in d["message"]
        std = d["std"]
        for i, ax in enumerate("xyz"):
            assert abs(d["offset"][i] - truth.offset[i]) < 4 * std[f"o_{ax}"]
            assert abs(d["sensitivity"][i][i] - truth.sensitivity[i, i]) < 4 * std[f"s_{ax}"]


# -- internal errors ---------------------------------------------------------------------------------
def test_internal_error_is_one_line_and_debug_shows_the_traceback(capsys, monkeypatch, six):
    import gravcal.core.pipeline as pipeline

    def boom(*a, **k):
        raise RuntimeError("kaboom")

    monkeypatch.setattr(pipeline, "calibrate_recording", boom)
    code, out, err = run_cli(capsys, "calibrate", six)
    assert code == 1
    assert_one_error_line(err, "internal error: RuntimeError: kaboom", "--debug")
    code, out, err = run_cli(capsys, "--debug", "calibrate", six)
    assert code == 1 and "Traceback" in err and "kaboom" in err


@pytest.mark.parametrize("readable", [True, False])
def test_a_package_whose_commands_cannot_be_listed_gets_one_line_naming_the_directory(tmp_path, monkeypatch,
                                                                                       capsys, readable):
    from gravcal.cli import main as cli

    monkeypatch.setattr(cli, "_commands_dir", lambda: tmp_path)  # e.g. an install this user cannot read
    if not readable:
        monkeypatch.setattr(cli.os, "access", lambda path, mode: False)
    assert cli.main(["watch"]) == cli.EXIT_INTERNAL
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"gravcal: error: no gravcal commands found in {tmp_path}") and "\n" not in err
    assert ("not readable by this user" in err) is (not readable)
    assert "invalid choice" not in err
