"""The gravcald socket server: many local clients, none of which can slow anything down.

Design (why it looks like this):

- One server thread runs a ``selectors`` event loop over non-blocking sockets. Nothing in
  it ever blocks on a client: sends that would block leave the data queued and register
  write interest.
- The acquisition side calls :meth:`SocketServer.publish` (thread-safe, non-blocking: it
  appends to a bounded inbox and pokes a wake-up socketpair). If the server thread itself
  falls behind, the inbox drops its oldest blocks and counts them (``inbox_overruns``).
- Every client has a bounded queue of encoded lines (``collections.deque(maxlen=...)``: C
  speed, oldest discarded). What a slow client loses is counted and announced to it with a
  ``DROPPED`` message before its next data. A client with output pending that makes no read
  progress for ``stall_timeout_s`` is disconnected.
- IMU lines are encoded once per block and encoding (plain / raw) and shared by all clients.

The listening socket is bound or inherited from systemd by socket_activation.py.
"""
from __future__ import annotations

import collections
import errno
import logging
import os
import selectors
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from . import protocol
from .output_queue import OutputQueue
from .protocol import ImuBlock, ProtocolError, WatchPolicy
from .socket_activation import bind_unix_socket

log = logging.getLogger("gravcal.server")


@dataclass
class _Client:
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

    def pending(self) -> bool:
        return bool(self.out) or bool(self.queue) or self.dropped_unreported > 0


@dataclass
class ServerConfig:
    """Bounds that protect the daemon (units in the names)."""

    max_clients: int = 64
    queue_messages: int = 4096  # per client, oldest dropped beyond
    stall_timeout_s: float = 10.0  # pending output and no read progress for this long -> disconnect
    max_request_bytes: int = protocol.MAX_REQUEST_BYTES
    max_oversize: int = 3  # oversized requests tolerated before disconnecting
    inbox_blocks: int = 1024  # publish() blocks held for the server thread
    send_chunk_bytes: int = 256 * 1024


