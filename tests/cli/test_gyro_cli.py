"""`gravcal calibrate --json` reports the gyro when the CSV has gx, gy, gz; `gravcal gyro`."""
import json

import numpy as np
import pytest

from gravcal.core.calibration import Calibration
from gravcal.core.samples import raw_triad
from gravcal.core.simulate import simulate
from gravcal.cli.main import main


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    rng = np.random.default_rng(7)
    sim = simulate("loetters", seed=7, duration=300.0, theta_max_deg=120)
    S = np.diag([5200.0, 6100.0, 6900.0]) + rng.normal(0, 40, (3, 3))
    b = np.array([32700.0, 32800.0, 32900.0])
    gyro = sim.motion.omega @ S.T + b + rng.normal(0, 3, (len(sim.motion), 3))
    raw = raw_triad(sim.samples)
    path = tmp_path_factory.mktemp("gyro") / "rec.csv"
    cols = np.column_stack([sim.samples["t"], raw, gyro])
    np.savetxt(path, cols, delimiter=",", header="t,ax,ay,az,gx,gy,gz", comments="", fmt="%.9g")
    return path, S, b, Calibration.from_dict(sim.truth["calibration"])


def test_calibrate_json_has_the_gyro_object(recording, capsys):
    path, S, b, _ = recording
    assert main(["calibrate", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    g = out["gyro"]
    assert g["axes"] == 3 and g["observable"] is True
    sens = np.array(g["sensitivity"])
    sd = np.array([g["std"][f"S_{r}{c}"] for r in "xyz" for c in "xyz"]).reshape(3, 3)
    assert np.all(np.abs(sens - S) < 4 * sd)  # 9 entries, each within 4 sigma
    bsd = np.array([g["std"][f"b_{a}"] for a in "xyz"])
    assert np.all(np.abs(np.array(g["bias"]) - b) < 4 * bsd)
    assert g["units"]["convention"] == "omega = sensitivity^-1 (raw - bias)"
    assert "pose-to-pose" in g["methods"]["sensitivity"] and "quasi-static" in g["methods"]["bias"]


def test_calibrate_json_without_gyro_columns_has_no_gyro(recording, tmp_path, capsys):
    path, *_ = recording
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    p2 = tmp_path / "acc_only.csv"
    np.savetxt(p2, data[:, :4], delimiter=",", header="t,ax,ay,az", comments="", fmt="%.9g")
    assert main(["calibrate", str(p2), "--json"]) == 0
    assert "gyro" not in json.loads(capsys.readouterr().out)


def test_gyro_command_on_a_recording_and_bad_source(recording, capsys):
    path, S, *_ = recording
    assert main(["gyro", str(path), "--json"]) == 0
    g = json.loads(capsys.readouterr().out)["gyro"]
    assert np.allclose(np.diag(g["sensitivity"]), np.diag(S), rtol=0.02)
    assert g["heldout_rms_deg"] is not None and g["heldout_rms_deg"] < g["heldout_rms_deg_start"]
    assert main(["gyro", "no_such_dataset_or_file"]) == 2
    assert "neither a dataset" in capsys.readouterr().err
