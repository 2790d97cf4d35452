"""The socket as a program author meets it from docs/socket-protocol.md: requests a gpsd client sends."""
import json

import pytest

from gravcal.daemon.server import ServerConfig, SocketServer
from test_server import Raw

DEVICE = {"spec": "serial:///dev/ttyUSB0?baudrate=460800", "bus": "serial", "device": "/dev/ttyUSB0",
          "connected": True, "rate_hz": 199.5, "samples": 1234, "reconnects": 2, "crc_errors": 7}


@pytest.fixture
def served(tmp_path):
    path = str(tmp_path / "g.sock")
    srv = SocketServer(path, config=ServerConfig(), status_provider=lambda: {"device": dict(DEVICE)})
    srv.start()
    try:
        yield path
    finally:
        srv.stop()


def test_devices_names_the_device_from_status(served):
    c = Raw(served)
    assert c.line()["class"] == "VERSION"
    c.send(b"?devices;?STATUS;\n")
    devices, status = c.line(), c.line()
    assert devices["class"] == "DEVICES" and status["class"] == "STATUS"
    [entry] = devices["devices"]
    assert entry["class"] == "DEVICE" and entry["path"] == status["device"]["spec"] == DEVICE["spec"]
    for key in ("bus", "device", "connected", "rate_hz", "samples", "reconnects"):
        assert entry[key] == status["device"][key], key
    assert "crc_errors" not in entry
