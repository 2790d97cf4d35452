"""A small blocking client for the gravcald socket (see docs/socket-protocol.md).

    with Client("/run/gravcal.sock") as c:
        print(c.calib()["offset"])
        for msg in c.watch(rate=10):
            if msg["class"] == "IMU":
                print(msg["seq"], msg["acc"])          # m/s², calibrated

Replies to ?POLL/?CALIB/?STATUS are matched by class; other messages that arrive in the
meantime (IMU, CALIB pushes while watching) are kept for the watch iterator.
"""
from __future__ import annotations

import collections
import json
import os
import socket
import time
from typing import Any, Iterator

from ..daemon.protocol import PROTOCOL_MAJOR, PROTOCOL_MINOR

DEFAULT_SOCKET = "/run/gravcal.sock"


def default_socket_path() -> str:
    """$GRAVCAL_SOCKET, else /run/gravcal.sock (where gravcald.socket listens)."""
    return os.environ.get("GRAVCAL_SOCKET") or DEFAULT_SOCKET


class ClientError(OSError):
    """Cannot talk to gravcald (connect failed, connection closed, timeout)."""


class ProtocolMismatchError(ClientError):
    """gravcald speaks another major protocol version: connecting again will not help."""


class ServerError(ValueError):
    """gravcald answered a request with an ERROR message."""


class Client:
    """Blocking connection to gravcald. ``timeout`` [s] bounds every wait for a message."""

    def __init__(self, path: str | None = None, *, timeout: float = 5.0):
        self.path = path or default_socket_path()
        self.timeout = timeout
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.settimeout(timeout)
        try:
            self._sock.connect(self.path)
        except FileNotFoundError as exc:
            self._sock.close()
            raise ClientError(f"cannot connect to {self.path}: no such socket (is gravcald running? use --socket PATH)") from exc
        except PermissionError as exc:
            self._sock.close()
            raise ClientError(f"cannot connect to {self.path}: permission denied (the socket's group may connect, "
                              "see docs/daemon.md 'Least privilege')") from exc
        except OSError as exc:
            self._sock.close()
            raise ClientError(f"cannot connect to {self.path}: {exc.strerror or exc}") from exc
        self._buf = bytearray()
        self._pending: collections.deque[dict[str, Any]] = collections.deque()
        self.version = self._expect("VERSION")
        if self.version.get("proto_major") != PROTOCOL_MAJOR:  # a major change breaks what this client expects
            self._sock.close()
            raise ProtocolMismatchError(f"{self.path}: gravcald speaks protocol {self.version.get('proto_major')}."
                              f"{self.version.get('proto_minor')}; this client speaks {PROTOCOL_MAJOR}.{PROTOCOL_MINOR} "
                              "(use the gravcal of the same release as the daemon)")

    # -- plumbing --------------------------------------------------------------------
    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def send(self, command: str) -> None:
        """Send one raw command line, e.g. '?POLL;'."""
        if not command.endswith("\n"):
            command += "\n"
        try:
            self._sock.sendall(command.encode())
        except OSError as exc:
            raise ClientError(f"lost connection to {self.path}: {exc.strerror or exc}") from exc

    def read_message(self, timeout: float | None = None) -> dict[str, Any]:
        """The next message from the server (pending ones first)."""
        if self._pending:
            return self._pending.popleft()
        return self._read_line(self.timeout if timeout is None else timeout)

    def _read_line(self, timeout: float) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while True:
            nl = self._buf.find(b"\n")
            if nl >= 0:
                line = bytes(self._buf[:nl])
                del self._buf[: nl + 1]
                try:
                    msg = json.loads(line)
                except json.JSONDecodeError as exc:
                    raise ClientError(f"server sent a line that is not JSON: {line[:80]!r}") from exc
                return msg
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise ClientError(f"no message from {self.path} within {timeout:g} s")
            self._sock.settimeout(remaining)
            try:
                data = self._sock.recv(65536)
            except socket.timeout:
                raise ClientError(f"no message from {self.path} within {timeout:g} s") from None
            except OSError as exc:
                raise ClientError(f"lost connection to {self.path}: {exc.strerror or exc}") from exc
            if not data:
                raise ClientError(f"{self.path}: server closed the connection")
            self._buf += data

    def _expect(self, cls: str) -> dict[str, Any]:
        """Read until a message of class ``cls``; keep others; raise on ERROR."""
        deadline = time.monotonic() + self.timeout
        while True:
            msg = self._read_line(max(0.0, deadline - time.monotonic()))
            if msg.get("class") == cls:
                return msg
            if msg.get("class") == "ERROR":
                raise ServerError(msg.get("message", "unknown error"))
            self._pending.append(msg)

    def request(self, command: str, reply_class: str) -> dict[str, Any]:
        self.send(command)
        return self._expect(reply_class)

    # -- commands --------------------------------------------------------------------
    def poll(self) -> dict[str, Any]:
        """POLL message: {"class": "POLL", "time": ..., "imu": [latest IMU message] or []}."""
        return self.request("?POLL;", "POLL")

    def calib(self) -> dict[str, Any]:
        """The current CALIB message."""
        return self.request("?CALIB;", "CALIB")

    def status(self) -> dict[str, Any]:
        """The STATUS message (rates, counters, clients)."""
        return self.request("?STATUS;", "STATUS")

    def set_watch(self, *, enable: bool = True, rate: float | None = None, raw: bool = False) -> dict[str, Any]:
        args: dict[str, Any] = {"enable": enable, "raw": raw}
        if rate is not None:
            args["rate"] = rate
        return self.request("?WATCH=" + json.dumps(args, separators=(",", ":")) + ";", "WATCH")

    def watch(self, rate: float | None = None, raw: bool = False, *, timeout: float | None = None) -> Iterator[dict[str, Any]]:
        """Subscribe and yield every message (IMU, CALIB, DROPPED, ...) as it arrives.

        ``rate`` [Hz] caps IMU messages (None/0: every sample). Raises ClientError when
        nothing arrives within ``timeout`` (default: the client's timeout).
        """
        self.set_watch(enable=True, rate=rate, raw=raw)
        while True:
            yield self.read_message(timeout)
