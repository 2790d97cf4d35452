"""gravcald's processing on a stream with missing values (a period read as 0: the duty cycle is NaN; the
temperature and supply ADC out of range: NaN), block by block as the service runs it: it finishes (a child
process with a timeout: a NaN reaching LAPACK could hang the processing thread), every published revision
holds finite values, and the accepted calibration agrees with the one of the intact stream within the
uncertainty both state."""
from __future__ import annotations

import json
import textwrap

from tests.support.child import run_child

CHILD = textwrap.dedent("""
    import json
    import numpy as np
    from gravcal.core.simulate import simulate
    from gravcal.daemon.config import load_config
    from gravcal.daemon.persistence import CalibrationState
    from gravcal.daemon.processing import Processor, nominal_calibration

    FS = 100.0
    samples = simulate("six_position", seed=3, duration=900.0, fs=FS).samples

    def run(s):
        p = Processor(load_config(None, {"device.fs_hz": FS}),
                      CalibrationState(nominal_calibration(), 0, None, False, {}), resumed=False)
        finite, last = True, -1
        for i in range(0, s.shape[0], 100):
            p.process(s[i:i + 100])
            st = p.state
            if st.revision != last:
                last = st.revision
                c = st.calibration
                finite &= bool(np.isfinite(c.offset).all() and np.isfinite(c.sensitivity).all())
        c = p.state.calibration
        return {"accepted": bool(p.state.accepted), "finite": finite, "std": c.std,
                "values": {"o_x": c.offset[0], "o_y": c.offset[1], "o_z": c.offset[2], "s_x": c.sensitivity[0, 0],
                           "s_y": c.sensitivity[1, 1], "s_z": c.sensitivity[2, 2]}}

    bad = samples.copy()
    idx = np.arange(2000, bad.shape[0], 1777)
    bad["t2"][idx, 0] = 0  # a missing period of chip a: its channels' duty cycles are NaN
    bad["temp"][idx + 5] = np.nan
    bad["vsupply"][idx + 9] = np.nan
    print(json.dumps({"clean": run(samples), "missing": run(bad), "n_bad": int(idx.size)}, default=float))
""")


def test_missing_samples_leave_the_processing_running_and_the_calibration_within_its_uncertainty():
    stdout = run_child(CHILD, timeout=300, what="the processing of 15 minutes of samples with missing values")
    r = json.loads(stdout)
    clean, missing = r["clean"], r["missing"]
    assert r["n_bad"] > 0 and clean["accepted"] and missing["accepted"]
    assert clean["finite"] and missing["finite"]
    for name, v in missing["values"].items():
        tol = 3.0 * (clean["std"][name] ** 2 + missing["std"][name] ** 2) ** 0.5
        assert abs(v - clean["values"][name]) < tol, (name, v, clean["values"][name], tol)
