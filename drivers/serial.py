"""Serial driver (pyserial): the logger's frames over a USB-serial port or a UART.

Opens a device path (``/dev/ttyUSB0``, a pty slave from ``gravcal emulate``) or any pyserial
URL (``loop://``, ``spy://``, ``socket://``) via ``serial.serial_for_url``. Wakes on data
(select on the port's file descriptor) and returns everything that has arrived, so each frame
is published as soon as it is decoded. The terminal's VMIN is the number of bytes that complete the
frame in hand, so select() wakes once per frame rather than on its first bytes (a 29-byte frame
takes 0.63 ms at 460800 baud); ``latency_budget_s`` > 0 lets frames that arrive within
that time after the first go out together (fewer wake-ups at high rates). It reopens the port
by path after SerialException/OSError, so a USB cable pulled and plugged back in (or an
emulator recreating its pty behind a stable symlink) is survived.
"""
from __future__ import annotations

import errno
import os
import select
import termios
import time

import numpy as np
import serial

from ..core.samples import SAMPLE_DTYPE
from .base import (PERMISSION_ERRNOS, Backoff, DriverError, DriverSpec, FramedStreamDriver, boolean_option,
                   permission_hint, take_options)
from .codec import FRAME_LEN, TICK_HZ, FrameDecoder

DEFAULT_BAUDRATE = 460800
READ_BYTES = 1 << 16  # more than the kernel's tty buffer holds


