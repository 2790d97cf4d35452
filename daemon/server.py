"""The gravcald socket server: many local clients, none of which can slow anything down.

Design (why it looks like this):

- One server thread runs a ``selectors`` event loop over non-blocking sockets. Nothing in
  it ever blocks on a client: sends that would block leave the data queued and register
  write interest.
- The acquisition side calls :meth:`SocketServer.publish` (non-blocking): the block's line is
  encoded once and sent from the caller's thread to every watcher with nothing queued
  (fanout.py); the server thread is woken (a socketpair) only for what a socket did not take.
  :meth:`SocketServer.set_calibration` does the same for CALIB changes.
- Every client has a queue of encoded lines bounded in messages and bytes (output_queue.py).
  What a slow client loses is counted and announced to it (``DROPPED``) before its next data. A
  client with output pending that makes no read progress for ``stall_timeout_s`` is disconnected.
- Requests spend a per-client budget (client_limits.RequestBudget), one per command however many a
  line carries (request_intake.py); the excess is discarded with one ERROR and reading paused, so a
  flood costs bounded work; ``flood_timeout_s`` of it disconnects. Whatever one client's request
  raises costs that client, never the server thread. ?STATUS comes from a status cached for
  ``status_cache_s``.
- Non-watchers idle for ``idle_timeout_s`` are disconnected (as gpsd does) and the longest-idle
  makes room in a full table; clients whose peer hung up are closed even while no data flows.
- IMU lines are encoded once per block and encoding (plain / raw) and shared by all clients.
- ``publish`` has one caller thread at a time (the acquisition).

The listening socket is bound or inherited from systemd by socket_activation.py.
"""
from __future__ import annotations

import errno
import logging
import os
import selectors
import socket
import threading
import time
from typing import Any, Callable

import numpy as np

from . import protocol
from ._fastpath import WatcherBox
from .fanout import deliver, deliver_line, fast_snapshot, finish_delivery
from .client_limits import ClientState as _Client
from .client_limits import RequestBudget, ServerConfig, check_due_in, hung_up, return_memory_to_os
from .output_queue import OutputQueue
from .protocol import ImuBlock
from .request_intake import RequestIntake
from .socket_activation import bind_unix_socket

log = logging.getLogger("gravcal.server")

ROOM_IDLE_S = 5.0  # a full table closes the longest-idle non-watcher idle at least this long
TRIM_AFTER_BYTES = 1 << 20  # clients leaving with this much queued in all hand the memory back
_COUNTERS = ("clients_total", "clients_rejected", "clients_stalled", "clients_idle", "clients_hung_up",
             "clients_flooding", "requests_refused", "published_samples", "inbox_overruns")  # in STATUS's server


