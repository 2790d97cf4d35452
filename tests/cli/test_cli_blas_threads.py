"""`gravcal calibrate` starts OpenBLAS with one thread, unless the user chose a thread count.

Each case runs in a child process: the setting only counts before numpy loads."""
from __future__ import annotations

import json
import os
import subprocess
import sys

from gravcal.cli.main import BLAS_THREAD_VARIABLES

PROBE = (
    "import sys, json\n"
    "from gravcal.cli.main import pin_blas_threads\n"
    "{before}"
    "pinned = pin_blas_threads({argv!r})\n"
    "import numpy, threadpoolctl\n"
    "from gravcal.core.pipeline import blas_started_single_threaded\n"
    "print(json.dumps([pinned, [p['num_threads'] for p in threadpoolctl.threadpool_info() if p['user_api'] == 'blas'],\n"
    "                  blas_started_single_threaded()]))\n"
)


def _probe(argv: list[str], env_extra: dict[str, str] | None = None, before: str = "") -> list:
    env = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES}
    env.update(env_extra or {})
    out = subprocess.run([sys.executable, "-c", PROBE.format(argv=argv, before=before)], env=env, check=True,
                         capture_output=True, text=True, timeout=120).stdout
    return json.loads(out.strip().splitlines()[-1])


def _free_threads() -> int:
    """OpenBLAS's own thread count in a child with no setting (the machine's cores, at most its build's)."""
    return _probe(["simulate"])[1][0]


def test_calibrate_pins_one_blas_thread():
    pinned, threads, single = _probe(["-v", "calibrate", "rec.npy", "--json"])
    assert pinned is True
    assert threads == [1]
    assert single is True


def test_other_commands_and_user_settings_are_left_alone():
    free = _free_threads()
    assert _probe(["simulate", "--out", "x.npy"]) == [False, [free], False]
    # the user's own count wins, whatever variable carries it
    pinned, threads, single = _probe(["calibrate", "rec.npy"], {"OPENBLAS_NUM_THREADS": "2"})
    assert (pinned, single) == (False, False)
    assert threads == [free if free < 2 else 2]
    pinned, _, single = _probe(["calibrate", "rec.npy"], {"OMP_NUM_THREADS": "2"})
    assert (pinned, single) == (False, False)


def test_too_late_once_numpy_is_loaded():
    """numpy already loaded: setting the variable would change nothing but children, so it is not set."""
    free = _free_threads()
    pinned, threads, single = _probe(["calibrate", "rec.npy"], before="import numpy\n")
    assert (pinned, threads, single) == (False, [free], False)


def test_calibration_without_threadpoolctl_when_blas_started_single(tmp_path):
    """With one BLAS thread from the start, calibrate_recording neither imports nor needs threadpoolctl,
    and gives the same calibration as under threadpoolctl's limit."""
    code = (
        "import sys, json\n"
        "from gravcal.core.simulate import simulate\n"
        "from gravcal.core.samples import raw_triad\n"
        "from gravcal.core.pipeline import calibrate_recording\n"
        "sim = simulate('six_position', seed=3, duration=600.0)\n"
        "rep = calibrate_recording(sim.samples['t'], raw_triad(sim.samples), detection='blocks')\n"
        "print(json.dumps(['threadpoolctl' in sys.modules, rep.calibration.offset.tolist(),\n"
        "                  rep.calibration.sensitivity.tolist(), rep.heldout_rms_mg]))\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES}
    runs = {}
    for one in (True, False):
        e = dict(env, OPENBLAS_NUM_THREADS="1") if one else env
        out = subprocess.run([sys.executable, "-c", code], env=e, check=True, capture_output=True, text=True,
                             timeout=300).stdout
        runs[one] = json.loads(out.strip().splitlines()[-1])
    assert runs[True][0] is False, "threadpoolctl imported although BLAS started with one thread"
    assert runs[False][0] is True, "without the setting the calibration must limit BLAS through threadpoolctl"
    assert runs[True][1:] == runs[False][1:]
