"""Device formats through their readers, recognised by content: the vendor's own ActiGraph files
(../shared/data/actigraph_native, read by path), scikit-digital-health's own .cwa / .bin test fixtures
(tests/io/data of its source distribution, found through $GRAVCAL_SKDH_FIXTURES: they are not ours to commit), gzip CSV with mapped columns, and a missing reader naming its extra."""
from __future__ import annotations

import gzip
import json
import os
import shutil
import sys

import numpy as np
import pytest

from gravcal.cli.main import main
from gravcal.io.datasets import data_dir
from gravcal.errors import InputError
from gravcal.io.formats.sniff import sniff
from gravcal.io.recordings import read_recording
from support.inputs import skip_or_fail

FIXTURES = os.environ.get("GRAVCAL_SKDH_FIXTURES", "")


def skdh_fixture(name: str) -> str:
    path = os.path.join(FIXTURES, name)
    if not (FIXTURES and os.path.isfile(path)):
        skip_or_fail(f"scikit-digital-health's test fixture {name} not found: set GRAVCAL_SKDH_FIXTURES to the "
                     f"tests/io/data folder of its source distribution (.ci/fetch_skdh_fixtures.py DIR fetches it)",
                     "GRAVCAL_REQUIRE_SKDH_FIXTURES")
    return path


@pytest.fixture(scope="module")
def native():
    root = data_dir() / "actigraph_native"
    if not (root / "SOURCE.txt").is_file():
        skip_or_fail(f"measured data not found: {root} (set GRAVCAL_DATA to the folder holding actigraph_native)",
                     "GRAVCAL_REQUIRE_DATA")
    return root


def test_idle_sleep_filler_is_what_the_device_flagged(native):
    """The exactly-repeated runs gravcal excludes are the samples pygt3x marks as idle-sleep filled."""
    rec = read_recording(native / "ISM_Enabled.gt3x", exclude_filler=True)
    flagged = rec.metadata["idle_sleep_flagged"]
    assert flagged > 0 and rec.n_filler == flagged
    assert rec.units == "counts" and rec.metadata["format"] == "gt3x"
    assert any("repeated filler" in w for w in rec.warnings)
    kept = read_recording(native / "ISM_Enabled.gt3x")
    assert kept.n_samples == rec.n_samples + flagged


def test_agdc_brings_its_temperature(native):
    rec = read_recording(native / "CPW1C48210013_baseline.agdc")
    assert rec.metadata["format"] == "agdc" and rec.fs == pytest.approx(32.0, rel=1e-3)
    assert rec.temp is not None and rec.temp.shape == rec.t.shape
    # the chamber ran -1, 20 and 30 °C (SOURCE.txt): the interpolated die temperature spans them
    assert rec.temp.min() < 5 and rec.temp.max() > 25
    # the same recording, exported by its vendor reader to gzip CSV (../actigraph_cpw_thermal_chamber)
    csv = native.parent / "actigraph_cpw_thermal_chamber" / "cpw_chamber_raw_counts.csv.gz"
    if csv.is_file():
        ref = read_recording(csv, columns="t=t_unix,ax=x_counts,ay=y_counts,az=z_counts")
        assert ref.metadata["format"] == "csv.gz"
        assert np.array_equal(ref.raw, rec.raw) and np.allclose(ref.t, rec.t, rtol=0, atol=1e-3)


def test_format_is_read_from_content_not_name(native, tmp_path):
    p = tmp_path / "renamed.csv"
    shutil.copyfile(native / "neo.gt3x", p)  # a copy in tmp only, never into the repository
    rec = read_recording(p)
    assert rec.metadata["format"] == "gt3x" and rec.units == "g"
    assert np.median(np.linalg.norm(rec.raw, axis=1)) == pytest.approx(1.0, abs=0.05)


def test_calibrate_reports_the_filler(native, capsys):
    code = main(["calibrate", str(native / "neo.gt3x"), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0 and out["input"]["format"] == "gt3x" and out["input"]["units"] == "g"
    assert out["input"]["n_excluded_filler"] == 0
    code = main(["calibrate", str(native / "ISM_Enabled.gt3x")])
    cap = capsys.readouterr()
    assert "exactly repeated filler" in cap.out + cap.err


@pytest.mark.parametrize("name, kind, fs", [("ax3_sample.cwa", "cwa", 200.0), ("gnactv_sample.bin", "bin", 50.0)])
def test_skdh_fixtures(name, kind, fs):
    path = skdh_fixture(name)
    assert sniff(__import__("pathlib").Path(path)).kind == kind
    rec = read_recording(path, check_saturation=False)
    assert rec.metadata["format"] == kind and rec.units == "g"
    assert rec.metadata["device_fs_hz"] == fs
    assert rec.temp is not None and 0 < np.median(rec.temp) < 50
    assert np.median(np.linalg.norm(rec.raw, axis=1)) == pytest.approx(1.0, abs=0.1)


def test_missing_reader_names_the_extra(monkeypatch, native):
    monkeypatch.setitem(sys.modules, "pygt3x", None)  # makes `import pygt3x` raise ImportError
    with pytest.raises(InputError, match=r"ActiGraph \.gt3x file; reading it needs pygt3x: pip install 'gravcal\[formats\]'"):
        read_recording(native / "neo.gt3x")


def test_missing_skdh_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "skdh", None)
    with pytest.raises(InputError, match=r"Axivity \.cwa file; reading it needs skdh: pip install 'gravcal\[formats\]'"):
        read_recording(skdh_fixture("ax3_sample.cwa"))


def test_gzip_csv_with_mapped_columns(tmp_path, capsys):
    """A gzip CSV named .dat, with a logger's own column names, reads as the plain CSV does."""
    assert main(["simulate", "--scenario", "six_position", "--seed", "3", "--duration", "120",
                 "--out", str(tmp_path / "six.csv")]) == 0
    capsys.readouterr()
    lines = (tmp_path / "six.csv").read_text().splitlines()
    lines[0] = lines[0].replace("t,ax,ay,az,", "t_unix,x_counts,y_counts,z_counts,", 1)
    packed = tmp_path / "logger.dat"
    packed.write_bytes(gzip.compress(("\n".join(lines) + "\n").encode()))
    mapping = "t=t_unix,ax=x_counts,ay=y_counts,az=z_counts"
    rec = read_recording(packed, columns=mapping)
    ref = read_recording(tmp_path / "six.csv")
    assert rec.metadata["format"] == "csv.gz"
    assert np.array_equal(rec.raw, ref.raw) and np.array_equal(rec.t, ref.t)
    with pytest.raises(InputError, match="missing columns t, ax, ay, az; found: t_unix, x_counts"):
        read_recording(packed)
    with pytest.raises(InputError, match=r"--columns t='tee': no such column"):
        read_recording(packed, columns="t=tee")
    with pytest.raises(InputError, match="--columns: unknown name 'speed'"):
        read_recording(packed, columns="speed=x")
    # 8 windows of 120 s: a 6-parameter fit that its contiguous folds cannot confirm (exit 3, "unreliable")
    code = main(["calibrate", str(packed), "--columns", mapping, "--model", "6", "--json"])
    d = json.loads(capsys.readouterr().out)
    assert d["input"]["format"] == "csv.gz" and code == (0 if d["status"] in ("ok", "partial") else 3)