class SocketServer(RequestIntake):
    """Serves IMU/CALIB/STATUS to local clients from its own thread.

    ``status_provider`` (called in the server thread; must be quick and thread-safe)
    supplies the daemon's counters for ?STATUS.
    """

    def __init__(
        self,
        path: str | None = None,
        *,
        sock: socket.socket | None = None,
        config: ServerConfig | None = None,
        socket_mode: int | None = 0o660,
        socket_group: str = "",
        status_provider: Callable[[], dict[str, Any]] | None = None,
    ):
        if (path is None) == (sock is None):
            raise ValueError("SocketServer needs exactly one of path= or sock=")
        self.config = config or ServerConfig()
        self.status_provider = status_provider
        self._owned_path: str | None = None
        if sock is None:
            sock = bind_unix_socket(path, mode=socket_mode, group=socket_group)
            self._owned_path = os.fspath(path)
            self._owned_ino = os.stat(self._owned_path).st_ino
        sock.setblocking(False)
        self.listener = sock
        self.address = sock.getsockname()
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._wake_lock = threading.Lock()
        self._wake_pending = False  # the server thread has been woken for publish()'s leftovers
        self._calib_lock = threading.Lock()  # a new watcher gets the CALIB that is current
        self._clients: dict[int, _Client] = {}
        self._watchers: tuple[_Client, ...] = ()  # replaced, never mutated: publish() reads it unlocked
        self.fast_box = WatcherBox(())  # the C step's watchers: fast_box[0] = fanout.fast_snapshot(...)
        self._next_id = 1
        self._calib: dict[str, Any] | None = None
        self._calib_line: bytes | None = None  # self._calib encoded, as notify() sent it
        self._last_block: ImuBlock | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.started = time.monotonic()
        # counters (written by the server thread only, except inbox_* under the lock)
        self.published_samples = 0
        self.inbox_overruns = 0  # samples dropped before reaching the clients' queues (none: they go direct)
        self._dropped_direct = 0  # queue overflows counted by the publishing thread
        self.clients_total = 0
        self.clients_rejected = 0
        self.clients_stalled = 0
        self.clients_idle = 0  # closed for idling (timeout or to make room)
        self.clients_hung_up = 0  # closed because the peer had gone
        self.clients_flooding = 0  # closed for flooding requests
        self.requests_refused = 0  # requests over a client's budget, discarded
        self.dropped_total = 0
        self._status_cache: tuple[float, bytes] | None = None
        self._trim_due, self._freed = False, 0  # queued bytes of departed clients since the last trim
        self._next_check = 0.0

    # -- lifecycle -------------------------------------------------------------------
    def start(self) -> "SocketServer":
        self._sel.register(self.listener, selectors.EVENT_READ, "listener")
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._thread = threading.Thread(target=self._run, name="gravcal-server", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the thread, close every client and the listener; unlink the path if we bound it."""
        self._stop.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout)
        for c in list(self._clients.values()):
            self._close(c, "server stopping")
        try:
            self._sel.close()
        except Exception:
            pass
        self.listener.close()
        self._wake_r.close()
        self._wake_w.close()
        if self._owned_path is not None:
            try:
                if os.stat(self._owned_path).st_ino == self._owned_ino:
                    os.unlink(self._owned_path)
            except FileNotFoundError:
                pass
            except OSError as exc:  # e.g. privileges dropped since binding it in a root-owned directory
                log.warning("cannot remove socket %s: %s", self._owned_path, exc.strerror or exc)

    def reconfigure(self, section: Any) -> None:
        """New bounds from a reloaded [socket] section; queues of connected clients keep theirs."""
        self.config = ServerConfig.from_section(section)

    def __enter__(self) -> "SocketServer":
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()

    # -- producer side (any thread, never blocks) -----------------------------------
    def publish(self, samples: np.ndarray, acc_ms2: np.ndarray, gyro_rads: np.ndarray, static: np.ndarray) -> None:
        """Hand a block of calibrated samples to the clients.

        samples: SAMPLE_DTYPE (N,); acc_ms2 (N, 3) [m/s²]; gyro_rads (N,) [rad/s], NaN if
        uncalibrated; static (N,) bool. Returns at once; the arrays must not be modified
        afterwards.
        """
        n = samples.shape[0]
        if n == 0:
            return
        block = self._last_block = ImuBlock(samples, acc_ms2, gyro_rads, static)
        self.published_samples += n
        wake, dropped = deliver(self._watchers, block, time.monotonic())
        if dropped:
            self._dropped_direct += dropped
        if wake:
            self._wake_once()

    def finish_publish(self, block: ImuBlock, snapshot: tuple[tuple[Any, ...], ...], index: int, sent: int) -> None:
        """The rest of ``block``, whose delivery the C step (daemon/fastpath.py) stopped at watcher ``index`` of
        ``snapshot`` (fanout.finish_delivery; that client's lock is held by this thread and released there)."""
        self._last_block = block
        wake, dropped = finish_delivery(block, snapshot, index, sent, time.monotonic())
        self._dropped_direct += dropped
        if wake:
            self._wake_once()

    def count_published(self, n: int, latest: Any) -> None:
        """``n`` samples were delivered by the C step; ``latest`` answers ?POLL (``last_message(raw)``)."""
        self.published_samples += n
        self._last_block = latest

    def set_calibration(self, message: dict[str, Any]) -> None:
        """Set the current CALIB message (see protocol.calib_message) and push it (:meth:`notify`)."""
        self.notify({**message, "class": "CALIB"}, current_calib=True)

    def notify(self, msg: dict[str, Any], current_calib: bool = False) -> None:
        """Push a message to every watcher now, in order with this thread's samples (CALIB: kept for new ones)."""
        line = protocol.encode(msg)
        with self._calib_lock:
            if current_calib:
                self._calib, self._calib_line = msg, line
            wake, dropped = deliver_line(self._watchers, line, time.monotonic())
        self._dropped_direct += dropped
        if wake:
            self._wake_once()

    def _set_watchers(self) -> None:
        """Rebuild the watcher tuples after a change (under the changing client's lock, or as it closes)."""
        self._watchers = tuple(w for w in self._clients.values() if w.watch.enable)
        self.fast_box[0] = fast_snapshot(self._watchers)

    fast_watchers = property(lambda self: self.fast_box[0], doc="the C step's watcher snapshot (fast_box's item)")

    def _wake_once(self) -> None:
        with self._wake_lock:
            if self._wake_pending:
                return
            self._wake_pending = True
        self._wake()

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"\0")
        except (BlockingIOError, OSError):
            pass  # already full of wake-ups, or closed

    # -- introspection ---------------------------------------------------------------
    @property
    def backlog(self) -> int:
        """1 while output that publish() left queued waits for the server thread (a replay source
        may wait on it), else 0."""
        return int(self._wake_pending)

    @property
    def n_clients(self) -> int:
        return len(self._clients)

    def stats(self) -> dict[str, Any]:
        now = time.monotonic()
        clients = [c.stats(now) for c in list(self._clients.values())]
        return {"clients": len(clients), **{name: getattr(self, name) for name in _COUNTERS},
                "dropped_messages": self.dropped_total + self._dropped_direct, "per_client": clients}

    # -- event loop ------------------------------------------------------------------
    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                due = check_due_in(list(self._clients.values()), self.config, time.monotonic(), self._trim_due)
                for key, mask in self._sel.select(due):
                    if key.data == "listener":
                        self._accept()
                    elif key.data == "wake":
                        try:
                            while self._wake_r.recv(4096):
                                pass
                        except (BlockingIOError, OSError):
                            pass
                    else:
                        c: _Client = key.data
                        if c.id not in self._clients:
                            continue
                        if mask & selectors.EVENT_READ:
                            self._on_readable_guarded(c)
                        if mask & selectors.EVENT_WRITE and c.id in self._clients:
                            self._flush(c)
                self._flush_published()
                if time.monotonic() >= self._next_check:  # not per published block: 10 times a second
                    self._next_check = time.monotonic() + 0.1
                    self._check_clients()
        except Exception:  # never die silently: the daemon watches is_alive()
            log.exception("socket server thread crashed")
            raise

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                log.warning("accept failed: %s", exc)
                return
            conn.setblocking(False)
            if len(self._clients) >= self.config.max_clients:
                self._make_room()
            if len(self._clients) >= self.config.max_clients:
                self.clients_rejected += 1
                try:
                    conn.send(protocol.encode(protocol.error_message(f"too many clients (limit {self.config.max_clients})")))
                except OSError:
                    pass
                conn.close()
                continue
            now = time.monotonic()
            c = _Client(
                id=self._next_id,
                sock=conn,
                queue=OutputQueue(self.config.queue_messages, self.config.queue_bytes),
                connected=now,
                last_progress=now,
                budget=RequestBudget(self.config.request_rate_hz, self.config.request_burst, now),
                last_request=now,
            )
            self._next_id += 1
            self.clients_total += 1
            self._clients[c.id] = c
            self._sel.register(conn, selectors.EVENT_READ, c)
            c.events = selectors.EVENT_READ
            log.debug("client %d connected", c.id)
            self._enqueue(c, [protocol.version_line()])
            self._flush(c)

    def _close(self, c: _Client, why: str) -> None:
        if self._clients.pop(c.id, None) is None:
            return
        if c.watch.enable:
            self._set_watchers()
        c.fold()
        log.log(logging.INFO if why not in ("eof", "server stopping") else logging.DEBUG,
                "client %d disconnected: %s (sent %d, dropped %d)", c.id, why, c.sent_messages, c.dropped_total)
        try:
            self._sel.unregister(c.sock)
        except (KeyError, ValueError, OSError):
            pass
        with c.lock:  # a send from publish() is not in progress, and none follows
            c.closed = True
            c.sock.close()
            self._freed += c.queue.nbytes + (len(c.out) if c.out else 0)
            self._trim_due = self._freed >= TRIM_AFTER_BYTES
            c.queue.clear()
            c.out = None

    def _make_room(self) -> None:
        now = time.monotonic()
        idle = [c for c in self._clients.values() if not c.watch.enable and not c.pending()
                and now - c.last_request >= ROOM_IDLE_S]
        if idle:
            oldest = min(idle, key=lambda c: c.last_request)
            self.clients_idle += 1
            self._close(oldest, f"idle for {now - oldest.last_request:.0f} s, room made for a new client")

    # -- requests (read, split into lines and charged to the budget by RequestIntake) ------
    def _execute(self, c: _Client, req: protocol.Request, out: list[bytes]) -> None:
        """Append the replies to one command to ``out`` (queued per line by the intake, sent once per read: a
        line of many commands costs one send); ?WATCH queues ``out`` with its own under the client's lock."""
        if req.command == "WATCH":
            was = c.watch.enable
            watch = c.watch.updated(req.args)
            out.append(protocol.encode(watch.to_message()))
            with self._calib_lock, c.lock:  # the replies are queued before publish() sees the new policy
                c.watch = watch
                if watch.enable and not was:
                    c.last_bucket = -np.inf
                    if self._calib_line is not None:
                        out.append(self._calib_line)
                self._enqueue(c, out)
                self._set_watchers()
            out.clear()
        elif req.command == "POLL":
            imu = []
            if self._last_block is not None:
                m = self._last_block.last_message(raw=c.watch.raw)
                if m is not None:
                    imu.append(m)
            out.append(protocol.encode({"class": "POLL", "time": time.time(), "imu": imu}))
        elif req.command == "CALIB":
            with self._calib_lock:
                line = self._calib_line
            out.append(line if line is not None else protocol.NO_CALIB_LINE)
        elif req.command in ("STATUS", "DEVICES"):  # both from the cached status
            out.append(protocol.status_reply(req.command, self._status_line()))
        elif req.command == "VERSION":
            out.append(protocol.version_line())

    def _status_line(self) -> bytes:
        """The encoded STATUS, rebuilt at most every ``status_cache_s``: however many clients ask,
        the service's counters are read a bounded number of times."""
        now = time.monotonic()
        cached = self._status_cache
        if cached is None or now - cached[0] >= self.config.status_cache_s:
            cached = self._status_cache = (now, protocol.encode(self._status_message()))
        return cached[1]

    def _status_message(self) -> dict[str, Any]:
        msg: dict[str, Any] = {"class": "STATUS", "uptime_s": round(time.monotonic() - self.started, 3)}
        if self.status_provider is not None:
            try:
                msg.update(self.status_provider())
            except Exception as exc:  # a bug there must not kill the server thread
                log.exception("status provider failed")
                msg["status_error"] = str(exc)
        msg["server"] = self.stats()
        msg["class"] = "STATUS"
        return msg

    def _reply(self, c: _Client, message: dict[str, Any]) -> None:
        """Queue one message (sent by the caller's next _flush)."""
        self._enqueue(c, [protocol.encode(message)])

    # -- output ----------------------------------------------------------------------
    def _enqueue(self, c: _Client, lines: list[bytes], joined: bytes | None = None) -> None:
        with c.lock:
            lost = c.queue.put(lines, joined)
            if lost > 0:
                c.dropped_total += lost
                c.dropped_unreported += lost
                self.dropped_total += lost

    def _flush_published(self) -> None:
        """What publish() or set_calibration() could not hand to a socket goes out (or waits for
        EVENT_WRITE)."""
        with self._wake_lock:
            if not self._wake_pending:
                return
            self._wake_pending = False
        for c in self._watchers:
            if c.id in self._clients and not c.want_write and c.pending():
                self._flush(c)

    def _flush(self, c: _Client) -> None:
        """Send what the socket takes now; the rest waits for EVENT_WRITE."""
        with c.lock:  # held across non-blocking sends only
            self._flush_locked(c)

    def _flush_locked(self, c: _Client) -> None:
        now = time.monotonic()
        while True:
            if not c.out:
                chunk, n = c.queue.take(self.config.send_chunk_bytes)
                if c.dropped_unreported:
                    chunk.insert(0, protocol.encode(protocol.dropped_message(c.dropped_unreported, c.dropped_total)))
                    c.dropped_unreported = 0
                    n += 1
                if not chunk:
                    c.out = None
                    c.last_progress = now
                    break
                c.sent_messages += n
                c.out = memoryview(chunk[0] if len(chunk) == 1 else b"".join(chunk))
            try:
                n = c.sock.send(c.out)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:  # EPIPE, ECONNRESET: the client went away
                self._close(c, "eof" if exc.errno in (errno.EPIPE, errno.ECONNRESET) else f"write error: {exc}")
                return
            c.sent_bytes += n
            c.last_progress = now
            c.out = c.out[n:]
            if c.out:
                break  # the socket buffer is full
        if c.close_when_flushed and not c.pending():
            self._close(c, "eof")
            return
        self._update_interest(c)

    def _update_interest(self, c: _Client) -> None:
        with c.lock:  # publish() wakes this thread only while want_write is False
            c.want_write = c.pending()
        reading = not c.read_closed and c.paused_until <= time.monotonic()
        events = (selectors.EVENT_READ if reading else 0) | (selectors.EVENT_WRITE if c.want_write else 0)
        if events == c.events:
            return
        try:
            if not events:
                self._sel.unregister(c.sock)
            elif c.events:
                self._sel.modify(c.sock, events, c)
            else:
                self._sel.register(c.sock, events, c)
        except (KeyError, ValueError, OSError) as exc:
            log.debug("client %d: selector update failed: %s", c.id, exc)
        c.events = events

    def _check_clients(self) -> None:
        """Stalled, idle and hung-up clients leave; paused readers resume; freed memory goes back."""
        now = time.monotonic()
        cfg = self.config
        for c in list(self._clients.values()):
            if c.pending() and now - c.progress() > cfg.stall_timeout_s:
                self.clients_stalled += 1
                self._close(c, f"stalled: no reads for {now - c.last_progress:.1f} s with output pending")
            elif not c.watch.enable and not c.pending() and now - c.last_request > cfg.idle_timeout_s:
                self.clients_idle += 1
                self._close(c, f"idle: no request for {now - c.last_request:.0f} s and not watching")
            elif c.paused_until and c.paused_until <= now:
                c.paused_until = 0.0
                self._update_interest(c)
        for sock in hung_up(c.sock for c in self._clients.values() if c.read_closed or c.paused_until):
            c = next(c for c in self._clients.values() if c.sock is sock)
            self.clients_hung_up += 1
            self._close(c, "hung up")
        if self._trim_due:
            self._trim_due, self._freed = False, 0
            return_memory_to_os()
