"""What bench/bench_latency.py needs to split gravcald's CPU by thread: ?STATUS names each live
thread's OS id, and the emulated I2C device counts the CPU of its bus transactions (spent in the
driver's thread, which a real device would not cost)."""
import os
import threading
import time

from smbus2 import i2c_msg

from gravcal.daemon.config import Config
from gravcal.daemon.service import Gravcald
from gravcal.drivers.i2c import CTRL_ENABLE, REG_CTRL, REG_FIFO_DATA
from gravcal.drivers.rigs.fake_i2c import FakeI2CDevice, FakeSMBus, ManualClock
from gravcal.drivers.rigs.sources import pattern_blocks
from support.silent_driver import SilentDriver


def test_status_names_the_os_thread_id_of_every_daemon_thread(tmp_path):
    cfg = Config()
    cfg.socket.path = str(tmp_path / "g.sock")
    cfg.state.directory = str(tmp_path / "state")
    d = Gravcald(cfg, driver=SilentDriver(), environ={})
    d.start()
    try:
        threads = d.status()["threads"]
        tasks = {int(t) for t in os.listdir(f"/proc/{os.getpid()}/task")}
    finally:
        d.request_stop()
        d.shutdown()
    for name in ("gravcal-acquisition", "gravcal-processing", "gravcal-server", threading.main_thread().name):
        assert threads[name] in tasks, (name, threads)


def test_fake_i2c_device_counts_the_cpu_of_its_bus_transactions():
    clock = ManualClock()
    dev = FakeI2CDevice(pattern_blocks(seed=1, fs=200, duration=10, block=200), 200, clock=clock, fifo_depth=200)
    bus = FakeSMBus(dev)
    dev.write_registers(REG_CTRL, bytes([CTRL_ENABLE]))
    clock.advance(0.9)  # 180 frames in the FIFO
    t0 = time.thread_time()
    before = dev.bus_cpu_s
    for _ in range(60):
        w, r = i2c_msg.write(dev.address, [REG_FIFO_DATA]), i2c_msg.read(dev.address, 3 * 29)
        bus.i2c_rdwr(w, r)
    spent = time.thread_time() - t0
    counted = dev.bus_cpu_s - before
    assert 0.3 * spent < counted <= spent  # most of the loop is the transactions themselves
