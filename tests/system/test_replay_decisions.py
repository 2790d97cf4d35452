"""One online policy: gravcald (a real process, emulated I2C bus at full speed) and an in-process replay of
the windows it fed (``--record-windows``) through ``OnlineCalibrator.feed`` publish the same revisions
with the same verdicts and the same parameters, bit for bit: the daemon only feeds windows and publishes."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from gravcal.core.estimators.online import OnlineCalibrator
from gravcal.core.windows import Window
from gravcal.clients.client import Client, ClientError
from gravcal.daemon.config import load_config
from gravcal.daemon.processing import nominal_calibration
from gravcal.daemon.window_log import WindowRecorder, read_windows
from support.umockdev import require_umockdev

# sagittal_postures (stand, sit, bend, kneel, lie, ...) from the datasheet start: provisional offsets that are
# published but not accepted, the bootstrap seed fit, windows the 5 sigma gate rejects, then order 6 accepted
DURATION_S = 900.0
SCENARIO = "sagittal_postures"


def replay(cfg, windows: list[Window]) -> list[tuple]:
    """The windows through the service's online calibrator, in process: (calibration, accepted) per revision."""
    e = cfg.estimator
    oc = OnlineCalibrator.for_service(nominal_calibration(e.model), model=e.model, extended_terms=e.extended_terms,
                                      min_windows=e.min_windows, fs=cfg.device.fs_hz,
                                      process_noise=e.process_noise if e.process_noise > 0 else None)
    revisions = []
    for w in windows:
        step = oc.feed(w)
        if step.calibration is not None:
            revisions.append((step.calibration, step.accepted))
    return revisions


def test_gravcald_and_an_offline_replay_make_the_same_decisions(tmp_path: Path):
    require_umockdev()  # the session runs on the emulated I2C bus
    sock, windows_file = str(tmp_path / "g.sock"), tmp_path / "windows.jsonl"
    argv = [sys.executable, "-m", "gravcal.daemon.gravcald", "--emulate", "--bus", "i2c", "--speed", "max",
            "--scenario", SCENARIO, "--duration", str(DURATION_S), "--seed", "0", "--socket", sock,
            "--state-dir", str(tmp_path / "state")]
    env = {k: v for k, v in os.environ.items() if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "LISTEN_FDS")}
    effective = subprocess.run([*argv, "--print-config"], capture_output=True, text=True, env=env, check=True)
    (tmp_path / "effective.toml").write_text(effective.stdout)
    cfg = load_config(str(tmp_path / "effective.toml"))
    last_seq = int(DURATION_S * cfg.device.fs_hz) - 1

    log = open(tmp_path / "gravcald.log", "w")
    proc = subprocess.Popen([*argv, "--record-windows", str(windows_file)], stdout=log, stderr=subprocess.STDOUT,
                            env=env)
    published: dict[int, dict] = {}
    try:
        deadline = time.monotonic() + 240
        while not os.path.exists(sock):
            assert proc.poll() is None and time.monotonic() < deadline, (tmp_path / "gravcald.log").read_text()[-2000:]
            time.sleep(0.05)
        with Client(sock, timeout=10) as watcher, Client(sock, timeout=10) as poller:
            watcher.set_watch(enable=True, rate=0.2)  # CALIB on every published revision; IMU thinned out
            quiet_since, last_count = time.monotonic(), -1
            while True:
                assert time.monotonic() < deadline, "the emulated session did not finish in time"
                try:
                    msg = watcher.read_message(timeout=0.5)
                except ClientError:
                    msg = {}
                if msg.get("class") == "CALIB":
                    published[msg["revision"]] = msg
                st = poller.status()
                count = st["device"]["samples"]
                if count != last_count or st["ring"]["size"] or st["processing"]["lag_s"]:
                    quiet_since, last_count = time.monotonic(), count
                # the bus may lose the last samples (a full FIFO): the session is over when the analysed
                # data reached its last seconds and nothing more arrives
                near_end = (st["processing"]["analysed_seq"] or 0) >= last_seq - 5 * cfg.device.fs_hz
                if near_end and time.monotonic() - quiet_since > 2.0:
                    final = poller.calib()
                    published[final["revision"]] = final
                    break
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
        log.close()

    revisions = replay(cfg, read_windows(windows_file))
    # the session exercises the decisions: revisions published without acceptance, and accepted ones
    assert any(acc for _, acc in revisions) and any(not acc and cal.converged for cal, acc in revisions)
    assert max(published) == len(revisions), (sorted(published), len(revisions))
    compared = 0
    for r, msg in sorted(published.items()):
        if r == 0:
            continue  # the start, before any window
        cal, accepted = revisions[r - 1]
        assert (msg["model"], msg["accepted"], msg["n_windows"]) == (cal.model, accepted, cal.n_windows), r
        np.testing.assert_array_equal(msg["offset"], cal.offset)
        np.testing.assert_array_equal(msg["sensitivity"], cal.sensitivity)
        compared += 1
    assert compared >= 2 and published[len(revisions)]["accepted"]


def test_window_log_round_trip_and_a_torn_line(tmp_path: Path):
    rng = np.random.default_rng(1)
    ws = [Window(i * 100, i * 100 + 80, i * 0.5, i * 0.5 + 0.4, rng.normal(size=3), np.cov(rng.normal(size=(3, 9))),
                 rng.normal(size=2)) for i in range(3)]
    rec = WindowRecorder(tmp_path / "w.jsonl")
    for w in ws:
        rec(w)
    rec.close()
    back = read_windows(tmp_path / "w.jsonl")
    for a, b in zip(ws, back):
        assert (a.start, a.end, a.t_start, a.t_end) == (b.start, b.end, b.t_start, b.t_end)
        for f in ("mean", "cov", "aux_mean"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    with open(tmp_path / "w.jsonl", "a") as f:
        f.write(json.dumps({"class": "WINDOW", "start": 1})[:20])
    with pytest.raises(ValueError, match="line 4 is not a window record"):
        read_windows(tmp_path / "w.jsonl")
