"""Calibration files given to `gravcal calibrate` (--start, --lab-calibration) that nest too deeply or carry
numbers Python refuses: one error line naming the file and the problem, status 2, never an internal error."""
from __future__ import annotations

import pytest

from gravcal.cli.main import main


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    d = tmp_path_factory.mktemp("rec")
    assert main(["simulate", "--scenario", "six_position", "--seed", "5", "--duration", "120",
                 "--out", str(d / "six.csv")]) == 0
    return d / "six.csv"


@pytest.mark.parametrize("option", ["--start", "--lab-calibration"])
@pytest.mark.parametrize("content, problem", [
    pytest.param("[" * 100_000, "nested deeper than 64 levels", id="100k ["),
    pytest.param('{"schema": "gravcal.calibration/1", "metadata": ' + '{"a": ' * 3000, "nested deeper than 64 levels",
                 id="deep metadata"),
    pytest.param('{"offset": [1' + "0" * 5000 + "]}", "not usable JSON", id="5000 digits"),
])
def test_a_hostile_calibration_file_is_one_error_line(capsys, rec, tmp_path, option, content, problem):
    path = tmp_path / "deep.json"
    path.write_text(content)
    code = main(["calibrate", str(rec), option, str(path)])
    out, err = capsys.readouterr()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and out == "" and len(lines) == 1, err
    assert lines[0].startswith(f"gravcal: error: {path}: ") and problem in lines[0], lines[0]
    assert "internal error" not in err and "Traceback" not in err and len(lines[0]) < 200


@pytest.mark.parametrize("option", ["--start", "--lab-calibration"])
@pytest.mark.parametrize("kind, problem", [
    ("directory", "cannot be read: Is a directory"),
    ("binary", "not a text file, expected a calibration JSON"),
    ("missing", "no such file"),
])
def test_an_unreadable_calibration_file_is_one_error_line_naming_the_option(capsys, rec, tmp_path, option, kind,
                                                                           problem):
    path = tmp_path / "cal.json"
    if kind == "directory":
        path.mkdir()
    elif kind == "binary":
        path.write_bytes(b"\x93NUMPY\x01\x00\xd0\xff" * 8)
    code = main(["calibrate", str(rec), option, str(path)])
    out, err = capsys.readouterr()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and out == "" and len(lines) == 1, err
    assert lines[0] == f"gravcal: error: {path}: {problem} ({option})", lines[0]
