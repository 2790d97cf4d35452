"""One small driver interface for all buses, and ``open_driver(spec)``.

Like python-can's ``BusABC``: every bus (serial, CAN, I2C) is a :class:`Driver` with the same
four calls; which one you get is chosen by a URL-like spec, pyserial style::

    serial:///dev/ttyUSB0?baudrate=460800      serial:loop://  (pyserial's loopback, in-process)
    can://slcan/dev/ttyACM0?bitrate=1000000    can://socketcan/can0    can://virtual/gravcal0
    i2c://1/0x42?rate=200                      fake-i2c://0x42?scenario=static&seed=1&speed=1

The spec's scheme is looked up in :data:`DRIVER_SCHEMES` (python-can's interface table is the
model): each entry names the module and the class whose ``from_spec`` builds the driver, and
the module is imported on first use, so a scheme served by a test rig (``fake-i2c``) costs a
production install nothing and the real drivers never import the rigs.

``read`` never raises for transient bus trouble (a cable pulled, a bus-off, a NACK): the
driver counts it, reopens the device with exponential backoff inside later ``read`` calls,
and flags the first sample produced after the outage with FLAG_RECONNECT (and FLAG_GAP_BEFORE
from the sequence counter; samples a device FIFO held from before the outage come first,
unflagged). Only ``open`` raises :class:`DriverError`, with a message naming the problem
(missing device, missing group membership, wrong device at the address).
"""
from __future__ import annotations

import errno
import grp
import importlib
import logging
import os
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, Callable
from urllib.parse import parse_qsl

import numpy as np

from ..core.samples import FLAG_GAP_BEFORE, FLAG_RECONNECT, SAMPLE_DTYPE
from ._framekernel import stamp_rows
from .codec import TICK_HZ
from .ordering import InOrder

log = logging.getLogger(__name__)

PERMISSION_ERRNOS = (errno.EACCES, errno.EPERM)


class DriverError(Exception):
    """The device cannot be opened or used; the message says why and what to do."""


def permission_hint(path: str, default_group: str) -> str:
    """'add your user to group X' where X is the device's group (default_group if unknown)."""
    group = default_group
    try:
        gid = os.stat(path).st_gid
        name = grp.getgrgid(gid).gr_name
        if gid != 0:
            group = name
    except (OSError, KeyError):
        pass
    return (
        f"permission denied opening {path}: add your user to group '{group}' "
        f"(sudo usermod -aG {group} $USER, then log in again)"
    )


@dataclass
class Backoff:
    """Exponential reconnect backoff [s]: initial, doubling up to maximum; reset on success."""

    initial_s: float = 0.05
    maximum_s: float = 1.0
    _delay: float = 0.0
    _next_at: float = 0.0

    def reset(self) -> None:
        self._delay = 0.0
        self._next_at = 0.0

    def failed(self, now: float) -> None:
        self._delay = self.initial_s if self._delay == 0 else min(self._delay * 2, self.maximum_s)
        self._next_at = now + self._delay

    def wait_s(self, now: float) -> float:
        return max(0.0, self._next_at - now)


