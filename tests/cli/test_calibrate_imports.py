"""What `gravcal calibrate FILE` loads: nothing only other commands or other BLAS setups need.

numpy.random (~10 ms: only simulation draws numbers) and threadpoolctl (~14 ms with its library scan:
not needed when OpenBLAS started with one thread, as `gravcal calibrate` starts it) stay unloaded."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np

from gravcal.cli.main import BLAS_THREAD_VARIABLES


def test_calibrate_loads_neither_numpy_random_nor_threadpoolctl(tmp_path):
    from gravcal.core.samples import raw_triad
    from gravcal.core.simulate import simulate

    sim = simulate("daily_living", seed=4, duration=1800.0)
    raw = raw_triad(sim.samples)
    arr = np.zeros(len(raw), dtype=[("t", "<f8"), ("ax", "<f4"), ("ay", "<f4"), ("az", "<f4")])
    arr["t"], arr["ax"], arr["ay"], arr["az"] = sim.samples["t"], raw[:, 0], raw[:, 1], raw[:, 2]
    path = tmp_path / "rec.npy"
    np.save(path, arr)
    code = ("import sys, io, contextlib, json\n"
            "from gravcal.cli import main as cli\n"
            "cli.pin_blas_threads(['calibrate'])\n"
            "out = io.StringIO()\n"
            "with contextlib.redirect_stdout(out):\n"
            "    status = cli.main(['calibrate', sys.argv[1], '--json'])\n"
            "print(json.dumps([status, json.loads(out.getvalue())['n_windows'],\n"
            "                  sorted(m for m in ('numpy.random', 'threadpoolctl', 'scipy') if m in sys.modules)]))\n")
    env = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES}
    p = subprocess.run([sys.executable, "-c", code, str(path)], env=env, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    status, windows, loaded = json.loads(p.stdout.strip().splitlines()[-1])
    assert status in (0, 3) and windows > 0
    assert loaded == [], f"gravcal calibrate loaded {loaded}"
