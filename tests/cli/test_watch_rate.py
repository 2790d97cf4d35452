"""`gravcal watch --rate N` honoured against a running real-time daemon.

The server decimates by sample time `t` (docs/socket-protocol.md); the `pattern` scenario's `t`
follows the device clock. Jitter backwards is tested in test_server_limits.py."""
import json
import subprocess
import sys
import time

import pytest

from support.gravcald_process import GravcaldProcess

# measures rates, wake-ups or deadlines in real time: under pytest-xdist (--dist loadgroup) it runs on one
# worker, after the other real-time tests rather than beside them
pytestmark = pytest.mark.xdist_group("realtime")


@pytest.fixture(scope="module")
def daemon():
    d = GravcaldProcess(None, "--bus", "serial", "--scenario", "pattern", "--speed", "1", fs=200.0)
    try:
        d.wait_serving()
        with d.client() as c:  # past the emulator's start-up catch-up: samples at the device's pace
            c.set_watch(enable=True, rate=0)
            last = time.monotonic()
            while True:
                if c.read_message()["class"] == "IMU":
                    now = time.monotonic()
                    if now - last > 0.003:
                        break
                    last = now
        yield d
    finally:
        d.stop()


@pytest.mark.parametrize("rate", [1.0, 4.0])
def test_a_rate_limited_watcher_gets_at_most_rate_samples_per_second(daemon, rate):
    n = 6
    with daemon.client() as c:
        arrivals = []
        for msg in c.watch(rate=rate):
            if msg["class"] == "IMU":
                arrivals.append(time.monotonic())
                if len(arrivals) == n:
                    break
    gaps = [b - a for a, b in zip(arrivals, arrivals[1:])]
    # the first sample opens the watch mid-bucket; from then on one per 1/rate s of sample time,
    # which at real time is wall time (20 % for the device clock and scheduling)
    assert min(gaps[1:]) >= 0.8 / rate, (rate, [round(g, 3) for g in gaps])
    assert max(gaps) <= 2.0 / rate + 0.5  # and they keep coming


def test_gravcal_watch_cli_honours_rate(daemon):
    p = subprocess.run([sys.executable, "-m", "gravcal.cli.main", "watch", "--socket", daemon.sock,
                        "--rate", "2", "--count", "4", "--json"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    t = [m["t"] for m in map(json.loads, p.stdout.splitlines()) if m["class"] == "IMU"]
    assert len(t) == 4
    steps = [b - a for a, b in zip(t, t[1:])]
    assert min(steps[1:]) >= 0.5 - 0.01 and max(steps) <= 1.0, steps  # 2 Hz of sample time