class Driver(ABC):
    """Common interface: ``open()``, ``read(max_samples, timeout)``, ``close()``, ``stats()``.

    Subclasses implement ``_connect`` (raise DriverError or a transient error),
    ``_disconnect``, and ``_read_block(deadline)`` returning decoded SAMPLE_DTYPE samples with
    seq unwrapped and flags set (t may be NaN: the base stamps host time from device ticks).
    """

    bus: str = "?"
    transient_errors: tuple[type[BaseException], ...] = (OSError,)

    def __init__(self, *, tick_hz: float | None = TICK_HZ, backoff: Backoff | None = None):
        self.tick_hz = tick_hz
        self.backoff = backoff or Backoff()
        self._opened = False
        self._connected = False
        self._closing = threading.Event()
        self._pending = np.zeros(0, dtype=SAMPLE_DTYPE)
        self._flag_reconnect = False
        self._held_left = 0
        self._lost_at: float | None = None
        self._rate = _RateEstimate()
        self._last_t = -np.inf  # host time of the newest sample stamped
        # The longest a sample may wait in the driver so later ones go out with it [s]; 0: each
        # sample is returned as soon as it has arrived (set before open(): I2C derives its FIFO
        # watermark from it).
        self.latency_budget_s = 0.0
        self._order = InOrder()  # seq only goes up in what read() returns (ordering.py)
        self.counters: dict[str, Any] = {
            "samples": 0,
            "disconnects": 0,
            "reconnects": 0,
            "reconnect_failures": 0,
            "last_error": "",
        }

    # -- subclass hooks -------------------------------------------------------------
    @property
    @abstractmethod
    def description(self) -> str:
        """Human-readable device name for messages, e.g. '/dev/ttyUSB0'."""

    @abstractmethod
    def _connect(self, *, first: bool) -> None: ...

    @abstractmethod
    def _disconnect(self) -> None: ...

    @abstractmethod
    def _read_block(self, deadline: float) -> np.ndarray: ...

    def _after_reconnect(self) -> None:
        """Reset framing state after a reopen (partial frames are meaningless now)."""

    def _codec_stats(self) -> dict[str, Any]:
        return {}

    def _unwrapper(self):
        return None

    # -- public interface -----------------------------------------------------------
    def open(self) -> "Driver":
        """Open the device; raises DriverError with a clear message if it cannot."""
        if self._opened:
            return self
        self._closing.clear()
        self._connect(first=True)
        self._opened = self._connected = True
        return self

    def read(self, max_samples: int = 256, timeout: float = 0.1) -> np.ndarray:
        """Up to ``max_samples`` samples (SAMPLE_DTYPE), waiting at most ``timeout`` s.

        Returns an empty block when nothing arrives in time. Transient bus errors are counted
        (``stats()``) and handled by reconnecting with backoff; they are never raised.
        """
        if not self._opened:
            raise DriverError(f"{self.bus} driver for {self.description} is not open")
        if max_samples <= 0:
            raise ValueError(f"max_samples must be positive, got {max_samples}")
        if self._pending.shape[0]:
            return self._take(max_samples)
        deadline = time.monotonic() + max(0.0, timeout)
        order = self._order
        while not self._closing.is_set():
            if not self._connected and not self._reconnect(deadline):
                break
            held_due = order.wait_until
            try:
                block = self._read_block(deadline if held_due is None else min(deadline, held_due))
            except self.transient_errors as exc:
                self._lost(exc)
                continue
            if block.shape[0]:
                self._stamp(block, time.monotonic())
                if self._flag_reconnect:
                    self._mark_reconnect(block)
            if block.shape[0] or held_due is not None:
                block = order.settle(block, time.monotonic(), self._hold_s())
            n = block.shape[0]
            if n:
                if n <= max_samples:  # the usual case (a sample per read): handed over whole
                    self.counters["samples"] += n
                    return block
                self._pending = block
                return self._take(max_samples)
            if time.monotonic() >= deadline:
                break
        return np.zeros(0, dtype=SAMPLE_DTYPE)

    def close(self) -> None:
        """Close the device (idempotent); a read blocked in another thread returns soon."""
        self._closing.set()
        if self._connected:
            try:
                self._disconnect()
            except Exception as exc:  # closing a dead device must not raise
                log.debug("closing %s: %s", self.description, exc)
        self._connected = False
        self._opened = False

    def stats(self) -> dict[str, Any]:
        """Counters: samples, frames, crc_errors, gaps, missing, reconnects, ... (bus-specific extras)."""
        out = dict(self.counters)
        out.update(self._codec_stats())
        out["out_of_order"] = self._order.out_of_order
        out["connected"] = self._connected
        out["bus"] = self.bus
        out["device"] = self.description
        return out

    def __enter__(self) -> "Driver":
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.description} {'open' if self._opened else 'closed'}>"

    def fast_consumed(self, n: int, tick: int, tick_period: float | None, last_t: float, t_recv: float) -> None:
        """The daemon's C step (daemon/fastpath.py) took ``n`` samples, each continuing the stream by one, the
        last with device ``tick`` and host time ``last_t``: the state :meth:`read` leaves after them."""
        u = self._unwrapper()
        u.continued(n, tick, tick_period)
        self._count_fast_frames(n)
        self.counters["samples"] += n
        self._last_t = last_t
        self._order.last = u.last + u.offset
        self._rate.update_seq(u.last + u.offset, t_recv)

    def _count_fast_frames(self, n: int) -> None:
        """The bus's frame counters for ``n`` samples the C step took (a driver offering it says how)."""
        raise NotImplementedError

    # -- internals ------------------------------------------------------------------
    def _hold_s(self) -> float:
        """How long a sample that jumped may wait for the next to confirm it: three sample periods."""
        rate = self._rate.rate_hz
        return min(max(3.0 / rate, 0.02), 0.5) if rate else 0.1

    @property
    def _holding(self) -> bool:
        """A sample waits in the ordering filter: the next bytes go through read()."""
        return self._order.held is not None

    def _take(self, max_samples: int) -> np.ndarray:
        out, self._pending = self._pending[:max_samples], self._pending[max_samples:]
        self.counters["samples"] += out.shape[0]
        return out

    def _mark_reconnect(self, block: np.ndarray) -> None:
        """FLAG_RECONNECT on the first sample produced after the outage: after the samples a device
        FIFO still held from before it (``_held_at_reconnect``), at the first sequence gap among them."""
        held = self._held_left
        gaps = np.flatnonzero(block["flags"][: held + 1] & FLAG_GAP_BEFORE)
        if gaps.shape[0]:
            i = int(gaps[0])
        elif block.shape[0] > held:
            i = held
        else:  # all of it held from before the outage
            self._held_left -= block.shape[0]
            return
        block["flags"][i] |= FLAG_RECONNECT
        self._flag_reconnect = False

    def _held_at_reconnect(self) -> int:
        """Samples the device may still hold from before an outage (a FIFO's count at reconnect)."""
        return 0

    def _lost(self, exc: BaseException) -> None:
        self.counters["disconnects"] += 1
        self.counters["last_error"] = f"{type(exc).__name__}: {exc}"
        log.warning("%s %s lost: %s; reconnecting", self.bus, self.description, exc)
        try:
            self._disconnect()
        except Exception as exc2:
            log.debug("closing dead %s: %s", self.description, exc2)
        self._connected = False
        self._lost_at = time.monotonic()
        self.backoff.reset()
        self.backoff.failed(self._lost_at)  # first attempt after the initial delay

    def _reconnect(self, deadline: float) -> bool:
        while not self._closing.is_set():
            now = time.monotonic()
            wait = self.backoff.wait_s(now)
            if wait > 0 and now + wait > deadline:  # not due within this read: wait it out
                self._closing.wait(max(0.0, deadline - now))
                return False
            if wait > 0 and self._closing.wait(wait):
                return False
            try:
                self._connect(first=False)
            except (DriverError, *self.transient_errors) as exc:
                self.counters["reconnect_failures"] += 1
                self.counters["last_error"] = str(exc)
                log.debug("reopening %s failed: %s", self.description, exc)
                self.backoff.failed(time.monotonic())
                if time.monotonic() >= deadline:
                    return False
                continue
            self._connected = True
            self.counters["reconnects"] += 1
            self._flag_reconnect = True
            self._held_left = self._held_at_reconnect()
            self.backoff.reset()
            self._after_reconnect()
            unwrapper = self._unwrapper()
            rate = self._rate.rate_hz
            if unwrapper is not None:  # what the host clock says went by (None: unknown yet)
                known = rate and self._lost_at is not None
                unwrapper.expect_advance((time.monotonic() - self._lost_at) * rate if known else None,
                                         held=self._held_left)
            log.info("%s %s reconnected", self.bus, self.description)
            return True
        return False

    def _stamp(self, block: np.ndarray, t_recv: float) -> None:
        """Host time [s, time.monotonic]: the newest sample at reception, earlier ones by tick,
        never before a sample stamped earlier (reception jitter, a device reset or a wrong tick
        rate must not make ``t`` run backwards). In C (_framekernel.c ``stamp_rows``), the stamps the C step
        writes for its own reads; the numpy form is the test oracle (tests/support/stamp_reference.py)."""
        self._last_t = stamp_rows(block, float(self.tick_hz or 0.0), t_recv, self._last_t)
        self._rate.update(block, t_recv)


