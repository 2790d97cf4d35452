"""Per-client limits of the socket server: a request budget, hang-up detection, memory hand-back.

Kept apart from server.py so that the event loop reads as the protocol, and so that each limit can
be tested on its own.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import logging
import select
import socket
from dataclasses import dataclass, field
from typing import Any, Iterable

import numpy as np

from . import protocol
from ._fastpath import ClientRecord
from .output_queue import OutputQueue
from .protocol import WatchPolicy

log = logging.getLogger("gravcal.server")


# the longest the server's event loop sleeps with no client check due (a guard: every change wakes it)
IDLE_WAKE_S = 5.0


def check_due_in(clients: list["ClientState"], cfg: "ServerConfig", now: float, trim_due: bool) -> float:
    """How long the server's event loop may sleep: until its next client check is due. A client with output
    pending (stall check), paused or half-closed (resume, hang-up check), or freed memory to hand back, is
    looked at every min(0.25 s, stall_timeout / 4) as long as it lasts; an idle non-watcher at its idle
    deadline; with nothing due (watchers taking every line) until a socket or publish() wakes the loop (output
    left queued by either wakes it), at most IDLE_WAKE_S."""
    busy = min(0.25, cfg.stall_timeout_s / 4)
    if trim_due:
        return busy
    due = IDLE_WAKE_S
    for c in clients:
        if c.read_closed or c.paused_until or c.pending():
            return busy
        if not c.watch.enable:
            due = min(due, c.last_request + cfg.idle_timeout_s - now)
    return min(max(due, 0.0) + 0.01, IDLE_WAKE_S)


class ClientLock:
    """A client's lock (reentrant), held by both writers of its socket: the server thread and the acquisition
    thread (fanout.py, and the C step of daemon/fastpath.py, which takes it without the GIL: it is the mutex of
    the client's ClientRecord). Every Python holder may change what decides whether the C step may send (closed,
    out, queue, dropped_unreported, watch), so releasing it recomputes the client's gate (ClientState.regate)
    first: the gate is exact whenever the lock is free."""

    __slots__ = ("_client", "acquire", "release_unchanged")

    def __init__(self, client: "ClientState"):
        self._client = client
        self.acquire = client.record.lock  # (blocking=True, timeout=-1) -> bool, the GIL released while waiting
        # for a holder that changed none of it (the C step after a whole send): no recomputation
        self.release_unchanged = client.record.unlock

    def release(self) -> None:
        try:
            self._client.regate()
        finally:
            self.release_unchanged()

    def __enter__(self) -> "ClientLock":
        self.acquire()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.release()


@dataclass(slots=True)
class ClientState:
    """What the server keeps for one connected client."""

    id: int
    sock: socket.socket
    queue: OutputQueue
    connected: float
    watch: WatchPolicy = field(default_factory=WatchPolicy)
    inbuf: bytearray = field(default_factory=bytearray)
    discarding: bool = False  # inside an oversized request: skip to the next newline
    oversize_count: int = 0
    out: memoryview | None = None
    last_progress: float = 0.0
    last_bucket: float = -np.inf
    dropped_total: int = 0
    dropped_unreported: int = 0
    sent_messages: int = 0
    sent_bytes: int = 0
    read_closed: bool = False
    close_when_flushed: bool = False
    want_write: bool = False
    errors: int = 0
    events: int = 0  # selector interest registered
    budget: RequestBudget | None = None
    last_request: float = 0.0
    paused_until: float = 0.0  # reading paused (request budget exhausted) until this time
    flood_since: float | None = None
    refused: int = 0
    closed: bool = False  # set under ``lock`` before the socket closes: no send after it
    # the acquisition thread sends to this client too (fanout.py, the C step): both writers hold this lock
    lock: ClientLock = field(init=False, repr=False)
    # the C step's view of this client: its gate and the counters it adds (daemon/_clienttable.c ClientRecord)
    record: ClientRecord = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.record = ClientRecord()
        self.lock = ClientLock(self)
        self.regate()

    def pending(self) -> bool:
        return bool(self.out) or self.queue.size > 0 or self.dropped_unreported > 0

    def regate(self) -> None:
        """The C step may send under the current policy only while the client is open and nothing waits to go
        first (run by ``lock``'s release, so after every change made under it)."""
        self.record.policy = None if self.closed or self.pending() else self.watch

    def fold(self) -> None:
        """Add what the C step sent since the last fold to the counters (it keeps them in ``record``: no
        Python object per sample); every reader of sent_messages, sent_bytes or last_progress folds first."""
        with self.lock:
            messages, nbytes, progress = self.record.take()
            if messages or nbytes:
                self.sent_messages += messages
                self.sent_bytes += nbytes
                self.last_progress = max(self.last_progress, progress)

    def progress(self) -> float:
        """When the client last took output (last_progress, the C step's sends folded in)."""
        self.fold()
        return self.last_progress

    def stats(self, now: float) -> dict[str, Any]:
        """This client in STATUS's per_client list."""
        self.fold()
        return {"id": self.id, "watching": self.watch.enable, "raw": self.watch.raw, "rate": self.watch.rate,
                "queued": len(self.queue), "queued_bytes": self.queue.nbytes, "sent": self.sent_messages,
                "dropped": self.dropped_total, "refused_requests": self.refused,
                "connected_s": round(now - self.connected, 3)}


@dataclass
class ServerConfig:
    """Bounds that protect the daemon (units in the names)."""

    max_clients: int = 64
    queue_messages: int = 4096  # per client, oldest dropped beyond
    queue_bytes: int = 8 << 20  # per client, oldest dropped beyond
    stall_timeout_s: float = 10.0  # pending output and no read progress for this long -> disconnect
    idle_timeout_s: float = 60.0  # a non-watcher without a request for this long -> disconnect
    request_rate_hz: float = 50.0  # requests per client and second, on average
    request_burst: int = 100  # ... and at once
    flood_timeout_s: float = 10.0  # over the request budget for this long without a pause -> disconnect
    status_cache_s: float = 0.2  # ?STATUS answers are at most this old
    max_request_bytes: int = protocol.MAX_REQUEST_BYTES
    max_oversize: int = 3  # oversized requests tolerated before disconnecting
    send_chunk_bytes: int = 256 * 1024

    @classmethod
    def from_section(cls, section: Any) -> "ServerConfig":
        """The bounds a configuration's [socket] section sets (its other keys are not the server's)."""
        names = [f for f in cls.__dataclass_fields__ if hasattr(section, f)]
        return cls(**{f: getattr(section, f) for f in names})


class RequestBudget:
    """A token bucket: ``rate`` requests per second on average, ``burst`` at once (a request is one command:
    a line of several is charged for each, request_intake.py).

    ``take(n, now)`` grants up to ``n`` requests and returns how many; what is not granted is
    refused by the caller (one ERROR, reading paused) so that a flooding client costs the
    server a bounded amount of work whatever it sends.
    """

    __slots__ = ("rate", "burst", "tokens", "stamp")

    def __init__(self, rate: float, burst: float, now: float):
        self.rate = float(rate)
        self.burst = float(max(burst, 1.0))
        self.tokens = self.burst
        self.stamp = now

    def _refill(self, now: float) -> None:
        self.tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now

    def take(self, n: int, now: float) -> int:
        self._refill(now)
        granted = min(n, int(self.tokens))
        self.tokens -= granted
        return granted

    def wait_for_one(self, now: float) -> float:
        """Seconds until one request is granted again."""
        self._refill(now)
        return 0.0 if self.tokens >= 1.0 else (1.0 - self.tokens) / self.rate


def hung_up(socks: Iterable[socket.socket]) -> list[socket.socket]:
    """The sockets whose peer has closed completely (POLLHUP).

    A client that half-closes (``echo '?WATCH;' | nc -U``) still reads and gets no POLLHUP; one
    that has gone away does, even while no data flows to reveal it by a failed send.
    """
    poller = select.poll()
    by_fd = {}
    for s in socks:
        fd = s.fileno()
        if fd >= 0:
            by_fd[fd] = s
            poller.register(fd, 0)  # POLLHUP/POLLERR are always reported
    if not by_fd:
        return []
    return [by_fd[fd] for fd, ev in poller.poll(0) if ev & (select.POLLHUP | select.POLLERR | select.POLLNVAL)]


def _malloc_trim():
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):  # not glibc
        return None


_TRIM = _malloc_trim()


def return_memory_to_os() -> None:
    """Give freed heap back to the system after large client queues went away: glibc keeps it
    otherwise, and the daemon's resident size would stay at its peak."""
    if _TRIM is not None:
        _TRIM(0)
