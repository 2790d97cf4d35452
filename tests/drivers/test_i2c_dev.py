"""The fake logger served at /dev/i2c-1 from this process (rigs/i2c_dev.py), read by a child process under
umockdev's preload library through the production path: smbus2's ioctls on the device node, the I2C driver."""
from __future__ import annotations

import errno
import json
import subprocess
import sys

import numpy as np
import pytest

from gravcal.drivers.codec import FRAME_LEN
from gravcal.drivers.rigs.emulator import Faults
from gravcal.drivers.rigs.fake_i2c import FakeI2CDevice, ManualClock
from gravcal.drivers.rigs.i2c_dev import I2CDevServer
from gravcal.drivers.rigs.sources import pattern_blocks
from support.umockdev import require_umockdev



@pytest.fixture(autouse=True)
def _umockdev():
    require_umockdev()

FS = 200.0


def run_child(server: I2CDevServer, code: str) -> dict:
    p = subprocess.run([sys.executable, "-c", code], env=server.env(), capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr[-3000:]
    return json.loads(p.stdout.strip().splitlines()[-1])


READ_ALL = """
import json, time
from gravcal.drivers.i2c import I2CDriver
drv = I2CDriver(1, poll_s=0.002).open()
got, deadline = [], time.monotonic() + 30
while sum(b.shape[0] for b in got) < {n} and time.monotonic() < deadline:
    got.append(drv.read(max_samples=4096, timeout=0.2))
drv.close()
import numpy as np
s = np.concatenate(got)
print(json.dumps({{"seq": s["seq"].tolist(), "t1": s["t1"].tolist(), "gyro": s["gyro"].tolist(), "stats": drv.stats()}}))
"""


def test_the_driver_in_another_process_reads_every_sample_through_the_device_node():
    samples = next(pattern_blocks(seed=3, fs=FS, duration=2.0, block=400))
    device = FakeI2CDevice([samples], FS, speed=2.0, fifo_depth=64)
    with I2CDevServer(device) as server:
        out = run_child(server, READ_ALL.format(n=samples.shape[0]))
    assert out["seq"] == samples["seq"].tolist()
    np.testing.assert_array_equal(np.asarray(out["t1"]), samples["t1"])
    np.testing.assert_array_equal(np.asarray(out["gyro"]), samples["gyro"])
    st = out["stats"]
    assert st["gaps"] == st["crc_errors"] == st["fifo_overflows"] == 0 and st["bursts"] >= 1
    assert device.accesses >= st["polls"] + st["bursts"]  # every transfer reached this process's device


TRANSFERS = """
import errno, json
from smbus2 import SMBus, i2c_msg
out = {}
with SMBus(1) as bus:
    out["who"] = bus.read_byte_data(0x42, 0x00)
    bus.write_byte_data(0x42, 0x07, 5)
    out["watermark"] = bus.read_byte_data(0x42, 0x07)
    out["block"] = bus.read_i2c_block_data(0x42, 0x03, 3)
    msgs = [i2c_msg.write(0x42, [0x02]), i2c_msg.read(0x42, 2), i2c_msg.write(0x42, [0x10]), i2c_msg.read(0x42, {k})]
    bus.i2c_rdwr(*msgs)
    out["combined"] = [list(bytes(msgs[1])), bytes(msgs[3]).hex()]
    print(json.dumps(out), flush=True)
    out = {}
    for name, call in (("absent", lambda: bus.read_byte_data(0x43, 0)),
                       ("too_many", lambda: bus.i2c_rdwr(*[i2c_msg.write(0x42, [0])] * 43)),
                       ("nack", lambda: bus.i2c_rdwr(i2c_msg.write(0x42, [0x10]), i2c_msg.read(0x42, 4)))):
        try:
            if name == "nack":
                input()  # the parent unplugs the device
            call()
            out[name] = 0
        except OSError as exc:
            out[name] = exc.errno
print(json.dumps(out))
"""


def test_register_transfers_combined_reads_and_errors_are_those_of_i2c_dev():
    samples = next(pattern_blocks(seed=4, fs=FS, duration=1.0, block=200))
    clock = ManualClock()
    device = FakeI2CDevice([samples], FS, clock=clock, fifo_depth=16, faults=Faults(disconnects=[(0.1, 5.0)]))
    device.write_registers(0x06, bytes([0x02]))  # ENABLE: the FIFO fills as the clock advances
    clock.advance(3.5 / FS)  # three samples in the FIFO
    k = 4 * FRAME_LEN
    with I2CDevServer(device) as server:
        child = subprocess.Popen([sys.executable, "-c", TRANSFERS.replace("{k}", str(k))], env=server.env(), text=True,
                                 stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        first = child.stdout.readline()
        clock.advance(0.2)  # past the unplug at 0.1 s: the device NACKs
        stdout, stderr = child.communicate("\n", timeout=60)
    assert child.returncode == 0, stderr[-3000:]
    out = {**json.loads(first), **json.loads(stdout.strip().splitlines()[-1])}
    assert out["who"] == 0x47 and out["watermark"] == 5
    assert out["block"] == [3, 16, 3]  # FIFO_COUNT, FIFO_DEPTH, ODR code of 200 Hz (auto-increment)
    status, count = out["combined"][0]
    data = bytes.fromhex(out["combined"][1])
    assert status & 0x01 and count == 3
    assert data[:3 * FRAME_LEN] == samples_wire(samples[:3]) and data[3 * FRAME_LEN:] == bytes(FRAME_LEN)
    assert out["absent"] == errno.ENXIO and out["too_many"] == errno.EINVAL and out["nack"] == errno.EREMOTEIO


def samples_wire(s: np.ndarray) -> bytes:
    from gravcal.drivers.codec import encode_frames

    return encode_frames(s)


def test_a_host_cannot_open_the_node_once_the_server_is_closed():
    device = FakeI2CDevice([next(pattern_blocks(seed=0, fs=FS, duration=0.1, block=20))], FS)
    server = I2CDevServer(device)
    env = server.env()
    server.close()
    p = subprocess.run([sys.executable, "-c", "import os; os.open('/dev/i2c-1', os.O_RDWR)"], env=env,
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 1 and "FileNotFoundError" in p.stderr


def test_a_testbed_path_too_long_for_the_socket_is_refused_by_name(tmp_path):
    device = FakeI2CDevice([next(pattern_blocks(seed=0, fs=FS, duration=0.1, block=20))], FS)
    with pytest.raises(ValueError, match="too long for its ioctl socket"):
        I2CDevServer(device, testbed=str(tmp_path / ("x" * 100)))
    assert list(tmp_path.iterdir()) == []  # nothing made
