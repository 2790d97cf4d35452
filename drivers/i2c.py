"""I2C driver (smbus2): the logger MCU as an I2C target with a sample FIFO.

Register map (8-bit registers; multi-byte reads auto-increment, except FIFO_DATA)::

    0x00 WHO_AM_I    r   0x47 ('G')
    0x01 VERSION     r   1 (FIFO entries are the serial frame of codec.py, FRAME_LEN bytes)
    0x02 STATUS      r   bit0 DATA_READY (FIFO not empty), bit1 FIFO_OVERFLOW (latched:
                         samples were lost because the FIFO was full; cleared by reading STATUS),
                         bit2 RUNNING
    0x03 FIFO_COUNT  r   complete frames in the FIFO (0..FIFO_DEPTH)
    0x04 FIFO_DEPTH  r   FIFO capacity in frames (32 on the logger)
    0x05 ODR         rw  output data rate code: rate = 25 Hz * 2**code (0..5: 25..800 Hz)
    0x06 CTRL        rw  bit0 FIFO_RESET (self-clearing), bit1 ENABLE
    0x07 WATERMARK   rw  the DRDY output is high while FIFO_COUNT >= WATERMARK (1..FIFO_DEPTH; 1 at reset)
    0x10 FIFO_DATA   r   burst read: whole frames, oldest first; bytes past the FIFO's
                         content read as 0x00

When the FIFO is full the newest sample is discarded (the FIFO content stays contiguous), so
an overflow always shows as a sequence gap right after the entries that were in the FIFO.
With the DRDY line wired to a GPIO (``drdy=/sys/class/gpio/gpioN/value``, edge "rising"), the
driver sleeps on the line and wakes when the FIFO reaches the watermark (set from the latency
budget: 1 sample by default, so each sample is read as soon as it is in the FIFO). Without it,
the driver polls every ``poll_s`` (and after each drain waits that long before asking again). Each poll, or each DRDY wake-up, reads STATUS, FIFO_COUNT and the
watermark's frames in one combined I2C_RDWR (register write, read, register write, read, with repeated
starts), so a sample costs one transfer; more frames than that are drained with bursts of up to
``burst_frames`` frames. ``combined=0`` reads STATUS+FIFO_COUNT alone first (an adapter without
multi-message transfers, or a slow bus: an empty combined poll still carries the watermark's frame bytes,
0x00, ~0.7 ms per frame at 400 kHz).

Each transfer is prepared once per connection (:class:`_Transfer`: its messages, read buffers and the
``i2c_rdwr_ioctl_data`` pointing at them) and run with one ``fcntl.ioctl(fd, I2C_RDWR, data)``, which
is what ``SMBus.i2c_rdwr`` does after building those structures on every call; a bus object without a
file descriptor (the test rigs' fake) gets the same messages through its ``i2c_rdwr``.
"""
from __future__ import annotations

import errno
import os
import select
import time
from ctypes import create_string_buffer
from fcntl import ioctl
from typing import Any, Callable

import numpy as np
from smbus2 import SMBus, i2c_msg
from smbus2.smbus2 import I2C_M_RD, I2C_RDWR, i2c_rdwr_ioctl_data

from ..core.samples import FLAG_FIFO_OVERFLOW, FLAG_GAP_BEFORE, SAMPLE_DTYPE
from .base import (PERMISSION_ERRNOS, Backoff, DriverError, DriverSpec, FramedStreamDriver, boolean_option,
                   permission_hint, take_options)
from .codec import FRAME_LEN, TICK_HZ, FrameDecoder

DEFAULT_ADDRESS = 0x42
WHO_AM_I_VALUE = 0x47
PROTOCOL_VERSION = 1

REG_WHO_AM_I = 0x00
REG_VERSION = 0x01
REG_STATUS = 0x02
REG_FIFO_COUNT = 0x03
REG_FIFO_DEPTH = 0x04
REG_ODR = 0x05
REG_CTRL = 0x06
REG_WATERMARK = 0x07
REG_FIFO_DATA = 0x10

STATUS_DATA_READY = 1 << 0
STATUS_FIFO_OVERFLOW = 1 << 1
STATUS_RUNNING = 1 << 2
CTRL_FIFO_RESET = 1 << 0
CTRL_ENABLE = 1 << 1

ODR_BASE_HZ = 25.0
ODR_CODES = {code: ODR_BASE_HZ * 2**code for code in range(6)}  # code -> Hz


