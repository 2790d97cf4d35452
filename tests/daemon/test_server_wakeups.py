"""The server thread sleeps while no client check is due: a watcher taking every line costs it no timer
wake-up, while an idle non-watcher, output left queued or a paused reader still get their checks in time."""
from __future__ import annotations

import socket
import time

import pytest

from gravcal.daemon.client_limits import IDLE_WAKE_S, check_due_in
from gravcal.daemon.server import ServerConfig, SocketServer

from test_server import Raw, publish, wait_until

# measures rates, wake-ups or deadlines in real time: under pytest-xdist (--dist loadgroup) it runs on one
# worker, after the other real-time tests rather than beside them
pytestmark = pytest.mark.xdist_group("realtime")


def _due(srv: SocketServer) -> float:
    """How long the server's loop may sleep now (what its select() is given)."""
    return check_due_in(list(srv._clients.values()), srv.config, time.monotonic(), srv._trim_due)


def _sleeps(tid: int) -> int:
    """Voluntary context switches of thread ``tid`` of this process: the times it slept and was woken."""
    with open(f"/proc/self/task/{tid}/status") as fh:
        for line in fh:
            if line.startswith("voluntary_ctxt_switches:"):
                return int(line.split(":")[1])
    raise AssertionError("no voluntary_ctxt_switches in /proc")


@pytest.fixture
def sockpath(tmp_path):
    return str(tmp_path / "gravcal.sock")


def test_with_only_a_reading_watcher_the_server_thread_sleeps(sockpath):
    srv = SocketServer(sockpath, config=ServerConfig(stall_timeout_s=2.0)).start()
    try:
        w = Raw(sockpath)
        w.line()  # VERSION
        w.send(b'?WATCH={"enable":true};\n')
        w.line()
        publish(srv, 5)
        assert wait_until(lambda: srv.published_samples == 5 and not srv.backlog, 5.0)
        time.sleep(0.3)  # the request's and the publish's wake-ups are over
        assert _due(srv) > 1.0
        tid = srv._thread.native_id
        before = _sleeps(tid)
        time.sleep(1.5)
        # the fixed 0.25 s tick woke it 6 times here; with nothing due, no wake-up at all (1 allowed: a late one)
        assert _sleeps(tid) - before <= 1
        w.close()
    finally:
        srv.stop()


def test_checks_that_are_due_still_wake_it(sockpath):
    srv = SocketServer(sockpath, config=ServerConfig(idle_timeout_s=0.4, stall_timeout_s=2.0)).start()
    try:
        idle = Raw(sockpath)
        idle.line()
        assert _due(srv) <= 0.45  # the idle non-watcher's deadline
        t0 = time.monotonic()
        assert wait_until(lambda: srv.clients_idle == 1, IDLE_WAKE_S)
        assert time.monotonic() - t0 < IDLE_WAKE_S  # closed at its deadline, not at the guard's wake-up
        idle.close()
        # a watcher that does not read: its output stays queued, and the stall check runs every stall_timeout / 4
        slow = Raw(sockpath)
        slow.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        slow.line()
        slow.send(b'?WATCH={"enable":true};\n')
        assert wait_until(lambda: any(c.watch.enable for c in list(srv._clients.values())), 5.0)
        publish(srv, 4000)
        assert wait_until(lambda: any(c.pending() for c in list(srv._clients.values())), 5.0)
        assert _due(srv) == pytest.approx(0.25)
        assert wait_until(lambda: srv.clients_stalled == 1, 10.0)
        slow.close()
    finally:
        srv.stop()


def _daemon_with_a_long_tick(tmp_path, monkeypatch):
    """A gravcald on a silent driver whose main loop ticks every 30 s: any earlier wake-up is a request's."""
    from gravcal.daemon import service
    from gravcal.daemon.config import Config
    from support.silent_driver import SilentDriver

    monkeypatch.setattr(service, "MAIN_PERIOD_S", 30.0)  # a tick would come only after the test's waits
    cfg = Config()
    cfg.socket.path = str(tmp_path / "g.sock")
    cfg.state.directory = str(tmp_path / "state")
    return service.Gravcald(cfg, driver=SilentDriver(), environ={})


def test_the_main_loop_sleeps_its_period_and_wakes_at_once_for_reload_and_stop(tmp_path, monkeypatch):
    import threading

    d = _daemon_with_a_long_tick(tmp_path, monkeypatch)
    d.start()
    loop = threading.Thread(target=d.run)
    try:
        loop.start()
        time.sleep(0.3)
        before = _sleeps(loop.native_id)
        time.sleep(1.0)
        assert _sleeps(loop.native_id) - before == 0  # no timer wake-up inside its period
        d.request_reload()
        assert wait_until(lambda: d.reloads == 1, 10.0)  # at once, not at the 30 s tick
        d.request_stop()
        loop.join(10.0)
        assert not loop.is_alive()
    finally:
        d.request_stop()
        loop.join(10.0)


def test_a_signal_delivered_to_another_thread_wakes_the_main_loop_at_once(tmp_path, monkeypatch):
    """SIGHUP and SIGTERM sent to a worker thread (the kernel may pick any thread for a process signal): the
    handlers run in the main thread only, which must wake at once through the wakeup fd, not at its tick."""
    import signal
    import threading

    d = _daemon_with_a_long_tick(tmp_path, monkeypatch)
    saved = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
    old_fd = signal.set_wakeup_fd(-1)
    signal.set_wakeup_fd(old_fd)
    reloaded_at: list[float] = []
    worker_busy = threading.Event()
    worker_done = threading.Event()

    def worker():  # blocks no signal: a thread the kernel may deliver to
        worker_busy.set()
        worker_done.wait(60.0)

    def sender():
        worker_busy.wait(10.0)
        time.sleep(0.3)
        t = time.monotonic()
        signal.pthread_kill(w.ident, signal.SIGHUP)
        if wait_until(lambda: d.reloads == 1, 10.0):
            reloaded_at.append(time.monotonic() - t)
        signal.pthread_kill(w.ident, signal.SIGTERM)

    w = threading.Thread(target=worker)
    s = threading.Thread(target=sender)
    try:
        d.start()
        d.install_signal_handlers()
        w.start()
        s.start()
        t0 = time.monotonic()
        d.run()  # the main thread, as in gravcald
        ran = time.monotonic() - t0
    finally:
        worker_done.set()
        for t in (w, s):
            if t.ident is not None:
                t.join(10.0)
        for sig, handler in saved.items():
            signal.signal(sig, handler)
        signal.set_wakeup_fd(old_fd)
    assert reloaded_at and reloaded_at[0] < 5.0, reloaded_at  # the 30 s tick would be too late
    assert ran < 15.0
