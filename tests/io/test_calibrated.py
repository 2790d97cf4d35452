"""Calibrated data out (`gravcal calibrate REC --write OUT`, studies' --write-dir, gravcal.write_calibrated):
what is written is the Calibration's own apply (every term) with each row's flags, it reads back with
gravcal.read, and calibrating the written file gives the identity within the stated std."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

import gravcal
from gravcal.cli.main import main
from gravcal.core.calibration import Calibration
from gravcal.core.samples import FLAG_SATURATED
from gravcal.io.calibrated import read_parquet_metadata, sidecar, write_calibrated
from gravcal.io.recordings import FLAG_FILLER, read_recording

import pyarrow  # noqa: E402,F401  (a dependency: its absence is a failure, not a skip)
K_STD = 3.0  # each parameter of the identity within 3 of its stated std (all nine at once: P(false red) < 3 %)


@pytest.fixture(scope="module")
def six(tmp_path_factory):
    """A six-position session (all offsets and sensitivities determined) with a filler run and clipped rows."""
    d = tmp_path_factory.mktemp("six")
    assert main(["simulate", "--scenario", "six_position", "--seed", "5", "--duration", "240",
                 "--out", str(d / "plain.npy")]) == 0
    a = np.load(d / "plain.npy")
    a[3000:3400][["ax", "ay", "az"]] = a[3000][["ax", "ay", "az"]]  # 399 rows of exactly repeated filler
    top = a["ax"].max() + 1e-3
    a["ax"][20000:20150] = top  # clipped at a rail: 150 rows (0.6 %) at the extreme
    np.save(d / "rec.npy", a)
    return d


def assert_identity(path, k_std=K_STD):
    rec = gravcal.read(path)
    cal = gravcal.calibrate(rec, model="6")
    assert cal.converged and cal.observable, cal.message
    std = cal.std
    for i, ax in enumerate("xyz"):
        assert abs(cal.offset[i]) <= k_std * std[f"o_{ax}"], (ax, cal.offset, std)
        assert abs(cal.sensitivity[i, i] - 1.0) <= k_std * std[f"s_{ax}"], (ax, np.diag(cal.sensitivity), std)
    return rec, cal


@pytest.mark.parametrize("ext", ["npy", "csv.gz", "parquet"])
def test_write_round_trips_to_the_identity_with_every_row_flagged(six, tmp_path, capsys, ext):
    out = tmp_path / f"out.{ext}"
    assert main(["calibrate", str(six / "rec.npy"), "--write", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["written"] == str(out) and report["input"]["n_excluded_filler"] == 399
    meta = read_parquet_metadata(out) if ext == "parquet" else json.loads(sidecar(out).read_text())
    assert meta["columns"]["ax"] == "g" and meta["calibration"]["model"] == report["model"]
    assert meta["report"]["heldout_rms_mg"] == report["heldout_rms_mg"]
    rec, _ = assert_identity(out)
    # every finite row of the input is there, the filler run and the clipped rows flagged
    src = np.load(six / "rec.npy")
    assert rec.n_samples + rec.n_filler + rec.n_saturated == len(src)
    back = read_recording(out, exclude_filler=False, check_saturation=False)
    flags = back.metadata and np.asarray(_flags(out, ext))
    assert np.flatnonzero(flags & FLAG_FILLER).tolist() == list(range(3001, 3400))
    assert np.flatnonzero(flags & FLAG_SATURATED).tolist() == list(range(20000, 20150))
    assert back.n_samples == len(src)


def _flags(path, ext):
    if ext == "npy":
        return np.load(path)["flags"]
    if ext == "parquet":
        import pyarrow.parquet as pq

        return pq.read_table(path, columns=["flags"]).column(0).to_numpy()
    import gzip

    with gzip.open(path, "rt") as f:
        rows = [r for r in csv.reader(line for line in f if not line.startswith("#"))][1:]
    return np.array([int(r[4]) for r in rows])


def test_written_values_are_the_calibrations_apply_with_its_terms(six, tmp_path):
    rec = read_recording(six / "plain.npy", flag_only=True)
    temp = 25.0 + 10.0 * np.sin(np.linspace(0, 3, rec.n_samples))  # a temperature that moves
    rec.temp = temp
    cal = Calibration.from_dict({
        "schema": "gravcal.calibration/1", "model": "6+temperature_offset", "offset": [0.48, 0.51, 0.54], "sensitivity": np.diag([0.043, 0.045, 0.038]).tolist(),
        "metadata": {"extended": {"terms": ["temperature_offset"], "t_ref_c": 25.0, "t0_s": 0.0, "v_ref": 3.3,
                                  "temp_column": 0, "lag_tau_s": 300.0},
                     "params": {"s_x": 0.043, "s_y": 0.045, "s_z": 0.038, "o_x": 0.48, "o_y": 0.51, "o_z": 0.54,
                                "oT_x": 1.5e-4, "oT_y": 2e-4, "oT_z": -5e-5}}})
    expected = cal.apply(rec.raw, temp=temp, t=rec.t)
    assert np.abs(expected - cal.apply_reference(rec.raw)).max() > 0.01  # the term matters here [g]
    for ext in ("npy", "parquet", "csv"):
        out = write_calibrated(tmp_path / f"w.{ext}", rec, cal)
        got = gravcal.read(out, exclude_filler=False)
        tol = 0.5e-7 if ext == "csv" else 0.0  # CSV: a [g] to 7 decimals
        np.testing.assert_allclose(got.acc, expected, rtol=0, atol=tol, err_msg=ext)
        np.testing.assert_array_equal(got.t, rec.t)


def test_a_study_writes_one_file_per_recording_that_round_trips(six, tmp_path):
    import shutil

    d = tmp_path / "in"
    (d / "b").mkdir(parents=True)
    shutil.copy(six / "plain.npy", d / "s.npy")
    shutil.copy(six / "rec.npy", d / "b" / "s.npy")  # the same name twice: told apart
    (d / "broken.csv").write_text("t,ax,ay,az\n1,2,3\n")
    (tmp_path / "cal").mkdir()
    out = tmp_path / "r.csv"
    assert main(["calibrate", str(d), "--out", str(out), "--workers", "0", "--quiet", "--write-dir",
                 str(tmp_path / "cal"), "--write-format", "csv.gz"]) == 2  # the broken file's error row
    with open(out, newline="") as f:
        rows = {r["file"]: r for r in csv.DictReader(f)}
    assert rows[str(d / "broken.csv")]["status"] == "error" and not rows[str(d / "broken.csv")]["calibrated_file"]
    written = [rows[str(d / "s.npy")]["calibrated_file"], rows[str(d / "b" / "s.npy")]["calibrated_file"]]
    assert len(set(written)) == 2 and all(w.endswith(".calibrated.csv.gz") for w in written)
    for w in written:
        assert_identity(w)


def test_write_refuses_what_it_cannot_write_before_calibrating(six, tmp_path, capsys):
    assert main(["calibrate", str(six / "rec.npy"), "--write", str(tmp_path / "out.xlsx")]) == 2
    assert ".npy, .csv, .csv.gz or .parquet" in capsys.readouterr().err
    assert main(["calibrate", str(six / "rec.npy"), "--write", str(tmp_path / "no" / "out.npy")]) == 2
    assert "no such directory" in capsys.readouterr().err
    assert main(["calibrate", str(six / "rec.npy"), "--write-dir", str(tmp_path)]) == 2
    assert "--write-dir is for a study" in capsys.readouterr().err


def test_the_api_writes_what_the_command_writes(six, tmp_path, capsys):
    cli_out, api_out = tmp_path / "cli.npy", tmp_path / "api.npy"
    assert main(["calibrate", str(six / "rec.npy"), "--write", str(cli_out), "--json"]) == 0
    capsys.readouterr()
    rec = gravcal.read(six / "rec.npy", blocks=True)
    cal = gravcal.calibrate(rec)
    assert cal.write(rec, api_out) == api_out
    a, b = np.load(cli_out), np.load(api_out)
    assert a.dtype == b.dtype and np.array_equal(a, b)
    assert json.loads(sidecar(api_out).read_text())["report"]["heldout_rms_mg"] == cal.heldout_rms_mg
    path_out = gravcal.write_calibrated(six / "rec.npy", cal, tmp_path / "p.npy")
    assert np.array_equal(np.load(path_out), a)
