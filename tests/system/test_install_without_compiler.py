"""`pip install .` with CC=/bin/false: the package installs without its compiled kernels, the build says in one
line why, and `gravcal calibrate` and the Python API calibrate with the numpy references; gravcald says in one
line that its native engine is missing. Into a fresh virtual environment that sees this interpreter's
site-packages as a plain path (numpy, scipy...: nothing downloaded; no editable-install hooks of gravcal)."""
from __future__ import annotations

import json
import os
import shutil
import site
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

SIMULATE = """
import numpy as np
from gravcal.core.samples import raw_triad
from gravcal.core.simulate import simulate
sim = simulate("six_position", seed=3)
raw = raw_triad(sim.samples)
rec = np.zeros(raw.shape[0], dtype=[("t", "<f8"), ("ax", "<f4"), ("ay", "<f4"), ("az", "<f4")])
rec["t"], rec["ax"], rec["ay"], rec["az"] = sim.samples["t"], raw[:, 0], raw[:, 1], raw[:, 2]
np.save("rec.npy", rec)
"""

API = """
import json, sys
import gravcal
import gravcal.core.fastdetect as f, gravcal.core.estimators.parameterization as p
assert f._kernels.__name__.endswith("_reference") and p._jacobians.__name__.endswith("_reference")
assert not any(name.endswith(".so") for name in [getattr(f._kernels, "__file__", "")])
cal = gravcal.calibrate("rec.npy", model="6")
print(json.dumps({"offset": list(map(float, cal.offset)), "site": gravcal.__file__}))
"""


@pytest.mark.slow
def test_install_with_cc_false_calibrates_with_the_numpy_forms(tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, capture_output=True)
    py = venv / "bin" / "python"
    purelib = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             check=True, capture_output=True, text=True).stdout.strip()
    # this interpreter's packages as plain path entries (their .pth hooks not run)
    deps = [p for p in (*site.getsitepackages(), sysconfig.get_paths()["purelib"]) if Path(p).is_dir()]
    Path(purelib, "test_deps.pth").write_text("\n".join(deps) + "\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "VIRTUAL_ENV"))}
    env.update(CC="/bin/false", PIP_NO_DEPS="1")
    # the sources only: a checkout's build/ or in-place .so files must not reach the wheel
    src = tmp_path / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(".git", ".venv", "build", "dist", "*.so", "__pycache__",
                                                             "*.egg-info", ".pytest_cache", ".hypothesis", "out"))
    build = subprocess.run([str(py), "-m", "pip", "install", "-v", "--no-deps", str(src)], cwd=tmp_path, env=env,
                           capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stdout[-2000:] + build.stderr[-2000:]
    said = [line.strip() for line in (build.stdout + build.stderr).splitlines() if line.strip().startswith("gravcal:")]
    assert said == ["gravcal: no working C compiler (/bin/false): installing without the compiled accelerators "
                    "(the numpy forms calibrate; gravcald needs them)"]
    site_dir = Path(purelib) / "gravcal"
    assert site_dir.is_dir() and not list(site_dir.rglob("*.so"))

    env.pop("CC")
    run = dict(cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    subprocess.run([str(py), "-c", SIMULATE], check=True, **run)
    cli = subprocess.run([str(venv / "bin" / "gravcal"), "calibrate", "rec.npy", "--model", "6", "--json"], **run)
    assert cli.returncode == 0, cli.stderr[-2000:]
    out = json.loads(cli.stdout)
    api = subprocess.run([str(py), "-c", API], **run)
    assert api.returncode == 0, api.stderr[-2000:]
    got = json.loads(api.stdout)
    assert got["site"].startswith(purelib)
    assert max(abs(a - b) for a, b in zip(got["offset"], out["calibration"]["offset"])) < 1e-12
    daemon = subprocess.run([str(venv / "bin" / "gravcald"), "--help"], **run)
    lines = daemon.stderr.strip().splitlines()
    assert daemon.returncode != 0 and len(lines) == 1 and "native engine" in lines[0] and "Traceback" not in daemon.stderr


def _native_off_runs(text: str) -> list[list[str]]:
    """The test files of each `GRAVCAL_NATIVE=0 python3 -m pytest` command in a shell text (continued lines joined)."""
    joined = text.replace("\\\n", " ")
    return [[w for w in line.split() if w.startswith("tests/")] for line in joined.splitlines()
            if "GRAVCAL_NATIVE=0 python3 -m pytest" in line]


def test_the_readme_and_ci_run_the_same_commands():
    readme, ci = (ROOT / "README.md").read_text(), (ROOT / ".ci" / "run").read_text()
    assert _native_off_runs(readme) == _native_off_runs(ci) and len(_native_off_runs(ci)) == 1
    for path in _native_off_runs(ci)[0]:
        assert (ROOT / path).is_file(), path
    assert "python3 -m venv" in ci and "python3 -m pip install -q -e '.[test,bench]'" in ci
    suite = "python3 -m pytest -q -n 2 --dist loadgroup\n"
    assert "python3 -m venv .venv" in readme and "python3 -m pip install -e '.[test,bench]' && " + suite in readme
    assert "\n" + suite in ci