class SocketServer:
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
        status_provider: Callable[[], dict[str, Any]] | None = None,
    ):
        if (path is None) == (sock is None):
            raise ValueError("SocketServer needs exactly one of path= or sock=")
        self.config = config or ServerConfig()
        self.status_provider = status_provider
        self._owned_path: str | None = None
        if sock is None:
            sock = bind_unix_socket(path, mode=socket_mode)
            self._owned_path = os.fspath(path)
            self._owned_ino = os.stat(self._owned_path).st_ino
        sock.setblocking(False)
        self.listener = sock
        self.address = sock.getsockname()
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._inbox: collections.deque = collections.deque()
        self._inbox_lock = threading.Lock()
        self._wake_pending = False
        self._clients: dict[int, _Client] = {}
        self._next_id = 1
        self._calib: dict[str, Any] | None = None
        self._last_block: ImuBlock | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.started = time.monotonic()
        # counters (written by the server thread only, except inbox_* under the lock)
        self.published_samples = 0
        self.inbox_overruns = 0  # samples dropped because the server thread fell behind
        self._inbox_lost = 0  # ... not yet reported to the watchers (DROPPED)
        self.clients_total = 0
        self.clients_rejected = 0
        self.clients_stalled = 0
        self.dropped_total = 0

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
        if samples.shape[0] == 0:
            return
        self._put(ImuBlock(samples, acc_ms2, gyro_rads, static))

    def set_calibration(self, message: dict[str, Any]) -> None:
        """Set the current CALIB message (see protocol.calib_message); pushed to watchers."""
        msg = dict(message)
        msg["class"] = "CALIB"
        self._put(("calib", msg))

    def _put(self, item: Any) -> None:
        with self._inbox_lock:
            if len(self._inbox) >= self.config.inbox_blocks:
                old = self._inbox.popleft()
                if isinstance(old, ImuBlock):
                    self.inbox_overruns += old.samples.shape[0]
                    self._inbox_lost += old.samples.shape[0]
                else:  # never lose a calibration change: keep it, drop the next block instead
                    self._inbox.appendleft(old)
                    for i, o in enumerate(self._inbox):
                        if isinstance(o, ImuBlock):
                            self.inbox_overruns += o.samples.shape[0]
                            self._inbox_lost += o.samples.shape[0]
                            del self._inbox[i]
                            break
            self._inbox.append(item)
            wake = not self._wake_pending
            self._wake_pending = True
        if wake:
            self._wake()

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"\0")
        except (BlockingIOError, OSError):
            pass  # already full of wake-ups, or closed

    # -- introspection ---------------------------------------------------------------
    @property
    def backlog(self) -> int:
        """Items published but not yet taken by the server thread (a replay source may wait on it)."""
        return len(self._inbox)

    @property
    def n_clients(self) -> int:
        return len(self._clients)

    def stats(self) -> dict[str, Any]:
        clients = [
            {
                "id": c.id,
                "watching": c.watch.enable,
                "raw": c.watch.raw,
                "rate": c.watch.rate,
                "queued": len(c.queue),
                "sent": c.sent_messages,
                "dropped": c.dropped_total,
                "connected_s": round(time.monotonic() - c.connected, 3),
            }
            for c in list(self._clients.values())
        ]
        return {
            "clients": len(clients),
            "clients_total": self.clients_total,
            "clients_rejected": self.clients_rejected,
            "clients_stalled": self.clients_stalled,
            "published_samples": self.published_samples,
            "inbox_overruns": self.inbox_overruns,
            "dropped_messages": self.dropped_total,
            "per_client": clients,
        }

    # -- event loop ------------------------------------------------------------------
    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                timeout = min(0.25, self.config.stall_timeout_s / 4)
                for key, mask in self._sel.select(timeout):
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
                            self._on_readable(c)
                        if mask & selectors.EVENT_WRITE and c.id in self._clients:
                            self._flush(c)
                self._drain_inbox()
                self._check_stalls()
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
                queue=OutputQueue(self.config.queue_messages),
                connected=now,
                last_progress=now,
            )
            self._next_id += 1
            self.clients_total += 1
            self._clients[c.id] = c
            self._sel.register(conn, selectors.EVENT_READ, c)
            log.debug("client %d connected", c.id)
            self._enqueue(c, [protocol.encode(protocol.version_message())])
            self._flush(c)

    def _close(self, c: _Client, why: str) -> None:
        if self._clients.pop(c.id, None) is None:
            return
        log.log(logging.INFO if why not in ("eof", "server stopping") else logging.DEBUG,
                "client %d disconnected: %s (sent %d, dropped %d)", c.id, why, c.sent_messages, c.dropped_total)
        try:
            self._sel.unregister(c.sock)
        except (KeyError, ValueError, OSError):
            pass
        c.sock.close()

    # -- requests --------------------------------------------------------------------
    def _on_readable(self, c: _Client) -> None:
        try:
            data = c.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._close(c, f"read error: {exc}")
            return
        if not data:
            self._on_eof(c)
            return
        limit = self.config.max_request_bytes
        buf = c.inbuf
        buf += data
        while True:
            nl = buf.find(b"\n")
            if c.discarding:
                if nl < 0:
                    buf.clear()
                    return
                del buf[: nl + 1]
                c.discarding = False
                continue
            if nl < 0:
                if len(buf) > limit:
                    self._oversized(c)
                    if c.id not in self._clients:
                        return
                    buf.clear()
                    c.discarding = True
                return
            line = bytes(buf[:nl])
            del buf[: nl + 1]
            if len(line) > limit:
                self._oversized(c)
                if c.id not in self._clients:
                    return
                continue
            self._handle_line(c, line)
            if c.id not in self._clients:
                return

    def _oversized(self, c: _Client) -> None:
        c.oversize_count += 1
        limit = self.config.max_request_bytes
        self._reply(c, protocol.error_message(f"request longer than {limit} bytes; discarded up to the next newline"))
        if c.oversize_count >= self.config.max_oversize:
            self._flush(c)
            self._close(c, f"{c.oversize_count} oversized requests")

    def _on_eof(self, c: _Client) -> None:
        # A client that half-closes after its commands (echo '?WATCH=...' | nc -U) still reads.
        c.read_closed = True
        if c.inbuf and not c.discarding:
            line = bytes(c.inbuf)
            c.inbuf.clear()
            if len(line) <= self.config.max_request_bytes:
                self._handle_line(c, line)
        if c.id not in self._clients:
            return
        if not c.watch.enable:
            c.close_when_flushed = True  # answer what it asked, then hang up
        self._flush(c)

    def _handle_line(self, c: _Client, line: bytes) -> None:
        text = line.decode("utf-8", "replace").strip()
        for req in protocol.parse_requests(line):
            if isinstance(req, ProtocolError):
                c.errors += 1
                self._reply(c, protocol.error_message(str(req), text))
                continue
            try:
                self._execute(c, req)
            except ProtocolError as exc:
                c.errors += 1
                self._reply(c, protocol.error_message(str(exc), text))

    def _execute(self, c: _Client, req: protocol.Request) -> None:
        if req.command == "WATCH":
            was = c.watch.enable
            c.watch = c.watch.updated(req.args)
            if c.watch.enable and not was:
                c.last_bucket = -np.inf
            self._reply(c, c.watch.to_message(), flush=False)
            if c.watch.enable and not was and self._calib is not None:
                self._reply(c, self._calib, flush=False)
            self._flush(c)
        elif req.command == "POLL":
            imu = []
            if self._last_block is not None:
                m = self._last_block.last_message(raw=c.watch.raw)
                if m is not None:
                    imu.append(m)
            self._reply(c, {"class": "POLL", "time": time.time(), "imu": imu})
        elif req.command == "CALIB":
            self._reply(c, self._calib if self._calib is not None else
                        {"class": "CALIB", "revision": 0, "accepted": False, "model": None,
                         "message": "no calibration yet"})
        elif req.command == "STATUS":
            self._reply(c, self._status_message())
        elif req.command == "VERSION":
            self._reply(c, protocol.version_message())

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

    def _reply(self, c: _Client, message: dict[str, Any], *, flush: bool = True) -> None:
        self._enqueue(c, [protocol.encode(message)])
        if flush:
            self._flush(c)

    # -- output ----------------------------------------------------------------------
    def _enqueue(self, c: _Client, lines: list[bytes], joined: bytes | None = None) -> None:
        lost = c.queue.put(lines, joined)
        if lost > 0:
            c.dropped_total += lost
            c.dropped_unreported += lost
            self.dropped_total += lost

    def _drain_inbox(self) -> None:
        with self._inbox_lock:
            items = list(self._inbox)
            self._inbox.clear()
            self._wake_pending = False
            lost, self._inbox_lost = self._inbox_lost, 0
        watchers = [c for c in self._clients.values() if c.watch.enable]
        if lost:  # samples this thread fell too far behind to take: every watcher missed them, and is told
            for c in watchers:
                c.dropped_total += lost
                c.dropped_unreported += lost
                self.dropped_total += lost
        if not items:
            return
        for k, item in enumerate(items):
            if k:  # hand the previous item to the sockets first: a burst must not overflow queues needlessly
                for c in watchers:
                    if c.id in self._clients and not c.want_write and c.queue:
                        self._flush(c)
            if isinstance(item, ImuBlock):
                self.published_samples += item.samples.shape[0]
                self._last_block = item
                if not watchers:
                    continue
                t = item.samples["t"]
                for c in watchers:
                    if c.watch.rate > 0:
                        mask, c.last_bucket = protocol.decimation_mask(t, c.watch.rate, c.last_bucket)
                        idx = np.flatnonzero(mask)
                        if idx.size != mask.size:
                            self._enqueue(c, item.lines_at(c.watch.raw, idx))
                            continue
                    self._enqueue(c, item.lines(c.watch.raw), item.joined(c.watch.raw))
            else:
                _, msg = item
                self._calib = msg
                line = protocol.encode(msg)
                for c in watchers:
                    self._enqueue(c, [line])
        for c in watchers:
            if c.id in self._clients and not c.want_write:
                self._flush(c)

    def _flush(self, c: _Client) -> None:
        """Send what the socket takes now; the rest waits for EVENT_WRITE."""
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
        want_write = c.pending()
        if want_write == c.want_write and not c.read_closed:
            return
        events = (0 if c.read_closed else selectors.EVENT_READ) | (selectors.EVENT_WRITE if want_write else 0)
        c.want_write = want_write
        try:
            if events:
                self._sel.modify(c.sock, events, c)
            else:
                self._sel.unregister(c.sock)
        except (KeyError, ValueError):
            if events:
                self._sel.register(c.sock, events, c)

    def _check_stalls(self) -> None:
        now = time.monotonic()
        limit = self.config.stall_timeout_s
        for c in list(self._clients.values()):
            if c.pending() and now - c.last_progress > limit:
                self.clients_stalled += 1
                self._close(c, f"stalled: no reads for {now - c.last_progress:.1f} s with output pending")
