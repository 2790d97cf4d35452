"""How the socket server takes requests in: read, split into lines, charged to the client's budget, handed on.

A mixin of server.SocketServer (its counters, ``_close``, ``_reply``, ``_flush`` and ``_execute``), kept apart so
that every bound on what a client may send sits in one place:

- a line longer than ``max_request_bytes`` is discarded up to its newline with one ERROR; ``max_oversize`` of
  them disconnect;
- the budget (client_limits.RequestBudget) is charged one request per line and one more per further command on
  it (``?STATUS;?POLL;`` is two): over it, the rest of the line and whatever is buffered is discarded with one
  ERROR and reading pauses; ``flood_timeout_s`` of flooding without a read within the budget disconnects;
- the answers to everything one read brought are sent together: a line of many commands costs one send, not
  one per command;
- whatever one client's bytes raise on this path (a bug reached by a request) closes that client with one log
  line: no request can end the server thread.
"""
from __future__ import annotations

import logging
import time

from . import protocol
from .client_limits import ClientState as _Client
from .protocol import ProtocolError

log = logging.getLogger("gravcal.server")


class RequestIntake:
    """The request side of SocketServer (see the module's docstring)."""

    def _on_readable_guarded(self, c: _Client) -> None:
        """Whatever one client's bytes raise (a bug anywhere on the request path) closes that client, logged in
        one line, and the server serves the rest: no request can end the server thread."""
        try:
            self._on_readable(c)
        except Exception as exc:
            log.error("client %d: its request raised %s: %s; disconnecting it", c.id, type(exc).__name__, exc)
            if c.id in self._clients:
                c.inbuf.clear()
                self._close(c, f"request failed ({type(exc).__name__})")

    def _on_readable(self, c: _Client) -> None:
        """Read what the client sent, answer its whole lines, and send the answers in one go."""
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
        c.inbuf += data
        self._take_lines(c)
        if c.id in self._clients:
            self._flush(c)

    def _take_lines(self, c: _Client) -> None:
        """Answer every whole line in the client's buffer within its budget (the replies queued together, not
        sent)."""
        out: list[bytes] = []
        try:
            self._answer_lines(c, out)
        finally:
            if out and c.id in self._clients:
                self._enqueue(c, out)

    def _answer_lines(self, c: _Client, out: list[bytes]) -> None:
        limit = self.config.max_request_bytes
        buf = c.inbuf
        now = time.monotonic()  # what one read brought arrived at once
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
                    self._queue(c, out)  # before the ERROR that follows them
                    self._oversized(c)
                    if c.id not in self._clients:
                        return
                    buf.clear()
                    c.discarding = True
                break
            if not c.budget.take(1, now):  # a line costs one request, empty or not ...
                self._queue(c, out)
                self._throttle(c)
                return
            line = bytes(buf[:nl])
            del buf[: nl + 1]
            if len(line) > limit:
                self._queue(c, out)
                self._oversized(c)
                if c.id not in self._clients:
                    return
                continue
            c.last_request = now
            requests = protocol.parse_requests(line)
            if not requests:
                continue
            granted = len(requests) if len(requests) == 1 else 1 + c.budget.take(len(requests) - 1, now)
            self._handle_line(c, line, requests[:granted], out)  # ... and each further command on it one more
            if c.id not in self._clients:
                return
            if granted < len(requests):
                self._queue(c, out)
                self._throttle(c, len(requests) - granted)
                return
        c.flood_since = None  # all it sent was within the budget: a later flood starts its own clock

    def _queue(self, c: _Client, out: list[bytes]) -> None:
        """Queue the replies gathered so far (before one that does not wait for them)."""
        if out:
            self._enqueue(c, out)
            out.clear()

    def _throttle(self, c: _Client, refused_on_line: int = 0) -> None:
        """Over the request budget: discard what is buffered, say so once, stop reading for a while."""
        now = time.monotonic()
        buf = c.inbuf
        refused = refused_on_line + buf.count(b"\n") + (0 if not buf or buf.endswith(b"\n") else 1)
        c.discarding = bool(buf) and not buf.endswith(b"\n")
        buf.clear()
        c.refused += refused
        self.requests_refused += refused
        if c.flood_since is None:
            c.flood_since = now
            log.warning("client %d: more than %g requests/s; refusing and pausing its reads",
                        c.id, self.config.request_rate_hz)
        elif now - c.flood_since > self.config.flood_timeout_s:
            self.clients_flooding += 1
            self._close(c, f"flooding requests for {now - c.flood_since:.0f} s ({c.refused} refused)")
            return
        self._reply(c, protocol.error_message(
            f"too many requests (limit {self.config.request_rate_hz:g}/s): {refused} discarded", None))
        c.paused_until = now + max(c.budget.wait_for_one(now), 0.25)
        self._flush(c)

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

    def _handle_line(self, c: _Client, line: bytes, requests: list | None = None,
                     out: list[bytes] | None = None) -> None:
        """Execute a line's commands in order; their replies go to ``out`` (queued by the caller), or are queued
        here without it."""
        mine = out is None
        out = [] if out is None else out
        for req in protocol.parse_requests(line) if requests is None else requests:
            if isinstance(req, ProtocolError):
                c.errors += 1
                out.append(protocol.encode(protocol.error_message(str(req), _text(line))))
                continue
            try:
                self._execute(c, req, out)
            except ProtocolError as exc:
                c.errors += 1
                out.append(protocol.encode(protocol.error_message(str(exc), _text(line))))
            except Exception as exc:  # the server's fault, not the client's: say so, log it once, carry on
                c.errors += 1
                log.error("client %d: ?%s raised %s: %s", c.id, req.command, type(exc).__name__, exc)
                out.append(protocol.encode(protocol.error_message(f"internal error answering ?{req.command}",
                                                                  _text(line))))
        if mine and out:
            self._enqueue(c, out)


def _text(line: bytes) -> str:
    """A request line as an ERROR quotes it."""
    return line.decode("utf-8", "replace").strip()