def odr_code(rate_hz: float) -> int:
    """The ODR register code for ``rate_hz``; ValueError if the logger has no such rate."""
    for code, hz in ODR_CODES.items():
        if abs(hz - rate_hz) < 1e-9:
            return code
    raise ValueError(f"output rate {rate_hz} Hz not supported; choose one of {sorted(ODR_CODES.values())}")


SHORT_SLEEP_S = 0.01  # a polled read's waits up to this long are plain sleeps (close() waits one out)
DRDY_RECHECK_S = 0.1  # with a DRDY line, STATUS is still read this often (a missed edge costs no more)

_NACK_ERRNOS = (errno.ENXIO, errno.EREMOTEIO, errno.EIO, errno.ETIMEDOUT, errno.EAGAIN)


class _Transfer:
    """One combined I2C_RDWR of register reads (a register write, then a read of ``length`` bytes from it, per
    ``(register, length)`` in ``reads``), built once and run many times: ``buffers[i].raw`` holds read i's bytes
    after :meth:`run`. On ``fd`` the ioctl gets the prepared ``i2c_rdwr_ioctl_data`` (no ctypes objects made
    per call); ``fd`` None: ``bus.i2c_rdwr(*msgs)``."""

    __slots__ = ("msgs", "buffers", "_data", "run")

    def __init__(self, bus: Any, fd: int | None, address: int, reads: tuple[tuple[int, int], ...]):
        msgs, self.buffers = [], []
        for register, length in reads:
            buf = create_string_buffer(length)
            msgs += [i2c_msg.write(address, [register]), i2c_msg(addr=address, flags=I2C_M_RD, len=length, buf=buf)]
            self.buffers.append(buf)
        self.msgs = tuple(msgs)
        if fd is None:
            self.run = lambda rdwr=bus.i2c_rdwr, msgs=self.msgs: rdwr(*msgs)
        else:
            self._data = i2c_rdwr_ioctl_data.create(*msgs)  # holds copies of the messages: same buffers
            self.run = lambda fd=fd, arg=self._data: ioctl(fd, I2C_RDWR, arg)


