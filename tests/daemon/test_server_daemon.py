"""gravcald as a subprocess with a fake driver: sd_notify, watchdog, SIGHUP, SIGTERM, resume.

The fake driver (below) synthesises the ADXL210 duty cycles of a board held in a sequence
of random still poses with a movement between them, from a known true calibration
raw = K a + o, faster than real time. The real detector and recursive estimator run.
"""
import json
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from gravcal.core.samples import empty
from gravcal.clients.client import Client

TRUE_OFFSET = np.array([0.51, 0.49, 0.505])  # duty cycle
TRUE_SENS = np.array([0.042, 0.038, 0.0415])  # duty cycle per g (datasheet start: 0.5 and 0.04)
G = 9.80665


class FakeDriver:
    """Still poses held ``hold_s`` each (the first 0.8 s of each hold is a movement), at
    ``speed`` x real time; silent while ``silence_file`` exists."""

    def __init__(self, fs=200.0, hold_s=4.0, noise_g=0.003, seed=0, speed=40.0, silence_file=None):
        self.fs, self.hold, self.noise, self.speed = fs, hold_s, noise_g, speed
        self.rng = np.random.default_rng(seed)
        r = np.random.default_rng(seed + 1).normal(size=(40, 3))
        self.poses = r / np.linalg.norm(r, axis=1)[:, None]
        self.n = 0
        self.t0 = time.monotonic()
        self.silence_file = silence_file
        self.closed = False

    def read(self, max_samples=256, timeout=0.1):
        if self.silence_file and os.path.exists(self.silence_file):
            time.sleep(timeout)
            self.t0 = time.monotonic() - self.n / (self.fs * self.speed)  # resume without a burst
            return empty(0)
        due = int((time.monotonic() - self.t0) * self.fs * self.speed)
        m = min(max_samples, due - self.n)
        if m <= 0:
            time.sleep(min(timeout, 0.005))
            return empty(0)
        idx = np.arange(self.n, self.n + m)
        t = idx / self.fs
        pose = self.poses[(t // self.hold).astype(int) % len(self.poses)]
        phase = t % self.hold
        bump = np.where((phase < 0.8)[:, None], 0.5 * np.sin(2 * np.pi * 2.5 * phase)[:, None] * pose, 0.0)
        a = pose + bump + self.rng.normal(scale=self.noise, size=(m, 3))
        s = empty(m)
        s["t"], s["seq"], s["t2"] = t, idx, 20000
        s["t1"][:, :3] = np.round((a * TRUE_SENS + TRUE_OFFSET) * 20000)
        s["t1"][:, 3] = s["t1"][:, 0]
        s["temp"], s["vsupply"] = 25.0, 3.3
        self.n += m
        return s

    def stats(self):
        return {"frames": self.n, "crc_errors": 0}

    def close(self):
        self.closed = True


CHILD = textwrap.dedent(
    """
    import sys
    sys.path.insert(0, {tests!r})
    from test_server_daemon import FakeDriver
    from gravcal.daemon.gravcald import main
    sys.exit(main(sys.argv[1:], driver=FakeDriver(silence_file={silence!r})))
    """
)


class Notifications:
    def __init__(self, path):
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(path)
        self.sock.settimeout(0.05)
        self.log = []  # (monotonic time, message)

    def drain(self):
        while True:
            try:
                self.log.append((time.monotonic(), self.sock.recv(4096).decode()))
            except socket.timeout:
                return

    def wait_for(self, prefix, timeout=30.0, after=0.0):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.drain()
            for t, m in self.log:
                if t >= after and m.startswith(prefix):
                    return t
        raise AssertionError(f"no {prefix!r} notification; got {[m for _, m in self.log][-10:]}")


def start_daemon(tmp_path, notify_path, extra_env=None):
    silence = str(tmp_path / "silence")
    env = dict(os.environ, NOTIFY_SOCKET=notify_path, WATCHDOG_USEC="400000", **(extra_env or {}))
    env.pop("LISTEN_FDS", None)
    code = CHILD.format(tests=str(Path(__file__).parent), silence=silence)
    proc = subprocess.Popen([sys.executable, "-c", code, "--config", str(tmp_path / "gravcald.toml")],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return proc, silence


CONFIG = """
[socket]
path = "{sock}"
[state]
directory = "{state}"
save_interval_s = 0.2
[detector]
threshold_g = {threshold}
"""


def write_config(tmp_path, threshold=0.02, sock=None, extra=""):
    (tmp_path / "gravcald.toml").write_text(
        CONFIG.format(sock=sock or tmp_path / "g.sock", state=tmp_path / "state", threshold=threshold) + extra)


def wait_accepted(client, timeout=60.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        cal = client.calib()
        if cal.get("accepted") and cal["n_windows"] >= 10:
            return cal
        time.sleep(0.2)
    raise AssertionError(f"calibration not accepted within {timeout} s: {cal}")


def test_daemon_lifecycle_notify_watchdog_reload_stop_and_resume(tmp_path):
    write_config(tmp_path)
    notes = Notifications(str(tmp_path / "notify"))
    proc, silence = start_daemon(tmp_path, str(tmp_path / "notify"))
    sock = str(tmp_path / "g.sock")
    try:
        t_ready = notes.wait_for("READY=1")
        assert os.path.exists(sock)  # READY only after the socket is bound
        with Client(sock, timeout=10) as c:
            cal = wait_accepted(c)
            # the fit recovers the true calibration from the datasheet start (5 % off in
            # sensitivity): within 6 reported std, plus 2e-4 for the model floor
            std = cal["std"]
            for i, ax in enumerate("xyz"):
                assert abs(cal["offset"][i] - TRUE_OFFSET[i]) < 6 * std[f"o_{ax}"] + 2e-4
                assert abs(cal["sensitivity"][i][i] - TRUE_SENS[i]) < 6 * std[f"s_{ax}"] + 2e-4
            # samples now come out calibrated: |a| of static samples is 1 g
            norms = []
            for m in c.watch(rate=0):
                if m["class"] == "IMU" and m["static"]:
                    norms.append(np.linalg.norm(m["acc"]))
                if len(norms) >= 400:
                    break
            # per-sample noise 3 mg -> the median of 400 is within ~0.3 mg; 2 mg allows for the fit
            assert abs(np.median(norms) - G) < 0.002 * G
            c.set_watch(enable=False)
            st = c.status()
            assert st["device"]["frames"] > 0 and st["calibration"]["accepted"] is True
            assert st["ring"]["overwritten"] == 0

        # watchdog: fed while samples flow (period = WATCHDOG_USEC / 2 = 0.2 s)
        t_feed = notes.wait_for("WATCHDOG=1", after=t_ready)
        notes.wait_for("WATCHDOG=1", after=t_feed + 0.01)
        Path(silence).touch()  # the bus goes silent
        time.sleep(0.5)
        notes.drain()
        t_silent = time.monotonic()
        time.sleep(1.5)  # 7 feed periods
        notes.drain()
        assert [m for t, m in notes.log if t > t_silent and m == "WATCHDOG=1"] == []
        os.unlink(silence)  # data again: fed again
        notes.wait_for("WATCHDOG=1", after=time.monotonic())

        # SIGHUP: a live setting changes, a restart-only one is refused with a warning
        write_config(tmp_path, threshold=0.03, sock=tmp_path / "other.sock")
        t_hup = time.monotonic()
        proc.send_signal(signal.SIGHUP)
        notes.wait_for("RELOADING=1", after=t_hup)
        notes.wait_for("READY=1", after=t_hup)
        # a broken config on reload: keep running with the old one
        (tmp_path / "gravcald.toml").write_text('[detector]\nthreshold_g = "high"\n')
        t_hup2 = time.monotonic()
        proc.send_signal(signal.SIGHUP)
        notes.wait_for("READY=1", after=t_hup2)
        with Client(sock, timeout=10) as c:
            assert c.status()["class"] == "STATUS"
            Path(silence).touch()  # freeze the estimate so the saved revision is known
            time.sleep(0.5)
            last = c.calib()

        t_term = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
        notes.wait_for("STOPPING=1", after=t_term)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert "[socket] path changed; it takes effect after a restart" in err
    assert "configuration reloaded" in err
    assert "threshold_g: expected a number, got 'high'; keeping the running configuration" in err
    assert not os.path.exists(sock)  # the daemon bound it, the daemon removed it
    saved = json.loads((tmp_path / "state" / "state.json").read_text())
    assert saved["revision"] == last["revision"] and saved["accepted"] is True
    assert saved["calibration"]["offset"] == pytest.approx(last["offset"], abs=1e-12)

    # restart: resumes the saved calibration instead of learning again from the datasheet
    write_config(tmp_path)
    os.unlink(silence)
    proc, _ = start_daemon(tmp_path, str(tmp_path / "notify"))
    try:
        notes.wait_for("READY=1", after=time.monotonic() - 0.01)
        with Client(sock, timeout=10) as c:
            first = c.calib()
            assert first["revision"] >= saved["revision"] and first["accepted"] is True
            assert first["offset"] == pytest.approx(saved["calibration"]["offset"], abs=1e-3)
            norms = []
            for m in c.watch(rate=0):  # calibrated from the first samples on
                if m["class"] == "IMU" and m["static"]:
                    norms.append(np.linalg.norm(m["acc"]))
                if len(norms) >= 200:
                    break
            assert abs(np.median(norms) - G) < 0.002 * G
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
        assert proc.returncode == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def test_daemon_refuses_a_socket_in_use(tmp_path):
    sock = tmp_path / "busy.sock"
    holder = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    holder.bind(str(sock))
    holder.listen(1)
    write_config(tmp_path, sock=sock)
    proc, _ = start_daemon(tmp_path, str(tmp_path / "notify"))
    out, err = proc.communicate(timeout=60)
    holder.close()
    assert proc.returncode == 2
    assert err.strip().splitlines()[-1] == f"gravcald: error: another gravcald is running on {sock} (a process accepts connections there)"


def test_daemon_starts_from_defaults_when_state_is_corrupt(tmp_path):
    (tmp_path / "state").mkdir()
    (tmp_path / "state" / "state.json").write_text('{"schema": "gravcal.state/1", "revis')
    write_config(tmp_path)
    notes = Notifications(str(tmp_path / "notify"))
    proc, _ = start_daemon(tmp_path, str(tmp_path / "notify"))
    try:
        notes.wait_for("READY=1")
        with Client(str(tmp_path / "g.sock"), timeout=10) as c:
            st = c.status()
            assert any("unusable" in n and "corrupt-" in n for n in st["notes"])
            assert any(n.startswith("starting from ADXL210 datasheet values") for n in st["notes"])
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    aside = [n for n in os.listdir(tmp_path / "state") if n.startswith("state.json.corrupt-")]
    assert len(aside) == 1
    assert (tmp_path / "state" / aside[0]).read_text() == '{"schema": "gravcal.state/1", "revis'
    assert "moved it to" in err
