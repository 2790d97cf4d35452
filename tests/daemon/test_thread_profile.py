"""What bench/bench_latency.py needs to split gravcald's CPU by thread: ?STATUS names each live
thread's OS id."""
import os
import threading

from gravcal.daemon.config import Config
from gravcal.daemon.service import Gravcald
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
