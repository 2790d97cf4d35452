"""Loaders of the measured recordings (io/datasets.py) against the files themselves."""
from __future__ import annotations

import sys

import numpy as np
import pytest

from gravcal.io import datasets as D
from gravcal.errors import InputError
from gravcal.io.recordings import read_recording
from support.concurrent_runs import run_together


def test_data_dir_follows_env(monkeypatch, tmp_path):
    monkeypatch.setenv("GRAVCAL_DATA", str(tmp_path))
    assert D.data_dir() == tmp_path
    monkeypatch.delenv("GRAVCAL_DATA")
    assert D.data_dir() == (D.REPO_ROOT.parent / "shared" / "data").resolve()


def test_unknown_name_and_missing_folder(tmp_path):
    with pytest.raises(InputError, match="unknown dataset 'nope'"):
        D.load("nope", data_dir=tmp_path)
    with pytest.raises(InputError, match="imu_tk_xsens.*not found"):
        D.load("imu_tk_xsens", data_dir=tmp_path)


def test_require_data_turns_skip_into_failure(tmp_path):
    """The shared fixture fails (not skips) when GRAVCAL_REQUIRE_DATA=1 and the folder is absent."""
    test = tmp_path / "test_probe.py"
    test.write_text("def test_probe(measured_data_dir):\n    assert measured_data_dir.is_dir()\n")
    conftest = (D.REPO_ROOT / "tests" / "conftest.py").read_text()
    (tmp_path / "conftest.py").write_text(conftest)
    # the conftest's helpers (tests/support); the probe needs no installed pytest plugin, so none is loaded
    env_base = {"GRAVCAL_DATA": str(tmp_path / "absent"), "PATH": "/usr/bin:/bin",
                "PYTHONPATH": str(D.REPO_ROOT / "tests"), "PYTEST_DISABLE_PLUGIN_AUTOLOAD": "1"}
    import os
    cases = (("1", "1 error"), ("0", "1 skipped"))  # a fixture failure is an error: red, not skipped
    runs = run_together([[sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rs", str(test)]] * 2,
                        timeout=120, envs=[dict(os.environ, **env_base, GRAVCAL_REQUIRE_DATA=r) for r, _ in cases],
                        cwd=tmp_path)
    for (_, expect), out in zip(cases, runs):
        assert expect in out.stdout, out.stdout + out.stderr
        assert "measured data not found" in out.stdout


def test_xsens(measured_data_dir):
    r = D.load("imu_tk_xsens")
    assert r.acc.shape == (51175, 3) and r.gyro.shape == (51175, 3) and r.temp is None
    assert r.fs == 100.0
    assert r.t[0] == 0.0 and np.all(np.diff(r.t) > 0)
    assert r.duration_s == pytest.approx(511.7, abs=0.2)
    # initial ~50 s static: the norm of the offset-removed mean is about one g at ~4066 counts/g
    still = r.acc[: 40 * 100]
    g = np.linalg.norm(still.mean(0) - 32768.0) / r.meta["acc_per_g"]
    assert 0.8 < g < 1.2
    assert "Xsens" in r.source


def test_actigraph_temperature_interpolated(measured_data_dir):
    r = D.load("actigraph_cpw_thermal_chamber")
    assert r.acc.shape == (409600, 3) and r.fs == 32.0
    assert np.allclose(np.diff(r.t), 1 / 32)
    assert r.temp is not None and r.temp.shape == (409600,)
    # chamber profile: ~19 °C -> ~ -1 °C -> 20 -> 30 °C (ADXL die temperature)
    assert r.temp.min() < 0.0 and r.temp.max() > 30.0
    # interpolation from the 4 s table: sample exactly on a table time equals the table value
    tab = np.loadtxt(measured_data_dir / "actigraph_cpw_thermal_chamber" / "cpw_chamber_temperature_C.csv",
                     delimiter=",", skiprows=1)
    k = 128 * 10  # 40 s in, one table row per 128 samples
    assert r.temp[k] == pytest.approx(tab[10, 2])
    assert r.temp[k + 64] == pytest.approx(0.5 * (tab[10, 2] + tab[11, 2]))
    mcu = D.load("actigraph_cpw_thermal_chamber/mcu")
    assert mcu.temp[k] == pytest.approx(tab[10, 1]) and mcu.meta["temp_source"] == "MCU"


def test_ferraris_sections(measured_data_dir):
    r = D.load("imucal_ferraris")
    assert r.fs == 102.4 and r.acc.shape == (10376, 3)
    assert set(r.sections) == {"x_p", "x_a", "y_p", "y_a", "z_p", "z_a", "x_rot", "y_rot", "z_rot"}
    # static faces: |mean acc| ~ 1 g in m/s^2, and x_p points +x
    xp = r.section("x_p")
    assert np.linalg.norm(xp.acc.mean(0)) == pytest.approx(9.81, rel=0.10)  # uncalibrated: 10.34 m/s^2
    assert xp.acc.mean(0)[0] > 9.0
    a = D.load("imucal_ferraris/annotated")
    assert a.acc.shape == (9414, 3) and a.fs == 204.8
    assert sum(b - s for s, b in a.sections.values()) == 9414
    xa = a.section("x_a").acc.mean(0)
    assert xa[0] < -1800  # x pointing down, ~2048 counts/g
    with pytest.raises(InputError, match="no section 'w_p'"):
        a.section("w_p")


def test_mpu6050_headers(measured_data_dir):
    r = D.load("mpu6050_tomisuarez")
    assert r.name == "mpu6050_tomisuarez/calibration" and r.fs == 100.0
    assert r.acc.shape == (10245, 3) and r.gyro.shape == (10245, 3)
    assert r.meta["header"]["Initialization time"] == "36.5"
    assert r.sections["initial_static"] == (0, 3650)
    s = D.load("mpu6050_tomisuarez/static")
    assert s.acc.shape == (44930, 3)
    assert np.linalg.norm(s.acc.mean(0)) / s.meta["acc_per_g"] == pytest.approx(1.0, abs=0.12)  # nominal scale, uncalibrated: 0.92
    assert D.load("mpu6050_tomisuarez/x_rot").acc.shape == (9987, 3)


@pytest.mark.parametrize("name", ["imu_tk_xsens", "imucal_ferraris/annotated", "mpu6050_tomisuarez/static"])
def test_calibrate_csv_roundtrip(measured_data_dir, tmp_path, name):
    r = D.load(name)
    p = D.to_calibrate_csv(r, tmp_path / "rec.csv")
    back = read_recording(p, check_saturation=False)
    assert back.raw.shape == r.acc.shape
    assert np.allclose(back.raw, r.acc) and np.allclose(back.t, r.t, atol=1e-6)
    assert back.gyro is not None and np.allclose(back.gyro, r.gyro)
    assert back.fs == pytest.approx(r.fs, rel=0.02)


def test_calibrate_csv_with_temperature(measured_data_dir, tmp_path):
    r = D.load("actigraph_cpw_thermal_chamber")
    p = D.to_calibrate_csv(r, tmp_path / "acti.csv")
    back = read_recording(p, check_saturation=False)
    assert back.temp is not None and np.allclose(back.temp, r.temp, atol=1e-4)
    assert back.fs == pytest.approx(32.0)
