"""Serial driver (pyserial): the logger's frames over a USB-serial port or a UART.

Opens a device path (``/dev/ttyUSB0``, a pty slave from ``gravcal emulate``) or any pyserial
URL (``loop://``, ``spy://``, ``socket://``) via ``serial.serial_for_url``. Reads in batches
(at least ``batch_frames`` frames per wake-up unless the timeout expires first) to keep CPU
low at 200 Hz, and reopens the port by path after SerialException/OSError, so a USB cable
pulled and plugged back in (or an emulator recreating its pty behind a stable symlink) is
survived.
"""
from __future__ import annotations

import errno
import time

import numpy as np
import serial

from ..core.samples import SAMPLE_DTYPE
from .base import PERMISSION_ERRNOS, Backoff, DriverError, DriverSpec, FramedStreamDriver, permission_hint, take_options
from .codec import FRAME_LEN, TICK_HZ, FrameDecoder

DEFAULT_BAUDRATE = 460800


class SerialDriver(FramedStreamDriver):
    """Frames from a serial port. ``port`` is a device path or a pyserial URL."""

    bus = "serial"
    transient_errors = (serial.SerialException, OSError)

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = DEFAULT_BAUDRATE,
        batch_frames: int = 16,
        exclusive: bool = True,
        tick_hz: float | None = TICK_HZ,
        backoff: Backoff | None = None,
    ):
        super().__init__(tick_hz=tick_hz, backoff=backoff)
        if not port:
            raise DriverError("serial driver needs a port, e.g. serial:///dev/ttyUSB0")
        if batch_frames < 1:
            raise ValueError(f"batch_frames must be >= 1, got {batch_frames}")
        self.port = port
        self.baudrate = int(baudrate)
        self.batch_bytes = FRAME_LEN * int(batch_frames)
        self.exclusive = exclusive
        self.decoder = FrameDecoder()
        self._ser: serial.SerialBase | None = None
        self._timeout: float | None = None

    @classmethod
    def from_spec(cls, spec: DriverSpec) -> "SerialDriver":
        opts = take_options(
            spec,
            {"baudrate": int, "batch_frames": int, "tick_hz": float, "exclusive": _boolean},
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
        self._ser = ser
        self._timeout = 0.1

    def _disconnect(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            ser.close()


    def _read_block(self, deadline: float) -> np.ndarray:
        ser = self._ser
        waiting = ser.in_waiting
        if waiting < self.batch_bytes and deadline > time.monotonic():
            # Let a batch accumulate instead of waking for every frame the port delivers:
            # one wake-up per ~batch_frames samples keeps the driver's CPU low at 200 Hz.
            self._closing.wait(min(deadline - time.monotonic(), self._batch_wait_s()))
            waiting = ser.in_waiting
        if waiting:
            data = ser.read(waiting)
        else:  # nothing yet: block until the first byte or the deadline (one wake-up)
            remaining = max(0.0, deadline - time.monotonic())
            if self._timeout is None or abs(self._timeout - remaining) > 0.002:
                ser.timeout = remaining  # pyserial reconfigures the port; only when it changes
                self._timeout = remaining
            data = ser.read(1)
            if data:
                data += ser.read(ser.in_waiting)
        if not data:
            return np.zeros(0, dtype=SAMPLE_DTYPE)
        return self.decoder.feed(data)

    def _batch_wait_s(self) -> float:
        rate = self._rate.rate_hz
        return min(0.1, max(0.002, self.batch_bytes / FRAME_LEN / rate)) if rate else 0.02


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


def _boolean(value: str) -> bool:
    v = value.strip().lower()
    if v in ("1", "true", "yes", "on"):
        return True
    if v in ("0", "false", "no", "off"):
        return False
    raise ValueError(value)