class SerialDriver(FramedStreamDriver):
    """Frames from a serial port. ``port`` is a device path or a pyserial URL."""

    bus = "serial"
    transient_errors = (serial.SerialException, OSError)

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = DEFAULT_BAUDRATE,
        latency_budget_s: float = 0.0,
        exclusive: bool = True,
        tick_hz: float | None = TICK_HZ,
        backoff: Backoff | None = None,
    ):
        super().__init__(tick_hz=tick_hz, backoff=backoff)
        if not port:
            raise DriverError("serial driver needs a port, e.g. serial:///dev/ttyUSB0")
        if not latency_budget_s >= 0:
            raise DriverError(f"latency_budget_s must be >= 0, got {latency_budget_s}")
        self.port = port
        self.baudrate = int(baudrate)
        self.latency_budget_s = float(latency_budget_s)
        self.exclusive = exclusive
        self.decoder = FrameDecoder()
        self._ser: serial.SerialBase | None = None
        self._fd: int | None = None
        self._timeout: float | None = None
        self._vmin: int | None = None  # the terminal's VMIN as set (None: not a terminal)
        self._poll: select.poll | None = None  # the port's fd registered for POLLIN
        self._unread = b""  # bytes read by the daemon's C step and handed back undecoded (fast_entry)

    @classmethod
    def from_spec(cls, spec: DriverSpec) -> "SerialDriver":
        opts = take_options(
            spec,
            {"baudrate": int, "latency_budget_s": float, "tick_hz": float, "exclusive": boolean_option},
        )
        # serial:///dev/ttyUSB0 -> /dev/ttyUSB0; serial:loop:// -> pyserial URL loop://
        port = f"{spec.host}{spec.path}" if spec.host else spec.path
        return cls(port, **opts)

    @property
    def description(self) -> str:
        return self.port

    def _connect(self, *, first: bool) -> None:
        is_url = "://" in self.port
        kwargs = {"baudrate": self.baudrate, "timeout": 0.1}
        if not is_url:
            kwargs["exclusive"] = self.exclusive
        try:
            ser = serial.serial_for_url(self.port, **kwargs)
        except serial.SerialException as exc:
            raise _open_error(self.port, exc) from None
        except ValueError as exc:  # bad baudrate or URL
            raise DriverError(f"cannot open serial port {self.port}: {exc}") from None
        try:
            self._fd = ser.fileno()
            ser.timeout = 0  # select() waits for the data; read() then takes what has arrived
        except (AttributeError, OSError, serial.SerialException):  # io.UnsupportedOperation is an OSError
            self._fd = None
        self._ser = ser
        self._poll = None
        if self._fd is not None:  # registered once: a poll() per read costs less than building select()'s sets
            self._poll = select.poll()
            self._poll.register(self._fd, select.POLLIN)
        self._timeout = 0.1
        self._vmin = 0 if self._fd is not None and os.isatty(self._fd) else None  # 0: pyserial's, set at first read

    def _disconnect(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            ser.close()


    # -- the daemon's latency path (daemon/fastpath.py) -----------------------------------
    def fast_entry(self) -> tuple[int, int, int, float] | None:
        """(fd, raw seq, output seq, last t) when the next bytes may go to the daemon's C step
        (daemon/_fastpath.c), which takes only whole intact frames each continuing the stream by one
        (``raw seq`` the next), and hands anything else back undecoded (:meth:`unread`); None: they go
        through :meth:`read` (a pyserial URL, an outage or a reconnect in hand, a partial frame or
        samples waiting, a latency budget, a sequence question open)."""
        if (self._fd is None or not self._connected or self._closing.is_set() or self._pending.shape[0]
                or self._holding or self._flag_reconnect or self.decoder.tail or self._unread or self.latency_budget_s > 0):
            return None
        nxt = self.decoder.unwrapper.next_frame()
        if nxt is None:
            return None
        self._wake_at(FRAME_LEN)
        return self._fd, nxt[0], nxt[1], self._last_t

    def unread(self, data: bytes) -> None:
        """Bytes the C step read but did not take: the next :meth:`read` decodes them first, as if just read."""
        self._unread += data

    def _read_block(self, deadline: float) -> np.ndarray:
        if self._unread:
            data, self._unread = self._unread, b""
            return self.decoder.feed(data)
        fd = self._fd
        if fd is None:  # a pyserial URL without a file descriptor (loop://, socket://)
            return self._read_block_url(self._ser, deadline)
        need = FRAME_LEN - len(self.decoder.tail)
        if need != self._vmin and self._vmin is not None:
            self._wake_at(need)
        if not self._poll.poll(max(0.0, deadline - time.monotonic()) * 1e3):
            return _NOTHING
        data = _read_now(fd)  # everything that has arrived (the port is non-blocking)
        if self.latency_budget_s > 0:  # frames arriving within the budget go out together
            hold = time.monotonic() + self.latency_budget_s
            while (left := hold - time.monotonic()) > 0 and select.select([fd], [], [], left)[0]:
                data += _read_now(fd)
        return self.decoder.feed(data)

    def _wake_at(self, nbytes: int) -> None:
        """select() reports the terminal readable once ``nbytes`` have arrived (VMIN with VTIME
        0; the kernel's n_tty applies it to poll). Set only when it changes: one syscall."""
        if self._vmin is None or self._vmin == nbytes:
            return
        try:
            attrs = termios.tcgetattr(self._fd)
            attrs[6][termios.VMIN], attrs[6][termios.VTIME] = nbytes, 0
            termios.tcsetattr(self._fd, termios.TCSANOW, attrs)
            self._vmin = nbytes
        except termios.error:  # not settable here: wake on every byte, as without it
            self._vmin = None

    def _read_block_url(self, ser, deadline: float) -> np.ndarray:
        remaining = max(0.0, deadline - time.monotonic())
        if self._timeout is None or abs(self._timeout - remaining) > 0.002:
            ser.timeout = remaining  # pyserial reconfigures the port; only when it changes
            self._timeout = remaining
        data = ser.read(max(1, ser.in_waiting))
        if data and ser.in_waiting:
            data += ser.read(ser.in_waiting)
        return self.decoder.feed(data) if data else np.zeros(0, dtype=SAMPLE_DTYPE)


_NOTHING = np.zeros(0, dtype=SAMPLE_DTYPE)


def _read_now(fd: int) -> bytes:
    try:
        data = os.read(fd, READ_BYTES)
    except BlockingIOError:
        return b""
    if not data:  # readable but empty: the device is gone (pyserial says the same)
        raise serial.SerialException("device reports readiness to read but returned no data "
                                     "(device disconnected or multiple access on port?)")
    return data


def _open_error(port: str, exc: serial.SerialException) -> DriverError:
    code = getattr(exc, "errno", None)
    if code in PERMISSION_ERRNOS:
        return DriverError(permission_hint(port, "dialout"))
    if code == errno.ENOENT:
        return DriverError(
            f"serial device {port} does not exist (is the logger plugged in? "
            f"see ls /dev/serial/by-id/)"
        )
    if code in (errno.EBUSY, errno.EAGAIN, errno.EWOULDBLOCK) or "lock" in str(exc).lower():
        return DriverError(f"serial device {port} is in use by another program")
    return DriverError(f"cannot open serial port {port}: {exc}")