class FramedStreamDriver(Driver):
    """A driver whose bytes go through the shared serial frame codec (``self.decoder``, a
    codec.FrameDecoder): the serial port, and the I2C FIFO, which carries the same frames."""

    decoder: Any

    def _after_reconnect(self) -> None:
        self.decoder.discard_partial()

    def _unwrapper(self):
        return self.decoder.unwrapper

    def _codec_stats(self) -> dict[str, Any]:
        return self.decoder.stats()

    def _count_fast_frames(self, n: int) -> None:
        self.decoder.count_frames(n)


class _RateEstimate:
    """Sample rate [Hz] from unwrapped seq vs host time, for resolving long outages (updated every
    UPDATE_S of host time: an outage is at least a reconnect backoff long)."""

    UPDATE_S = 0.25

    def __init__(self) -> None:
        self._first: tuple[int, float] | None = None
        self._next = -np.inf  # host time of the next update
        self.rate_hz: float | None = None

    def update(self, block: np.ndarray, t_recv: float) -> None:
        if t_recv >= self._next:
            self.update_seq(int(block["seq"][-1]), t_recv)

    def update_seq(self, seq: int, t_recv: float) -> None:
        """As :meth:`update`, from the newest sample's seq."""
        if t_recv < self._next:
            return
        if self._first is None:
            self._first = (seq, t_recv)
            self._next = t_recv + 1.0
        else:
            self.rate_hz = (seq - self._first[0]) / (t_recv - self._first[1])
            self._next = t_recv + self.UPDATE_S