class I2CDriver(FramedStreamDriver):
    """Samples from the logger's FIFO over I2C.

    ``smbus_factory(bus)`` makes the SMBus object (default ``smbus2.SMBus``); the test rigs
    (``rigs.fake_i2c``) substitute a fake device at exactly this boundary.
    """

    bus = "i2c"

    def __init__(
        self,
        bus: int | str,
        address: int = DEFAULT_ADDRESS,
        *,
        rate: float | None = None,
        burst_frames: int = 16,
        poll_s: float | None = None,
        data_ready: Any = None,
        latency_budget_s: float = 0.0,
        reset_fifo: bool = True,
        combined: bool = True,
        smbus_factory: Callable[[Any], Any] = SMBus,
        tick_hz: float | None = TICK_HZ,
        backoff: Backoff | None = None,
    ):
        super().__init__(tick_hz=tick_hz, backoff=backoff)
        if not 0x03 <= int(address) <= 0x77:
            raise DriverError(f"I2C address 0x{int(address):02X} is outside the 7-bit range 0x03..0x77")
        if rate is not None:
            try:
                odr_code(rate)
            except ValueError as exc:
                raise DriverError(str(exc)) from None
        self.i2c_bus = bus
        self.address = int(address)
        self.rate = rate
        self.burst_frames = max(1, int(burst_frames))
        self._transfers: dict[Any, _Transfer] = {}  # per connection: burst frames, or ("combined", frames)
        self.poll_s = poll_s
        self.data_ready = data_ready  # the DRDY line: fileno() and wait(timeout) -> bool
        if not latency_budget_s >= 0:
            raise DriverError(f"latency_budget_s must be >= 0, got {latency_budget_s}")
        self.latency_budget_s = float(latency_budget_s)
        self.reset_fifo = reset_fifo
        self.combined = bool(combined)
        self.smbus_factory = smbus_factory
        self.decoder = FrameDecoder()
        self._smbus = None
        self._fd: int | None = None  # the bus's descriptor (None: a bus object without one)
        self._overflow_pending = False
        self._overflow_after = 0  # frames the FIFO held when it reported the overflow: its gap comes after them
        self._fifo_at_connect = 0
        self._poll = 0.02
        self._next_poll_at = 0.0  # polled: the FIFO is not asked before (a read that may wait)
        self.counters.update(fifo_overflows=0, polls=0, bursts=0)
        self._unread: list[bytes] = []  # bursts read for the daemon's C step and handed back undecoded

    @classmethod
    def from_spec(cls, spec: DriverSpec) -> "I2CDriver":
        opts = take_options(spec, {"rate": float, "burst_frames": int, "poll_s": float, "tick_hz": float,
                                   "latency_budget_s": float, "drdy": str, "combined": boolean_option})
        if "drdy" in opts:
            opts["data_ready"] = SysfsDataReady(opts.pop("drdy"))
        try:
            bus: int | str = int(spec.host)
        except ValueError:
            raise DriverError(f"I2C bus {spec.host!r} is not a number (i2c://1/0x42 means /dev/i2c-1)") from None
        try:
            address = int(spec.path.strip("/") or str(DEFAULT_ADDRESS), 0)
        except ValueError:
            raise DriverError(f"I2C address {spec.path.strip('/')!r} is not a number like 0x42") from None
        return cls(bus, address, **opts)

    @property
    def description(self) -> str:
        bus = self.i2c_bus
        dev = f"/dev/i2c-{bus}" if isinstance(bus, int) else str(bus)
        return f"{dev}@0x{self.address:02X}"

    @property
    def _dev_path(self) -> str:
        return f"/dev/i2c-{self.i2c_bus}" if isinstance(self.i2c_bus, int) else str(self.i2c_bus)

    # -- connection -----------------------------------------------------------------
    def _connect(self, *, first: bool) -> None:
        try:
            sm = self.smbus_factory(self.i2c_bus)
        except FileNotFoundError:
            raise DriverError(
                f"I2C bus {self._dev_path} does not exist (enable the I2C controller and load "
                f"i2c-dev: sudo modprobe i2c-dev)"
            ) from None
        except OSError as exc:
            if exc.errno in PERMISSION_ERRNOS:
                raise DriverError(permission_hint(self._dev_path, "i2c")) from None
            raise DriverError(f"cannot open I2C bus {self._dev_path}: {exc}") from None
        try:
            who = sm.read_byte_data(self.address, REG_WHO_AM_I)
            if who != WHO_AM_I_VALUE:
                raise DriverError(
                    f"device at {self.description} is not a gravcal logger: WHO_AM_I = 0x{who:02X}, "
                    f"expected 0x{WHO_AM_I_VALUE:02X}"
                )
            depth = sm.read_byte_data(self.address, REG_FIFO_DEPTH)
            if self.rate is not None:
                sm.write_byte_data(self.address, REG_ODR, odr_code(self.rate))
            rate = ODR_CODES.get(sm.read_byte_data(self.address, REG_ODR) & 0x07, 200.0)
            self.watermark = max(1, min(depth // 2 or 1, round(self.latency_budget_s * rate)))
            sm.write_byte_data(self.address, REG_WATERMARK, self.watermark)
            ctrl = CTRL_ENABLE | (CTRL_FIFO_RESET if first and self.reset_fifo else 0)
            sm.write_byte_data(self.address, REG_CTRL, ctrl)
            self._fifo_at_connect = sm.read_byte_data(self.address, REG_FIFO_COUNT)
        except OSError as exc:
            sm.close()
            if exc.errno in _NACK_ERRNOS:
                raise DriverError(f"no device answers at address 0x{self.address:02X} on {self._dev_path}") from None
            raise DriverError(f"I2C error talking to {self.description}: {exc}") from None
        except DriverError:
            sm.close()
            raise
        # Without DRDY: poll every half sample period (or the latency budget), never slower than a
        # quarter of the FIFO's fill time, so it never overflows while read() is called.
        fill = depth / rate / 4 if depth else 0.01
        # Retry a NACKing device well within the FIFO's fill time: a logger back from an outage keeps
        # sampling, and a reconnect after a long backoff would find its FIFO overflowed.
        self.backoff.maximum_s = min(self.backoff.maximum_s, max(0.005, fill))
        self.backoff.initial_s = min(self.backoff.initial_s, self.backoff.maximum_s)
        self._poll = self.poll_s if self.poll_s else max(0.001, min(fill, max(self.latency_budget_s, 0.5 / rate)))
        self._smbus = sm
        fd = getattr(sm, "fd", None)
        self._fd = fd if isinstance(fd, int) else None
        self._transfers = {}

    def _held_at_reconnect(self) -> int:
        return self._fifo_at_connect + sum(len(b) for b in self._unread) // FRAME_LEN

    def _disconnect(self) -> None:
        sm, self._smbus = self._smbus, None
        if sm is not None:
            sm.close()


    # -- reading --------------------------------------------------------------------
    def _transfer(self, key: Any, reads: tuple[tuple[int, int], ...]) -> _Transfer:
        got = self._transfers[key] = _Transfer(self._smbus, self._fd, self.address, reads)
        return got

    def _status(self) -> tuple[int, int]:
        t = self._transfers.get("status") or self._transfer("status", ((REG_STATUS, 2),))
        t.run()
        self.counters["polls"] += 1
        status, count = t.buffers[0].raw
        return status, count

    def _burst(self, frames: int) -> bytes:
        t = self._transfers.get(frames) or self._transfer(frames, ((REG_FIFO_DATA, frames * FRAME_LEN),))
        t.run()
        self.counters["bursts"] += 1
        return t.buffers[0].raw

    def _read_block(self, deadline: float) -> np.ndarray:
        bursts, self._unread = self._unread or self._read_fifo(deadline), []
        if not bursts:
            return np.zeros(0, SAMPLE_DTYPE)
        blocks = [self.decoder.feed(b) for b in bursts]
        samples = np.concatenate(blocks) if len(blocks) > 1 else blocks[0]
        if self._overflow_pending and samples.shape[0]:
            self._flag_overflow(samples, sum(len(b) for b in bursts) // FRAME_LEN)
        return samples

    def _flag_overflow(self, samples: np.ndarray, frames: int) -> None:
        """FLAG_FIFO_OVERFLOW on the first gap from ``_overflow_after`` frames on (a full FIFO drops the newest:
        at its first report after a reconnect the gap follows the frames it holds, not the reconnect's gap among
        them). ``frames``: the frames read, of which ``samples`` is what the decoder kept (a frame it dropped
        shifts the gap back)."""
        after = max(0, self._overflow_after - max(0, frames - samples.shape[0]))
        gaps = np.flatnonzero(samples["flags"] & FLAG_GAP_BEFORE)
        gaps = gaps[gaps >= after]
        if gaps.shape[0]:
            samples["flags"][gaps[0]] |= FLAG_FIFO_OVERFLOW
            self._overflow_pending = False
        else:
            self._overflow_after = max(0, self._overflow_after - frames)

    def _status_and_first(self, frames: int) -> tuple[int, int, bytes]:
        """STATUS, FIFO_COUNT and the FIFO's first ``frames`` frames in one combined transaction; the bytes are
        the frames it took: ``frames`` when FIFO_COUNT had them, else the count's and any that came in before
        the data phase (a frame starts with its sync bytes; past the FIFO's content the device reads 0x00)."""
        key = ("combined", frames)
        t = self._transfers.get(key) or self._transfer(key, ((REG_STATUS, 2), (REG_FIFO_DATA, frames * FRAME_LEN)))
        t.run()
        counters = self.counters
        counters["polls"] += 1
        counters["bursts"] += 1
        status, count = t.buffers[0].raw
        data = t.buffers[1].raw
        if count >= frames:
            return status, count, data
        taken = count
        while taken < frames and any(data[taken * FRAME_LEN:(taken + 1) * FRAME_LEN]):
            taken += 1
        return status, count, data[:taken * FRAME_LEN]

    def _sleep(self, seconds: float) -> bool:
        """Wait ``seconds``; True if the driver is closing. A poll interval's wait is a plain sleep (an Event's
        timed wait costs a lock and a condition per call, ~15 us here, twice a sample): close() waits for it."""
        if seconds <= SHORT_SLEEP_S:
            time.sleep(seconds)
            return self._closing.is_set()
        return self._closing.wait(seconds)

    def _read_fifo(self, deadline: float) -> list[bytes]:
        """The FIFO's content as bursts of whole frames, once it holds any ([] if not by ``deadline``)."""
        bursts = []
        if self.data_ready is None:  # polled: asking again right after a drain finds the FIFO empty (but for a frame
            # that came in meanwhile), so a read that may wait sleeps out the poll interval first; one that may not
            # asks at once
            now = time.monotonic()
            wait = self._next_poll_at - now
            if 0 < wait <= deadline - now and self._sleep(wait):
                return []
        while True:
            first = b""
            if self.data_ready is not None:  # sleep until the FIFO reaches the watermark
                high = self.data_ready.wait(max(0.0, min(deadline - time.monotonic(), DRDY_RECHECK_S)))
                combined = high and self.combined
            else:
                combined = self.combined
            if combined:
                status, count, first = self._status_and_first(min(self.watermark, self.burst_frames))
            else:
                status, count = self._status()
            if status & STATUS_FIFO_OVERFLOW:
                self.counters["fifo_overflows"] += 1
                if not self._overflow_pending:  # its gap: after the frames held now if none was read since the
                    # (re)connect, else somewhere among them (frames read since made room): the first gap
                    self._overflow_pending, self._overflow_after = True, count if self._flag_reconnect else 0
            if first:
                bursts.append(first)
                count -= len(first) // FRAME_LEN
                break
            if count:
                break
            remaining = deadline - time.monotonic()
            if remaining <= 0 or self._closing.is_set():
                return []
            if self.data_ready is None and self._sleep(min(self._poll, remaining)):
                return []
        while count > 0:
            n = min(count, self.burst_frames)
            try:
                bursts.append(self._burst(n))
            except self.transient_errors:  # what earlier bursts took out of the FIFO comes first after the reconnect
                self._unread = self._unread + bursts
                raise
            count -= n
        self._next_poll_at = time.monotonic() + self._poll
        return bursts

    # -- the daemon's latency path (daemon/fastpath.py) -----------------------------------
    def fast_ready(self) -> tuple[int, int, float] | None:
        """(raw seq, output seq, last t) when the FIFO's next frames may go to the daemon's C step
        (daemon/_i2cpoll.c), which takes only whole intact frames each continuing the stream by one
        (``raw seq`` the next) and hands anything else back (:meth:`unread`); None: they go through
        :meth:`read` (an outage or a reconnect in hand, a partial frame or samples waiting, a sequence
        question open, a FIFO overflow to flag)."""
        if (not self._connected or self._closing.is_set() or self._pending.shape[0] or self._flag_reconnect
                or self._holding or self._overflow_pending or self.decoder.tail or self._unread):
            return None
        nxt = self.decoder.unwrapper.next_frame()
        return None if nxt is None else (nxt[0], nxt[1], self._last_t)

    def fast_bus(self) -> tuple[int, int, int, int, bool, float, int, float] | None:
        """What the daemon's C step needs to read the FIFO as :meth:`_read_fifo` does: (fd, address, frames read
        with STATUS, burst frames, combined, poll interval [s], the DRDY line's fd or -1, the next poll's
        time.monotonic()); None: the bus has no file descriptor (the test rigs' in-process fake) or the DRDY
        line is not a sysfs GPIO: :meth:`read` reads it."""
        drdy = self.data_ready
        if not self._connected or self._fd is None or (drdy is not None and not isinstance(drdy, SysfsDataReady)):
            return None
        return (self._fd, self.address, min(self.watermark, self.burst_frames), self.burst_frames, self.combined,
                self._poll, -1 if drdy is None else drdy.fileno(), self._next_poll_at)

    def fast_polled(self, polls: int, bursts: int, next_poll_at: float, overflow: bool, err: int) -> None:
        """What the C step's reads did, as :meth:`_read_fifo` counts it: the transfers, the next poll's time, a
        FIFO overflow STATUS reported (its frames were handed back: :meth:`read` flags the gap), the errno of a
        transfer that failed (0: none; the bus is lost and reconnects, the frames read before it come first)."""
        counters = self.counters
        counters["polls"] += polls
        counters["bursts"] += bursts
        self._next_poll_at = next_poll_at
        if overflow:
            counters["fifo_overflows"] += 1
            if not self._overflow_pending:  # no reconnect in hand (fast_ready): the gap is the first one
                self._overflow_pending, self._overflow_after = True, 0
        if err:
            self._lost(OSError(err, os.strerror(err)))

    def unread(self, bursts: list[bytes]) -> None:
        """Bursts the C step did not take: the next :meth:`read` decodes them first, as if just read."""
        self._unread = self._unread + list(bursts)


class SysfsDataReady:
    """The logger's DRDY output on a GPIO, through sysfs (``/sys/class/gpio/gpioN/value`` with its
    ``edge`` set to "rising"): ``wait`` returns at once while the line is high, else at the next
    edge or after ``timeout``."""

    def __init__(self, path: str):
        try:
            self._fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
        except OSError as exc:
            if exc.errno in PERMISSION_ERRNOS:
                raise DriverError(permission_hint(path, "gpio")) from None
            raise DriverError(f"cannot open the DRDY line {path}: {exc.strerror}") from None
        self.path = path
        self._poll = select.poll()
        self._poll.register(self._fd, select.POLLPRI | select.POLLERR)

    def fileno(self) -> int:
        return self._fd

    def wait(self, timeout: float) -> bool:
        if os.pread(self._fd, 1, 0) == b"1":
            return True
        return bool(self._poll.poll(max(0.0, timeout) * 1000.0))

    def close(self) -> None:
        os.close(self._fd)
