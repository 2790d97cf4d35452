"""A watcher is told when the bus goes away and when it is back (DEVICE, as gpsd pushes), in stream order:
DEVICE connected false after the last sample before the unplug, DEVICE connected true before the first
sample after it (which carries flags gap + reconnect). Without it a client acting on every sample cannot
tell a lost bus from a hung daemon."""
from __future__ import annotations

import json
import socket
import time

import pytest
from gravcal.core.samples import FLAG_RECONNECT
from support.gravcald_process import GravcaldProcess
from support.umockdev import require_umockdev


@pytest.mark.parametrize("bus", ["serial", "can", "i2c"])
def test_watchers_see_the_unplug_and_the_replug(tmp_path, bus):
    if bus == "i2c":
        require_umockdev()
    d = GravcaldProcess(tmp_path, "--bus", bus, "--speed", "2", "--disconnect-at", "6:6", fs=100.0)
    events, spec = [], None
    try:
        d.wait_serving()
        spec = d.status()["device"]["spec"]
        s = socket.socket(socket.AF_UNIX)
        s.settimeout(30)
        s.connect(d.sock)
        f = s.makefile("rb")
        f.readline()
        s.sendall(b'?WATCH={"enable":true,"raw":true};\n')
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            m = json.loads(f.readline())
            if m["class"] == "DEVICE":
                events.append(("DEVICE", m["connected"], m["path"]))
            elif m["class"] == "IMU" and m["flags"] & FLAG_RECONNECT:
                events.append(("IMU", m["flags"]))
                break
        s.close()
    finally:
        d.stop()
    assert [e[:2] for e in events] == [("DEVICE", False), ("DEVICE", True), ("IMU", 3)], events
    assert events[0][2] == events[1][2] == spec, (events, spec)