# ---------------------------------------------------------------- specs
@dataclass
class DriverSpec:
    """A parsed driver spec: scheme, host-ish part, path, options (strings)."""

    scheme: str
    host: str
    path: str
    options: dict[str, str]


def parse_spec(spec: str) -> DriverSpec:
    if not isinstance(spec, str) or not spec.strip():
        raise DriverError("empty driver spec; expected e.g. serial:///dev/ttyUSB0")
    spec = spec.strip()
    if spec.startswith("/"):
        spec = "serial://" + spec  # a bare device path means a serial port
    scheme, sep, rest = spec.partition(":")
    if not sep:
        raise DriverError(f"driver spec {spec!r} has no scheme; use one of "
                          f"{', '.join(s + ':' for s in sorted(DRIVER_SCHEMES))}")
    scheme = scheme.lower()
    rest, _, query = rest.partition("?")
    try:
        options = dict(parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query)))
    except ValueError:
        raise DriverError(f"driver spec {spec!r}: cannot parse options {query!r}") from None
    if rest.startswith("//"):
        host, _, path = rest[2:].partition("/")
        path = "/" + path if path else ""
    else:
        host, path = "", rest
    return DriverSpec(scheme, host, path, options)


def boolean_option(value: str) -> bool:
    """A yes/no option's text (1/true/yes/on, 0/false/no/off); anything else is not valid (take_options says so)."""
    v = value.strip().lower()
    if v in ("1", "true", "yes", "on"):
        return True
    if v in ("0", "false", "no", "off"):
        return False
    raise ValueError(value)


def take_options(spec: DriverSpec, known: dict[str, Callable[[str], Any]]) -> dict[str, Any]:
    """Convert the spec's options with ``known`` converters; unknown names are an error."""
    out = {}
    for name, value in spec.options.items():
        if name not in known:
            raise DriverError(
                f"unknown option {name!r} for {spec.scheme} driver; known: {', '.join(sorted(known))}"
            )
        try:
            out[name] = known[name](value)
        except ValueError:
            raise DriverError(f"option {name}={value!r} for {spec.scheme} driver is not valid") from None
    return out


DRIVER_SCHEMES: dict[str, tuple[str, str]] = {
    "serial": ("gravcal.drivers.serial", "SerialDriver"),
    "can": ("gravcal.drivers.can", "CanDriver"),
    "i2c": ("gravcal.drivers.i2c", "I2CDriver"),
    "fake-i2c": ("gravcal.drivers.rigs.fake_i2c", "FakeI2CDriver"),
}
"""Scheme -> (module, class with ``from_spec(DriverSpec) -> Driver``); extend with :func:`register_scheme`."""


def register_scheme(scheme: str, module: str, class_name: str) -> None:
    """Serve ``scheme://...`` specs with ``module.class_name.from_spec`` (imported on first use)."""
    scheme = scheme.lower()
    if not scheme or not (scheme[0].isalpha() and all(c.isalnum() or c in "+-." for c in scheme)):
        raise ValueError(f"driver scheme {scheme!r} is not a URL scheme (a letter, then letters, digits, + - .)")
    DRIVER_SCHEMES[scheme] = (module, class_name)


def driver_class(scheme: str) -> type[Driver]:
    """The driver class serving ``scheme``; DriverError listing the known schemes if none does."""
    entry = DRIVER_SCHEMES.get(scheme.lower())
    if entry is None:
        raise DriverError(f"unknown bus {scheme!r}; known schemes: {', '.join(sorted(DRIVER_SCHEMES))}")
    module_name, class_name = entry
    module = importlib.import_module(module_name)
    try:
        return getattr(module, class_name)
    except AttributeError:
        raise DriverError(f"driver scheme {scheme!r}: {module_name} has no {class_name}") from None


def open_driver(spec: str, *, open: bool = True) -> Driver:
    """A driver for ``spec`` (see the module docstring), opened unless ``open=False``."""
    parsed = parse_spec(spec)
    try:
        cls = driver_class(parsed.scheme)
    except DriverError as exc:
        raise DriverError(f"{exc} (driver spec {spec!r})") from None
    driver = cls.from_spec(parsed)
    if open:
        driver.open()
    return driver
