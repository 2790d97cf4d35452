"""``gravcal calibrate`` on a recording holding NaN samples (bursts in an acceleration column and in the
temperature column, .csv and .npy): the reader drops those rows and says so in one warning line, and the
calibration is the one of the same file with the rows deleted, bit for bit. Run as a child process with a
timeout: a NaN that reached a LAPACK call could hang it (dgelsd loops forever on some NaN systems)."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from gravcal.cli.main import main

BURSTS = (7000, 19000, 33000, 47000)  # first rows of 25-sample NaN bursts
BURST = 25
FIELDS = ("t", "ax", "ay", "az", "temp")


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    d = tmp_path_factory.mktemp("nan")
    assert main(["simulate", "--scenario", "six_position", "--seed", "5", "--duration", "600",
                 "--out", str(d / "six.csv")]) == 0
    head = (d / "six.csv").read_text().splitlines()[0].split(",")
    data = np.loadtxt(d / "six.csv", delimiter=",", skiprows=1, usecols=[head.index(f) for f in FIELDS])
    return d, data


def write(path, data: np.ndarray) -> None:
    if path.suffix == ".npy":
        rec = np.zeros(data.shape[0], dtype=[(f, "f8") for f in FIELDS])
        for k, f in enumerate(FIELDS):
            rec[f] = data[:, k]
        np.save(path, rec)
    else:
        lines = [",".join(FIELDS)] + [",".join(repr(float(v)) for v in row) for row in data]
        path.write_text("\n".join(lines) + "\n")


def calibrate(path) -> tuple[int, dict, str]:
    try:
        r = subprocess.run([sys.executable, "-m", "gravcal.cli.main", "calibrate", str(path), "--json", "--quiet"],
                           capture_output=True, text=True, timeout=240)
    except subprocess.TimeoutExpired:
        pytest.fail(f"gravcal calibrate {path.name} did not finish within 240 s")
    return r.returncode, (json.loads(r.stdout) if r.returncode == 0 else {}), r.stderr


@pytest.mark.parametrize("suffix", [".csv", ".npy"])
def test_nan_samples_are_dropped_with_a_warning_and_leave_the_calibration_of_the_rest(recording, suffix):
    d, data = recording
    bad = np.concatenate([np.arange(s, s + BURST) for s in BURSTS])
    nan = data.copy()
    nan[bad[::2], FIELDS.index("ax")] = np.nan
    nan[bad[1::2], FIELDS.index("temp")] = np.nan
    write(d / f"nan{suffix}", nan)
    write(d / f"kept{suffix}", np.delete(data, bad, axis=0))
    code, got, err = calibrate(d / f"nan{suffix}")
    assert code == 0, err[-2000:]
    assert "Traceback" not in err
    warnings = [ln for ln in err.splitlines() if "WARNING" in ln]
    assert len(warnings) == 1 and f"dropped {bad.size} of {data.shape[0]} samples" in warnings[0], err
    assert got["input"]["n_dropped_nonfinite"] == bad.size
    code, want, err = calibrate(d / f"kept{suffix}")
    assert code == 0, err[-2000:]
    assert got["converged"] and got["calibration"] == want["calibration"]
    assert (got["offset"], got["sensitivity"], got["model"]) == (want["offset"], want["sensitivity"], want["model"])
