"""Delivery of a published block from the producer's thread straight to the watching clients.

At 200 Hz a thread hand-off per sample costs more CPU than the sample's work, so the acquisition
thread itself sends each block's encoded line to every watcher whose output is empty, with a
non-blocking send(). Only what a socket does not take goes to that client's byte-bounded queue,
and only then is the server thread woken (to register write interest and send the rest).

Each client's ``lock`` orders the two writers of its socket: the server thread holds it only
around non-blocking sends and queue updates, never across request handling or status building,
so acquisition never waits for more than one such send.
"""
from __future__ import annotations

from typing import Any, Iterable

import numpy as np

from .client_limits import ClientState
from .protocol import ImuBlock, decimation_mask


def deliver(watchers: Iterable[ClientState], block: ImuBlock, now: float) -> tuple[bool, int]:
    """Send ``block`` to each watcher: (the server thread has work to do, messages dropped)."""
    wake, dropped = False, 0
    n = block.samples.shape[0]
    for c in watchers:
        with c.lock:
            watch = c.watch
            if c.closed or not watch.enable:
                continue
            lines = None
            if watch.rate > 0:
                mask, c.last_bucket = decimation_mask(block.samples["t"], watch.rate, c.last_bucket)
                if not mask.all():
                    lines = block.lines_at(watch.raw, np.flatnonzero(mask))
                    if not lines:
                        continue
            if lines is not None:
                w, lost = _send(c, b"".join(lines), len(lines), now)
            else:
                w, lost = _send(c, block.joined(watch.raw), n, now)
            wake, dropped = wake or (w and not c.want_write), dropped + lost
    return wake, dropped


def deliver_line(watchers: Iterable[ClientState], line: bytes, now: float) -> tuple[bool, int]:
    """Send one encoded message (a CALIB change) to each watcher, as :func:`deliver`."""
    wake, dropped = False, 0
    for c in watchers:
        with c.lock:
            if c.closed or not c.watch.enable:
                continue
            w, lost = _send(c, line, 1, now)
            wake, dropped = wake or (w and not c.want_write), dropped + lost
    return wake, dropped


def fast_snapshot(watchers: tuple[ClientState, ...]) -> tuple[tuple[Any, ...], ...] | None:
    """The watchers as the latency path's C step sends to them (daemon/_fastcall.c): (client, its record, fd,
    raw, watch policy, lock.acquire, lock.release_unchanged) each, in order (the bound methods: no lookup per
    sample); None while one of them is decimated (the Python path serves it)."""
    if any(w.watch.rate > 0 for w in watchers):
        return None
    return tuple((w, w.record, w.sock.fileno(), w.watch.raw, w.watch, w.lock.acquire, w.lock.release_unchanged)
                 for w in watchers)


def finish_delivery(block: ImuBlock, snapshot: tuple[tuple[Any, ...], ...], index: int, sent: int,
                    now: float) -> tuple[bool, int]:
    """The rest of a delivery the C step stopped at watcher ``index`` of its ``snapshot``, whose lock this
    thread holds (released here): that client took ``sent`` bytes of its line(s) (-1: none tried), as
    :func:`deliver` does after its own send; the watchers after it get the block from :func:`deliver`."""
    c, raw = snapshot[index][0], snapshot[index][3]
    try:
        wake, dropped, rest = False, 0, snapshot[index:]
        if sent >= 0:
            wake, dropped = _sent(c, block.joined(raw), block.samples.shape[0], sent, now)
            wake, rest = wake and not c.want_write, snapshot[index + 1:]
    finally:
        c.lock.release()  # recomputes its gate: what _sent queued goes first
    w, lost = deliver([e[0] for e in rest], block, now)
    return wake or w, dropped + lost


def _send_now(c: ClientState, data: bytes) -> int:
    """Bytes of ``data`` the socket took at once (0: something already waits, which goes first, or
    the socket is full (EAGAIN) or gone: the server thread's next send tells which)."""
    if c.pending():
        return 0
    try:
        return c.sock.send(data)
    except OSError:
        return 0


def _send(c: ClientState, data: bytes, n: int, now: float) -> tuple[bool, int]:
    """(the server thread must send the rest, messages dropped from the queue) for ``data``, ``n`` whole
    messages. Called with ``c.lock`` held."""
    return _sent(c, data, n, _send_now(c, data), now)


def _sent(c: ClientState, data: bytes, n: int, sent: int, now: float) -> tuple[bool, int]:
    """The bookkeeping after ``sent`` bytes of ``data`` went out: the rest is the server thread's."""
    if sent == 0:
        return True, _queue(c, data, n)
    c.sent_messages += n
    c.sent_bytes += sent
    c.last_progress = now
    if sent < len(data):  # the rest of a line must follow before anything else
        c.out = memoryview(data)[sent:]
        return True, 0
    return False, 0


def _queue(c: ClientState, data: bytes, n: int) -> int:
    lost = c.queue.put_joined(data, n)
    if lost:
        c.dropped_total += lost
        c.dropped_unreported += lost
    return lost
