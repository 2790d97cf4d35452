"""python-can's slcan bus with a read path that costs one system call per burst, not per byte.

python-can's ``slcanBus._read`` asks the port for one byte per call and assembles each ASCII
line in a Python loop: at 200 Hz x 4 CAN frames that loop is most of the daemon's CPU.
:class:`BufferedSlcanBus` keeps everything else of python-can (open/close commands, bitrate,
frame parsing, ``recv``/``Notifier``/filters) and replaces only ``_read``: it waits on the
port's file descriptor (poll), takes every byte that has arrived in one os.read, and serves the
complete lines from memory. ``recv(timeout=0)`` never blocks.

For a service running for days, socketcan (``slcand`` or a native CAN controller,
``can://socketcan/can0``) is the production path: the kernel assembles frames and python-can
reads whole frames from a socket.
"""
from __future__ import annotations

import os
import re
import select
import termios
import time
from collections import deque

from can.interfaces.slcan import slcanBus
from serial import SerialException

_LINE_END = re.compile(rb"[\r\a]")  # CR ends a line, BELL is an error reply
READ_BYTES = 1 << 16  # more than the kernel's tty buffer holds


class BufferedSlcanBus(slcanBus):
    """``can.interfaces.slcan.slcanBus`` reading its port in bursts (same arguments)."""

    def __init__(self, channel, *args, **kwargs):
        self._lines: deque[bytes] = deque()
        self._partial = bytearray()
        self._fd: int | None = None
        self._poll: select.poll | None = None  # the port's descriptor registered for POLLIN
        self._vmin: tuple[int, int] | None = None  # (VMIN set by wake_at, the port's own) while it differs
        super().__init__(channel, *args, **kwargs)

    def _port_fd(self) -> int | None:
        if self._fd is None:
            try:
                self._fd = self.serialPortOrig.fileno()
            except (AttributeError, OSError, ValueError):  # a URL port without a descriptor
                self._fd = -1
            else:
                self._poll = select.poll()
                self._poll.register(self._fd, select.POLLIN)
        return self._fd if self._fd >= 0 else None

    def _take_bytes(self, wait_s: float | None) -> bytes:
        """What the port holds, waiting at most ``wait_s`` (None: forever) for the first byte: one poll()
        on the registered descriptor and one os.read (pyserial's read costs more than both)."""
        fd = self._port_fd()
        if fd is None:  # a URL port: pyserial's read, which blocks up to the port's own timeout
            port = self.serialPortOrig
            return port.read(max(1, port.in_waiting))
        if self._vmin is not None:  # python-can's replies are short: wake on every byte again
            self._set_vmin(self._vmin[1])
            self._vmin = None
        if not self._poll.poll(None if wait_s is None else max(0.0, wait_s) * 1e3):
            return b""
        data = os.read(fd, READ_BYTES)
        if not data:  # readable but empty: unplugged (what pyserial raises)
            raise SerialException("device reports readiness to read but returned no data "
                                  "(device disconnected or multiple access on port?)")
        return data

    def _split(self, data: bytes) -> None:
        self._partial += data
        start = 0
        for m in _LINE_END.finditer(self._partial):
            self._lines.append(bytes(self._partial[start:m.end()]))
            start = m.end()
        if start:
            del self._partial[:start]

    def _read(self, timeout: float | None) -> str | None:
        """The next line including its CR (or BELL), or None once ``timeout`` [s] passed. A non-ASCII
        line raises UnicodeDecodeError (a ValueError) after it is consumed, as python-can's reader."""
        end = None if timeout is None else time.monotonic() + timeout
        while not self._lines:
            wait = None if end is None else end - time.monotonic()
            data = self._take_bytes(wait)
            if data:
                self._split(data)
            elif end is not None and time.monotonic() >= end:
                return None
        return self._lines.popleft().decode("ascii")

    # -- the daemon's C step (drivers/can.py fast_entry) ------------------------------------
    def fast_fd(self) -> int | None:
        """The port's descriptor when nothing read from it waits here (no line, partial line or queued reply):
        the next bytes may go to a reader outside python-can; else None."""
        if self._lines or self._partial or self._queue.qsize():
            return None
        fd = self._port_fd()
        if fd is not None and self.serialPortOrig.in_waiting:  # less than wake_at's bytes, there since the
            return None  # last wait: a sample cut short is python-can's (the assembler's partial timeout)
        return fd

    def unread(self, data: bytes) -> None:
        """Bytes read from the port outside python-can and not taken: recv() parses them first, in order."""
        self._split(data)

    def wake_at(self, nbytes: int) -> None:
        """poll() reports the terminal readable once ``nbytes`` have arrived (VMIN with VTIME 0, which the
        kernel's n_tty applies to poll), until python-can's own read next waits on the port."""
        if self._vmin is not None and self._vmin[0] == nbytes:
            return
        own = self._set_vmin(nbytes)
        if own is not None:
            self._vmin = (nbytes, own if self._vmin is None else self._vmin[1])

    def _set_vmin(self, nbytes: int) -> int | None:
        """Set VMIN (VTIME 0): the previous VMIN, or None when the port is not a terminal."""
        try:
            attrs = termios.tcgetattr(self._fd)
            before = attrs[6][termios.VMIN]
            attrs[6][termios.VMIN], attrs[6][termios.VTIME] = nbytes, 0
            termios.tcsetattr(self._fd, termios.TCSANOW, attrs)
        except (termios.error, TypeError):  # not a terminal: the reader wakes on every byte
            return None
        return before if isinstance(before, int) else ord(before)

    def has_buffered_line(self) -> bool:
        """A complete line is already in memory (recv(0) returns it without reading the port)."""
        return bool(self._lines)

    def flush(self) -> None:
        self._lines.clear()
        self._partial.clear()
        super().flush()
