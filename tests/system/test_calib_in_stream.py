"""A watcher can tell which calibration corrected each sample: every IMU line after a CALIB is corrected
with that CALIB's `applied_revision` and none before, as a client reading the stream sees it.

The check recomputes each sample's acc from its raw duty cycles (a = 9.80665 · K⁻¹(duty − o), the
published formula) with the values of the last CALIB received, against `gravcald --emulate` in a
six_position session where the estimator accepts several revisions while the stream runs. Tolerance:
duty is published with 6 decimals (rounding ≤ 5e-7), K⁻¹ entries ≤ 1/0.035 per g, three terms:
≤ 3 · 5e-7 / 0.035 · 9.81 ≈ 4.2e-4 m/s², plus acc's own 5-decimal rounding (5e-6): 5e-4 m/s² bounds
both. Successive early revisions correct many samples differently by more than twice that (asserted: the
stream is read until a thousand such samples were seen), so a sample corrected with another revision than
announced fails the check.
"""
from __future__ import annotations

import json
import socket
import time

import numpy as np
from support.gravcald_process import GravcaldProcess

G = 9.80665
TOL_MS2 = 5e-4  # see the module docstring


def _acc(calib: dict, duty: list) -> np.ndarray:
    k = np.asarray(calib["sensitivity"], dtype=float)
    return G * np.linalg.solve(k, np.asarray(duty[:3], dtype=float) - np.asarray(calib["offset"], dtype=float))


def test_every_sample_after_a_calib_is_corrected_with_it(tmp_path):
    d = GravcaldProcess(tmp_path, "--bus", "serial", "--speed", "20", "--scenario", "six_position",
                        "--duration", "3000", fs=200.0)
    try:
        d.wait_serving()
        s = socket.socket(socket.AF_UNIX)
        s.settimeout(30)
        s.connect(d.sock)
        f = s.makefile("rb")
        assert json.loads(f.readline())["class"] == "VERSION"
        s.sendall(b'?WATCH={"enable":true,"raw":true};\n')
        values: dict = {}  # applied revision -> its CALIB (offset, sensitivity)
        current = None
        bad, n, revisions, deadline = [], 0, [], time.monotonic() + 240
        telling = 0  # samples the previous accepted revision would have corrected differently (> 2 TOL_MS2)
        # read until the check has shown its power (or the stream ends): how soon revisions follow each other
        # depends on the host's load, so a fixed number of revisions may leave too few telling samples
        while time.monotonic() < deadline and not (len(revisions) >= 3 and telling > 1000):
            line = f.readline()
            if not line:
                break
            m = json.loads(line)
            if m["class"] == "CALIB":
                rev = m.get("applied_revision")
                if rev is None or rev == m["revision"]:  # a CALIB carrying the applied values
                    values[rev] = m
                if rev != current and rev in values:
                    current = rev
                    if rev is not None:
                        revisions.append(rev)
            elif m["class"] == "IMU" and current in values and None not in m["duty"][:3]:
                n += 1
                err = np.max(np.abs(_acc(values[current], m["duty"]) - np.asarray(m["acc"], dtype=float)))
                if err > TOL_MS2 and len(bad) < 5:
                    bad.append((m["seq"], current, float(err)))
                if len(revisions) >= 2:
                    before = _acc(values[revisions[-2]], m["duty"])
                    telling += bool(np.max(np.abs(before - np.asarray(m["acc"], dtype=float))) > 2 * TOL_MS2)
        s.close()
    finally:
        d.stop()
    assert len(revisions) >= 3, f"fewer accepted revisions than needed to test: {revisions}"
    assert not bad, f"samples corrected with another calibration than the last CALIB announced (seq, rev, err): {bad}"
    # the check has power: many samples would have failed it had they been corrected with the previous revision
    assert telling > 100, (telling, n, revisions)
