"""`gravcal watch` and the Python client against a live server."""
import argparse
import io
import json
import threading
import time

import numpy as np
import pytest

from gravcal.cli import cmd_watch
from gravcal.clients.client import Client, ClientError
from gravcal.daemon.server import SocketServer
from gravcal.core.samples import empty


def parse(argv):
    p = argparse.ArgumentParser()
    sub = p.add_subparsers()
    cmd_watch.add_parser(sub)
    return p.parse_args(["watch", *argv])


@pytest.fixture
def server(tmp_path):
    srv = SocketServer(str(tmp_path / "g.sock")).start()
    yield srv
    srv.stop()


def feeder(srv, stop, n=40):
    """Publish blocks of 40 samples (0.2 s at 200 Hz) until stopped."""
    seq = 0
    while not stop.is_set():
        s = empty(n)
        s["seq"] = seq + np.arange(n)
        s["t"] = s["seq"] / 200.0
        s["t1"], s["t2"] = 10000, 20000
        acc = np.tile([3.0, 4.0, 0.0], (n, 1))  # |a| = 5 m/s²
        srv.publish(s, acc, np.full(n, 0.25), np.arange(n) % 2 == 0)
        if seq == 0:
            srv.set_calibration({"revision": 2, "model": "6", "accepted": True, "n_windows": 8,
                                 "offset": [0.5, 0.5, 0.5], "sensitivity": np.diag([0.125] * 3).tolist()})
        seq += n
        time.sleep(0.01)


def run_watch(srv, argv):
    stop = threading.Event()
    t = threading.Thread(target=feeder, args=(srv, stop))
    t.start()
    out = io.StringIO()
    try:
        code = cmd_watch.run(parse(["--socket", srv.address, *argv]), out=out)
    finally:
        stop.set()
        t.join()
    return code, out.getvalue().splitlines()


def test_watch_prints_samples_and_calibration(server):
    code, lines = run_watch(server, ["--count", "5", "--rate", "0", "--raw"])
    assert code == 0
    imu = [x for x in lines if x.startswith("IMU")]
    assert len(imu) == 5
    assert "|a|   5.000 m/s² (0.5099 g)" in imu[0]
    assert "gyro  +0.250 rad/s" in imu[0] and "duty 0.50000 0.50000 0.50000 0.50000" in imu[0]
    assert ("static" in imu[0]) != ("static" in imu[1])  # alternating in the feed
    calib = [x for x in lines if x.startswith("CALIB")]
    assert calib and "revision 2 model 6 (accepted, 8 windows)" in calib[0] and "sensitivity 0.12500 0.12500 0.12500" in calib[0]


def test_watch_json_mode_and_rate(server):
    code, lines = run_watch(server, ["--count", "6", "--rate", "10", "--json"])
    msgs = [json.loads(x) for x in lines]
    imu = [m for m in msgs if m["class"] == "IMU"]
    assert code == 0 and len(imu) == 6
    assert np.diff([m["t"] for m in imu]).min() >= 0.1 - 1e-9  # at most 10 per second of sample time
    assert imu[0]["acc"] == [3.0, 4.0, 0.0]


def test_watch_errors(tmp_path):
    with pytest.raises(ClientError, match=f"cannot connect to {tmp_path}/none.sock: no such socket"):
        cmd_watch.run(parse(["--socket", str(tmp_path / "none.sock")]))
    with pytest.raises(ValueError, match="--rate must be"):
        cmd_watch.run(parse(["--rate", "-1"]))


def test_client_times_out_cleanly_when_nothing_comes(server):
    with Client(server.address, timeout=0.3) as c:
        c.set_watch()
        with pytest.raises(ClientError, match="no message .* within 0.3 s"):
            c.read_message()


def test_watchers_get_every_sample_while_the_server_thread_is_stuck(tmp_path):
    """The publishing thread sends to the watchers' sockets itself: a server thread held up
    elsewhere (a loaded host, a slow request) delays no sample and loses none."""
    srv = SocketServer(str(tmp_path / "g.sock")).start()
    try:
        with Client(srv.address, timeout=5) as a, Client(srv.address, timeout=5) as b:
            for c in (a, b):
                c.set_watch(enable=True, rate=0)
            flush, held = srv._flush_published, threading.Event()

            def stuck() -> None:
                held.wait(10)
                flush()

            srv._flush_published = stuck
            srv._wake()  # the server thread now waits inside stuck()
            time.sleep(0.2)
            for k in range(10):
                s = empty(10)
                s["seq"] = 10 * k + np.arange(10)
                s["t"] = s["seq"] / 200.0
                s["t1"], s["t2"] = 10000, 20000
                srv.publish(s, np.tile([0.0, 0.0, 9.80665], (10, 1)), np.full(10, np.nan), np.ones(10, bool))
            try:
                for c in (a, b):
                    got = [c.read_message(timeout=5) for _ in range(100)]
                    assert [m["class"] for m in got] == ["IMU"] * 100
                    assert [m["seq"] for m in got] == list(range(100))
            finally:
                held.set()
        assert srv.stats()["inbox_overruns"] == 0 and srv.stats()["dropped_messages"] == 0
    finally:
        srv.stop()
