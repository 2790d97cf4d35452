"""The Python API: docs/python-api.md's examples run as written; import gravcal stays light; the
Calibration round-trips and agrees with `gravcal calibrate --json` on the same file."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import gravcal

DOC = Path(__file__).resolve().parents[2] / "docs" / "python-api.md"


def python_blocks(text: str) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def test_the_documented_examples_run():
    blocks = python_blocks(DOC.read_text(encoding="utf-8"))
    assert len(blocks) >= 6
    env_path = str(Path(sys.executable).parent) + os.pathsep + os.environ.get("PATH", "")
    old = os.environ["PATH"]
    os.environ["PATH"] = env_path  # the examples call the `gravcal` command of this environment
    try:
        ns: dict = {}
        for i, code in enumerate(blocks):
            exec(compile(code, f"{DOC.name}[block {i}]", "exec"), ns)
    finally:
        os.environ["PATH"] = old
    assert ns["cal"].heldout_rms_mg > 0


def test_import_gravcal_loads_no_numerics():
    code = ("import sys, gravcal; heavy = [m for m in ('numpy', 'scipy', 'gravcal.core', 'gravcal.daemon', 'dask') "
            "if m in sys.modules]; print(heavy, gravcal.__version__)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd="/")
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("[] "), r.stdout


def test_unknown_attribute_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'nonsense'"):
        gravcal.nonsense  # noqa: B018


@pytest.fixture(scope="module")
def six(tmp_path_factory):
    from gravcal.cli.main import main

    d = tmp_path_factory.mktemp("api")
    assert main(["simulate", "--scenario", "six_position", "--seed", "7", "--duration", "600",
                 "--out", str(d / "six.npy")]) == 0
    return d / "six.npy"


def test_api_and_command_line_give_the_same_calibration(six, capsys):
    from gravcal.cli.main import main

    cal = gravcal.calibrate(six)
    assert main(["calibrate", str(six), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["model"] == cal.model
    assert np.allclose(out["offset"], cal.offset) and np.allclose(out["sensitivity"], cal.sensitivity)
    assert out["heldout_rms_mg"] == pytest.approx(cal.heldout_rms_mg)
    assert cal.n_windows == out["n_windows"] and cal.order == out["order"]


def test_arrays_and_truth(six):
    """(t, acc) arrays give the file's calibration, and it maps the still samples to 1 g."""
    rec = gravcal.read(six)
    a = gravcal.calibrate((rec.t, rec.acc), model="6")
    b = gravcal.calibrate(rec, model="6")
    assert np.allclose(a.offset, b.offset) and np.allclose(a.sensitivity, b.sensitivity)
    g = a.apply(rec.acc)
    assert g.shape == rec.acc.shape
    # a six-position session is mostly still: calibrated magnitudes sit at 1 g
    assert np.median(np.linalg.norm(g, axis=1)) == pytest.approx(1.0, abs=0.02)


def test_bad_arrays_and_inputs_say_what_is_wrong():
    with pytest.raises(ValueError, match=r"acc of shape \(N, 3\)"):
        gravcal.calibrate((np.arange(10.0), np.zeros((10, 2))))
    with pytest.raises(TypeError, match="a Recording, a path or a tuple"):
        gravcal.calibrate(42)
    with pytest.raises(ValueError, match="unknown --model"):
        gravcal.calibrate((np.arange(10.0), np.zeros((10, 3))), model="seven")


def test_a_recording_that_determines_nothing_is_a_refusal_not_an_exception():
    """One still posture (its own generator: 60 s at 50 Hz, in g, 3 mg noise): the API returns the verdict."""
    rng = np.random.default_rng(11)
    t = np.arange(3000) / 50.0
    acc = np.array([0.02, -0.01, 1.0]) + rng.normal(0.0, 0.003, (3000, 3))
    cal = gravcal.calibrate((t, acc))
    assert cal.status == "refused" and cal.reason and cal.heldout_rms_mg is None
    assert not (cal.converged and cal.observable)


def test_json_round_trip_keeps_report_and_start_accepts_it(six, tmp_path, capsys):
    from gravcal.cli.main import main

    cal = gravcal.calibrate(six, model="6")
    back = gravcal.Calibration.from_json(cal.to_json())
    assert back.heldout_rms_mg == cal.heldout_rms_mg and back.model == "6"
    assert np.array_equal(back.sensitivity, cal.sensitivity)
    p = tmp_path / "cal.json"
    p.write_text(cal.to_json())
    code = main(["calibrate", str(six), "--start", str(p), "--model", "6", "--json"])
    again = json.loads(capsys.readouterr().out)
    # the start already fits these windows (in-sample): a refit holding out no better returns it unchanged
    assert again["verdict"]["uncalibrated_rms_mg"] == pytest.approx(cal.insample_rms_mg, rel=1e-6)
    if again["status"] == "not_improved":
        assert code == 3 and np.allclose(again["offset"], cal.offset, rtol=0, atol=0)
    else:
        assert code == 0 and again["heldout_rms_mg"] < again["verdict"]["uncalibrated_rms_mg"]


def test_calibrate_from_a_path_reuses_the_reading_pass_blocks(tmp_path, monkeypatch):
    """gravcal.calibrate(path) reads with the block statistics and does not pass over the samples
    again; the result is that of reading without them."""
    from gravcal.core import pipeline
    from gravcal.core.samples import raw_triad
    from gravcal.core.simulate import simulate

    sim = simulate("six_position", seed=7, duration=600.0).samples
    rec = np.empty(len(sim), dtype=[("t", "<f8"), ("ax", "<f4"), ("ay", "<f4"), ("az", "<f4"), ("temp", "<f4")])
    rec["t"], rec["temp"] = sim["t"], sim["temp"]
    rec["ax"], rec["ay"], rec["az"] = raw_triad(sim).T
    path = tmp_path / "no_supply.npy"
    np.save(path, rec)
    monkeypatch.setattr(pipeline, "BLOCKS_MIN_SAMPLES", 0)  # block detection for this short file
    plain = gravcal.calibrate(gravcal.read(path))  # no blocks from reading: calibrating passes over the samples

    def no_second_pass(*args, **kwargs):
        raise AssertionError("calibrate(path) passed over the samples again")

    monkeypatch.setattr(pipeline, "_block_stats", no_second_pass)
    cal = gravcal.calibrate(path)
    assert cal.offset.tolist() == plain.offset.tolist() and cal.n_windows == plain.n_windows > 0
    assert cal.heldout_rms_mg == plain.heldout_rms_mg
