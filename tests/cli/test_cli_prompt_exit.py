"""`gravcal calibrate FILE` ends the process without the interpreter's teardown (cli.console, os._exit)
once its output is written: everything it printed, logged and saved must still arrive whole."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from gravcal.core.calibration import Calibration
from gravcal.core.simulate import simulate
from gravcal.cli import main as cli
from gravcal.io.recordings import write_recording


@pytest.fixture(scope="module")
def rec_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("prompt_exit") / "rec.npy"
    write_recording(path, simulate("loetters", seed=4, duration=600.0).samples)
    return path


def _program(tmp_path, *args):
    """The program as a shell runs it, stdout and stderr to files (block-buffered, unlike a terminal)."""
    out, err = tmp_path / "out.txt", tmp_path / "err.txt"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    with open(out, "wb") as fo, open(err, "wb") as fe:
        rc = subprocess.run([sys.executable, "-m", "gravcal.cli.main", *args], stdout=fo, stderr=fe, env=env,
                            timeout=120).returncode
    return rc, out.read_text(encoding="utf-8"), err.read_text(encoding="utf-8")


def test_json_saved_calibration_and_log_arrive_whole(tmp_path, rec_path):
    saved = tmp_path / "cal.json"
    rc, out, err = _program(tmp_path, "-v", "calibrate", str(rec_path), "--json", "--save", str(saved))
    obj = json.loads(out)  # exactly one complete object
    assert rc == (0 if obj["status"] in ("ok", "partial") else 3)
    assert obj["n_windows"] > 0 and set(obj["timing_s"]) >= {"read", "calibrate"}
    cal = Calibration.from_json(saved.read_text(encoding="utf-8"))
    assert cal.offset.tolist() == obj["offset"] and cal.sensitivity.tolist() == obj["sensitivity"]
    assert "gravcal: INFO: read " in err  # the log handler's lines too


def test_summary_arrives_whole(tmp_path, rec_path):
    rc, out, _ = _program(tmp_path, "calibrate", str(rec_path))
    assert rc in (0, 3)
    assert out.splitlines()[0].startswith("recording ") and out.rstrip().endswith("(raw - offset)")


def test_an_error_keeps_its_status_and_message(tmp_path):
    rc, out, err = _program(tmp_path, "calibrate", str(tmp_path / "missing.npy"), "--json")
    assert rc == cli.EXIT_BAD_INPUT and out == "" and err.startswith("gravcal: error:")


def test_main_in_process_returns(rec_path, capsys):
    # only the program ends early: a caller of main() gets the status back and goes on
    assert cli.main(["calibrate", str(rec_path), "--json"]) in (0, 3)
    assert json.loads(capsys.readouterr().out)["n_windows"] > 0
