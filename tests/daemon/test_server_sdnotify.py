"""sd_notify over a real datagram socket, WATCHDOG_USEC parsing, and the watchdog policy."""
import os
import socket
import threading
import uuid

import pytest

from gravcal.daemon.sdnotify import Notifier, WatchdogPolicy, watchdog_interval


def receiver(address):
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(address)
    s.settimeout(5)
    return s


def test_messages_reach_a_path_socket(tmp_path):
    path = str(tmp_path / "notify")
    r = receiver(path)
    n = Notifier({"NOTIFY_SOCKET": path})
    assert n.enabled
    assert n.ready("serving /run/gravcal.sock")
    assert r.recv(4096) == b"READY=1\nSTATUS=serving /run/gravcal.sock"
    assert n.watchdog() and r.recv(4096) == b"WATCHDOG=1"
    assert n.status("200 samples/s,\n  3 clients") and r.recv(4096) == b"STATUS=200 samples/s, 3 clients"
    assert n.stopping() and r.recv(4096) == b"STOPPING=1"
    assert n.reloading()
    msg = r.recv(4096).decode().split("\n")
    assert msg[0] == "RELOADING=1" and msg[1].startswith("MONOTONIC_USEC=") and int(msg[1].split("=")[1]) > 0
    assert n.sent == 5
    n.close()
    r.close()


def test_abstract_namespace_socket():
    name = f"gravcal-test-{uuid.uuid4().hex}"
    r = receiver("\0" + name)
    n = Notifier({"NOTIFY_SOCKET": "@" + name})
    assert n.ready()
    assert r.recv(4096) == b"READY=1"
    r.close()


def test_no_notify_socket_is_a_quiet_no_op(tmp_path):
    n = Notifier({})
    assert not n.enabled and n.ready() is False and n.watchdog() is False
    assert Notifier({"NOTIFY_SOCKET": "relative/path"}).enabled is False
    # the socket vanished (systemd gone): no exception, just False
    gone = Notifier({"NOTIFY_SOCKET": str(tmp_path / "nobody")})
    assert gone.ready() is False and gone.ready() is False


@pytest.mark.parametrize(
    "env, expected",
    [
        ({}, None),
        ({"WATCHDOG_USEC": "30000000"}, 30.0),
        ({"WATCHDOG_USEC": "400000", "WATCHDOG_PID": str(os.getpid())}, 0.4),
        ({"WATCHDOG_USEC": "400000", "WATCHDOG_PID": str(os.getpid() + 1)}, None),
        ({"WATCHDOG_USEC": "soon"}, None),
        ({"WATCHDOG_USEC": "0"}, None),
    ],
)
def test_watchdog_interval(env, expected):
    assert watchdog_interval(env) == expected


class Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t


def test_watchdog_feeds_only_when_samples_flowed(tmp_path):
    path = str(tmp_path / "notify")
    r = receiver(path)
    r.settimeout(0.05)
    clock = Clock()
    wd = WatchdogPolicy(Notifier({"NOTIFY_SOCKET": path}), 10.0, clock=clock)
    assert wd.period_s == 5.0
    fed = []
    # 60 s in 1 s ticks: samples flow for the first 30 s, then the bus goes silent
    for second in range(60):
        clock.t += 1.0
        if second < 30:
            wd.samples_arrived(200)
        fed.append(wd.tick())
    feeds_at = [i for i, f in enumerate(fed) if f]
    assert feeds_at == [4, 9, 14, 19, 24, 29]  # every period while data flows, never after
    # a feed is due again from second 34 (5 s after the last one): 34..59 withheld
    assert wd.feeds == 6 and wd.withheld == 26
    got = []
    while True:
        try:
            got.append(r.recv(64))
        except socket.timeout:
            break
    assert got == [b"WATCHDOG=1"] * 6
    # data again: fed at the next tick
    wd.samples_arrived(1)
    clock.t += 1.0
    assert wd.tick()


def test_watchdog_disabled_never_feeds():
    wd = WatchdogPolicy(Notifier({}), None)
    wd.samples_arrived(100)
    assert wd.tick() is False and wd.feeds == 0


def test_a_manager_that_stops_reading_never_blocks_the_sender(tmp_path, caplog):
    path = str(tmp_path / "notify")
    r = receiver(path)  # bound, never read: its queue fills
    n = Notifier({"NOTIFY_SOCKET": path})
    results = []
    sender = threading.Thread(target=lambda: results.extend(n.watchdog() for _ in range(5000)), daemon=True)
    sender.start()  # 5000: more than any datagram queue holds
    sender.join(30)
    blocked = sender.is_alive()
    if blocked:
        r.close()  # the blocked send then fails, and the thread ends
    assert not blocked, "a send blocked on the full queue"
    assert results[0] and not results[-1]
    assert n.sent == results.index(False) == sum(results)
    assert sum("queue is full" in rec.getMessage() for rec in caplog.records) == 1  # warned once
    assert r.recv(64) == b"WATCHDOG=1"  # what was queued is intact
    n.close()
    r.close()
