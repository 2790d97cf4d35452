"""sd_notify(3) for Type=notify services, and a watchdog that only feeds while data flows.

The protocol is one datagram of newline-separated KEY=VALUE assignments sent to the
AF_UNIX socket named in $NOTIFY_SOCKET (a leading '@' means the Linux abstract namespace).
Without $NOTIFY_SOCKET (not under systemd) every call is a no-op that returns False.

The watchdog rule: WATCHDOG=1 is a claim that the service works, so it is sent
only when samples arrived since the previous feed. A silent bus therefore lets systemd's
WatchdogSec= expire and restart the daemon (which reopens the device).
"""
from __future__ import annotations

import logging
import os
import socket
import threading
import time
from typing import Callable, Mapping

log = logging.getLogger("gravcal.sdnotify")


def _address(value: str) -> str | bytes:
    if value.startswith("@"):
        return b"\0" + value[1:].encode()  # abstract namespace
    return value


class Notifier:
    """Sends sd_notify messages to $NOTIFY_SOCKET (read once, at construction)."""

    def __init__(self, environ: Mapping[str, str] | None = None):
        env = os.environ if environ is None else environ
        addr = env.get("NOTIFY_SOCKET", "")
        self.address = _address(addr) if addr and (addr.startswith("/") or addr.startswith("@")) else None
        if addr and self.address is None:
            log.warning("ignoring NOTIFY_SOCKET=%r: not an absolute path or @abstract name", addr)
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()
        self.sent = 0
        self._warned = False

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def notify(self, *assignments: str) -> bool:
        """Send "KEY=VALUE" lines in one datagram. True if sent."""
        if self.address is None:
            return False
        msg = "\n".join(assignments).encode()
        with self._lock:
            try:
                if self._sock is None:
                    # non-blocking: a manager that stops reading must not stall the caller (the main
                    # thread, which also handles SIGTERM); a message it has no room for is dropped
                    self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC
                                               | socket.SOCK_NONBLOCK)
                self._sock.sendto(msg, self.address)
            except BlockingIOError:
                if not self._warned:
                    log.warning("sd_notify to %r: the service manager's queue is full; message dropped", self.address)
                    self._warned = True
                return False
            except OSError as exc:
                if not self._warned:  # once: a notify failure must not flood the journal
                    log.warning("sd_notify to %r failed: %s", self.address, exc)
                    self._warned = True
                return False
            self.sent += 1
            return True

    def ready(self, status: str | None = None) -> bool:
        return self.notify("READY=1", *([f"STATUS={status}"] if status else []))

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def status(self, text: str) -> bool:
        return self.notify(f"STATUS={' '.join(text.split())}")  # one line

    def stopping(self, status: str | None = None) -> bool:
        return self.notify("STOPPING=1", *([f"STATUS={status}"] if status else []))

    def reloading(self) -> bool:
        # MONOTONIC_USEC lets Type=notify-reload (systemd >= 253) match the reload; older ignore it.
        return self.notify("RELOADING=1", f"MONOTONIC_USEC={time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000}")

    def close(self) -> None:
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None


def watchdog_interval(environ: Mapping[str, str] | None = None) -> float | None:
    """The watchdog timeout [s] from $WATCHDOG_USEC (sd_watchdog_enabled), None when off.

    $WATCHDOG_PID, when set, must be our pid (otherwise the variables were meant for
    another process).
    """
    env = os.environ if environ is None else environ
    usec = env.get("WATCHDOG_USEC")
    if not usec:
        return None
    pid = env.get("WATCHDOG_PID")
    if pid:
        try:
            if int(pid) != os.getpid():
                return None
        except ValueError:
            log.warning("ignoring malformed WATCHDOG_PID=%r", pid)
            return None
    try:
        value = int(usec)
    except ValueError:
        log.warning("ignoring malformed WATCHDOG_USEC=%r", usec)
        return None
    if value <= 0:
        return None
    return value / 1e6


class WatchdogPolicy:
    """Feeds the watchdog every ``interval_s / 2`` -- but only if samples arrived since the
    previous feed. Call ``samples_arrived(n)`` from acquisition and ``tick()`` periodically
    (at least every interval/4)."""

    def __init__(self, notifier: Notifier, interval_s: float | None, *, clock: Callable[[], float] = time.monotonic):
        self.notifier = notifier
        self.interval_s = interval_s
        self.period_s = None if interval_s is None else interval_s / 2.0
        self._clock = clock
        # samples counted by acquisition (its only writer) and that count at the last feed (tick's only):
        # no lock on the per-sample path
        self._arrived = 0
        self._at_feed = 0
        self._last_feed = clock()
        self.feeds = 0
        self.withheld = 0  # ticks at which a feed was due but no samples had arrived

    def samples_arrived(self, n: int) -> None:
        self._arrived += n

    def tick(self) -> bool:
        """Feed if due and data flowed; True when WATCHDOG=1 was sent."""
        if self.period_s is None:
            return False
        now = self._clock()
        if now - self._last_feed < self.period_s:
            return False
        arrived = self._arrived
        if arrived == self._at_feed:
            self.withheld += 1
            return False
        self._at_feed = arrived
        self._last_feed = now
        self.feeds += 1
        self.notifier.watchdog()
        return True
