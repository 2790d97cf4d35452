"""Fake I2C logger, substituted at the smbus2 boundary (smbus2 has no kernel I2C here).

:class:`FakeI2CDevice` is the logger MCU: it serves the register map of ``i2c.py``; its FIFO
fills with time (``clock``, ``speed``) from a sample source, overflows when the host reads too
slowly, and injects faults (drops, bit errors in bursts, NACKs while "disconnected").
:class:`FakeSMBus` has the methods of ``smbus2.SMBus`` the driver uses and fills real
``smbus2.i2c_msg`` buffers, so the driver's code path is the production one.
:class:`FakeI2CDriver` is the real I2C driver on such a device, the ``fake-i2c://`` scheme, in one process (tests
with a manual clock); ``i2c_dev`` serves such a device at ``/dev/i2c-N`` to another process.
"""
from __future__ import annotations

import ctypes
import errno
import math
import os
import select
import threading
import time
from typing import Callable, Iterable, Iterator

import numpy as np
from smbus2.smbus2 import I2C_M_RD

from ...core.samples import SAMPLE_DTYPE
from ..base import DriverError, DriverSpec, boolean_option, take_options
from ..codec import FRAME_LEN, encode_frames
from ..i2c import (
    CTRL_ENABLE,
    CTRL_FIFO_RESET,
    DEFAULT_ADDRESS,
    ODR_CODES,
    PROTOCOL_VERSION,
    REG_CTRL,
    REG_FIFO_COUNT,
    REG_FIFO_DATA,
    REG_FIFO_DEPTH,
    REG_ODR,
    REG_STATUS,
    REG_VERSION,
    REG_WATERMARK,
    REG_WHO_AM_I,
    STATUS_DATA_READY,
    STATUS_FIFO_OVERFLOW,
    STATUS_RUNNING,
    WHO_AM_I_VALUE,
    I2CDriver,
    odr_code,
)
from .emulator import CORRUPTED, DROPPED, FIFO_FULL, OFFLINE, SENT, Faults, SentLog
from .sources import PATTERN, scenario_source


class ManualClock:
    """A clock tests advance by hand: deterministic FIFO filling without sleeping."""

    def __init__(self, t: float = 0.0):
        self.t = t

    def __call__(self) -> float:
        return self.t

    def advance(self, seconds: float) -> None:
        self.t += seconds


MIN_SAMPLING_INTERVAL_S = 0.002
I2C_RDWR_IOCTL_MAX_MSGS = 42  # linux/i2c-dev.h
I2C_RDWR_MAX_LEN = 8192  # drivers/i2c/i2c-dev.c: the longest message I2C_RDWR accepts


class DataReadyLine:
    """The logger's DRDY output as the host sees it: a pipe that is readable while the line is high. The device
    writes a byte each time it raises the line (each sample that leaves the FIFO at or above the watermark) and
    drains the pipe when a read takes the FIFO below it, so a sample is never left without a readable line
    whichever thread's call lands last (a byte for a sample already taken costs one empty read, no more)."""

    def __init__(self) -> None:
        self._r, self._w = os.pipe()
        os.set_blocking(self._r, False)
        os.set_blocking(self._w, False)
        self._poll = select.poll()  # registered once, as SysfsDataReady (drivers/i2c.py) waits on a GPIO
        self._poll.register(self._r, select.POLLIN)
        self.high = False

    def fileno(self) -> int:
        return self._r

    def set(self, high: bool) -> None:
        self.high = high
        try:
            if high:
                os.write(self._w, b"1")
            else:
                os.read(self._r, 1 << 16)  # all the raises (one byte each) in one read
        except BlockingIOError:
            pass  # full of raises nobody took (readable already), or nothing to drain

    def wait(self, timeout: float) -> bool:
        return bool(self._poll.poll(max(0.0, timeout) * 1e3))

    def close(self) -> None:
        os.close(self._r)
        os.close(self._w)


class FakeI2CDevice:
    """The logger as an I2C target. Samples are produced at the ODR rate times ``speed``.

    Samples are produced while ENABLE is set: on each bus access, and in real time by a sampling
    thread once ``start_sampling()`` is called (as a real logger fills its FIFO whether or not the
    host asks); ``data_ready`` is the DRDY line, high while the FIFO holds at least WATERMARK frames; the FIFO holds ``fifo_depth`` frames and drops
    the newest when full (STATUS.FIFO_OVERFLOW latches until STATUS is read). Every produced
    sample's fate goes to ``log`` (SentLog): SENT once in the FIFO, FIFO_FULL, DROPPED,
    OFFLINE; CORRUPTED when a burst carrying it was hit by a bit error.
    """

    def __init__(
        self,
        blocks: Iterable[np.ndarray],
        fs: float,
        *,
        address: int = DEFAULT_ADDRESS,
        speed: float = 1.0,
        fifo_depth: int = 32,
        faults: Faults | None = None,
        clock: Callable[[], float] = time.monotonic,
        log: SentLog | None = None,
    ):
        self.address = address
        self._odr = odr_code(fs)
        self.speed = float(speed)
        self.depth = int(fifo_depth)
        if not 1 <= self.depth <= 255:
            raise ValueError(f"FIFO depth must be 1..255 frames, got {fifo_depth}")
        self.faults = faults or Faults()
        self.clock = clock
        self.log = log
        self._blocks: Iterator[np.ndarray] = iter(blocks)
        self._buffered = np.zeros(0, SAMPLE_DTYPE)
        self._buffered_wire = b""  # the frames of _buffered, encoded with its source block
        self._exhausted = False
        self._fifo = bytearray()
        self._fifo_seq: list[int] = []  # sample index of each FIFO entry (for CORRUPTED marks)
        self._overflow = False
        self._enabled = False
        self._pointer = 0
        self._produced = 0
        self._t_enable = 0.0
        self._lock = threading.Lock()
        self.corrupted: list[int] = []  # sample indices hit by a bit error in a burst
        self.accesses = 0
        self.watermark = 1
        self.data_ready = DataReadyLine()
        self._line_deferred = False  # inside the sampling thread's locked section: a raise waits for its end
        self._line_raise = False
        self._sampling: threading.Thread | None = None
        self._stop_sampling = threading.Event()

    # -- real-time sampling ----------------------------------------------------------
    def start_sampling(self) -> None:
        """Fill the FIFO in real time from a thread (and drive DRDY), not only on bus accesses."""
        if self._sampling is None:
            self._stop_sampling.clear()
            self._sampling = threading.Thread(target=self._sample_loop, name="fake-i2c-device", daemon=True)
            self._sampling.start()

    def stop_sampling(self) -> None:
        self._stop_sampling.set()
        if self._sampling is not None:
            self._sampling.join(2.0)
            self._sampling = None

    def _sample_loop(self) -> None:
        while not self._stop_sampling.is_set():
            with self._lock:
                self._line_deferred = True
                try:
                    self._advance()
                finally:
                    self._line_deferred = False
                raise_line, self._line_raise = self._line_raise, False
                due = (self._t_enable + (self._produced + 1) / (self.rate * self.speed) if self._enabled
                       else self.clock() + 0.01)
            # DRDY rises once the FIFO write is done and the device's lock is free, as on the logger: the host
            # it wakes finds the FIFO ready (a raise under the lock would wake it into a wait for that lock)
            if raise_line:
                self.data_ready.set(True)
            # each sample on time, but a time-lapse at most every MIN_SAMPLING_INTERVAL_S (in small batches)
            self._stop_sampling.wait(max(MIN_SAMPLING_INTERVAL_S, due - self.clock()))

    def _update_line(self) -> None:
        high = len(self._fifo_seq) >= self.watermark
        if high and self._line_deferred:  # the sampling thread raises it once its lock is released
            self._line_raise = True
        else:
            self.data_ready.set(high)

    # -- time ------------------------------------------------------------------------
    @property
    def rate(self) -> float:
        return ODR_CODES[self._odr]

    @property
    def stream_time(self) -> float:
        """Seconds of samples the device has produced since ENABLE (stream time)."""
        return self._produced / self.rate

    @property
    def exhausted(self) -> bool:
        return self._exhausted and self._buffered.shape[0] == 0

    def _advance(self) -> None:
        if not self._enabled:
            return
        due = math.floor((self.clock() - self._t_enable) * self.rate * self.speed) - self._produced
        if due > 0:
            self._produce(due)

    def _take(self, n: int) -> tuple[np.ndarray, bytes]:
        """The next ``n`` source samples (fewer when it runs dry) and their frames."""
        parts, wire, have = [self._buffered], [self._buffered_wire], self._buffered.shape[0]
        while have < n and not self._exhausted:
            try:
                b = next(self._blocks)
            except StopIteration:
                self._exhausted = True
                break
            parts.append(b)
            wire.append(encode_frames(b))  # a block at a time: one numpy pass, not one per sample
            have += b.shape[0]
        allb = np.concatenate(parts) if len(parts) > 1 else parts[0]
        allw = b"".join(wire) if len(wire) > 1 else wire[0]
        out, self._buffered = allb[:n], allb[n:]
        k = out.shape[0] * FRAME_LEN
        self._buffered_wire = allw[k:]
        return out, allw[:k]

    def _produce(self, n: int) -> None:
        samples, wire = self._take(n)
        m = samples.shape[0]
        self._produced += n  # time moves on even when the source has run dry
        if m == 0:
            return
        if (self.log is None and not self.faults.drop and not self.faults.disconnects
                and m <= self.depth - len(self._fifo_seq)):  # every sample into the FIFO: the frames as they are
            self._fifo += wire
            self._fifo_seq.extend(range(self._produced - n, self._produced - n + m))
            self._update_line()
            return
        idx = np.arange(self._produced - n, self._produced - n + m)
        status = np.full(m, SENT, np.uint8)
        status[self.faults.offline(idx / self.rate)] = OFFLINE  # NACKing, not sampling
        if self.faults.drop:
            status[(status == SENT) & (self.faults.rng.random(m) < self.faults.drop)] = DROPPED
        ok = np.flatnonzero(status == SENT)
        free = self.depth - len(self._fifo_seq)
        if ok.shape[0] > free:
            status[ok[free:]] = FIFO_FULL
            self._overflow = True
            ok = ok[:free]
        self._fifo += encode_frames(samples[ok])
        self._fifo_seq.extend(idx[ok].tolist())
        self._update_line()
        if self.log is not None:
            self.log.add(samples, status)

    # -- bus side --------------------------------------------------------------------
    def _check_online(self) -> None:
        self.accesses += 1
        if self.faults.disconnects and self.faults.offline(np.array([self.stream_time]))[0]:
            raise OSError(errno.EREMOTEIO, "Remote I/O error (no ACK)")

    def read_registers(self, reg: int, n: int) -> bytes:
        with self._lock:
            self._advance()
            self._check_online()
            if reg == REG_FIFO_DATA:
                return self._read_fifo(n)
            out = bytearray()
            for r in range(reg, reg + n):
                out.append(self._read_reg(r))
            return bytes(out)

    def write_registers(self, reg: int, values: bytes) -> None:
        with self._lock:
            self._advance()
            self._check_online()
            for r, v in zip(range(reg, reg + len(values)), values):
                self._write_reg(r, v)

    def _read_reg(self, reg: int) -> int:
        if reg == REG_WHO_AM_I:
            return WHO_AM_I_VALUE
        if reg == REG_VERSION:
            return PROTOCOL_VERSION
        if reg == REG_STATUS:
            st = (STATUS_DATA_READY if self._fifo_seq else 0) | (STATUS_RUNNING if self._enabled else 0)
            if self._overflow:
                st |= STATUS_FIFO_OVERFLOW
                self._overflow = False  # clear on read
            return st
        if reg == REG_FIFO_COUNT:
            return len(self._fifo_seq)
        if reg == REG_FIFO_DEPTH:
            return self.depth
        if reg == REG_ODR:
            return self._odr
        if reg == REG_CTRL:
            return CTRL_ENABLE if self._enabled else 0
        if reg == REG_WATERMARK:
            return self.watermark
        return 0

    def _write_reg(self, reg: int, value: int) -> None:
        if reg == REG_ODR:
            if value not in ODR_CODES:
                return  # ignored, like the MCU firmware
            self._t_enable = self.clock() - self._produced / (ODR_CODES[value] * self.speed)
            self._odr = value
        elif reg == REG_WATERMARK:
            self.watermark = min(max(1, value), self.depth)
            self._update_line()
        elif reg == REG_CTRL:
            if value & CTRL_FIFO_RESET:
                self._fifo.clear()
                self._fifo_seq.clear()
                self._overflow = False
                self._update_line()
            enable = bool(value & CTRL_ENABLE)
            if enable and not self._enabled:
                self._t_enable = self.clock() - self._produced / (self.rate * self.speed)
            self._enabled = enable

    def _read_fifo(self, n: int) -> bytes:
        k = min(n // FRAME_LEN, len(self._fifo_seq))
        data = bytearray(self._fifo[: k * FRAME_LEN])
        taken = self._fifo_seq[:k]
        del self._fifo[: k * FRAME_LEN]
        del self._fifo_seq[:k]
        self._update_line()
        data += bytes(n - len(data))  # past the content: zeros
        hit = self.faults.flip_bits(data)
        if hit.size:  # (np.unique of nothing would still import numpy.ma, once per read)
            for frame in np.unique(hit // FRAME_LEN).tolist():
                if frame < k:
                    self.corrupted.append(taken[frame])
        return bytes(data)

    def fates(self) -> dict[str, np.ndarray]:
        """The log's arrays with CORRUPTED applied to the samples whose bursts were hit."""
        if self.log is None:
            raise ValueError("device was created without a SentLog")
        out = self.log.arrays()
        if self.corrupted:
            out["status"][np.asarray(self.corrupted)] = CORRUPTED
        return out


class FakeSMBus:
    """The parts of ``smbus2.SMBus`` the I2C driver uses, talking to FakeI2CDevice(s)."""

    def __init__(self, devices: FakeI2CDevice | dict[int, FakeI2CDevice], bus: int | str = 1):
        if isinstance(devices, FakeI2CDevice):
            devices = {devices.address: devices}
        self.devices = devices
        self.bus = bus
        self.closed = False

    def _dev(self, addr: int) -> FakeI2CDevice:
        if self.closed:
            raise OSError(errno.EBADF, "Bad file descriptor (bus closed)")
        dev = self.devices.get(addr)
        if dev is None:
            raise OSError(errno.ENXIO, f"No such device or address 0x{addr:02X}")
        return dev

    def read_byte_data(self, i2c_addr: int, register: int, force=None) -> int:
        return self._dev(i2c_addr).read_registers(register, 1)[0]

    def write_byte_data(self, i2c_addr: int, register: int, value: int, force=None) -> None:
        self._dev(i2c_addr).write_registers(register, bytes([value & 0xFF]))

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int, force=None) -> list[int]:
        return list(self._dev(i2c_addr).read_registers(register, length))

    def i2c_rdwr(self, *i2c_msgs) -> None:
        """Combined transaction: a write sets the register pointer (and writes the rest); a read
        reads from the pointer into the message's ctypes buffer."""
        # i2c-dev's I2C_RDWR refuses, before any transfer, more than I2C_RDWR_IOCTL_MAX_MSGS messages or a message
        # longer than 8192 bytes (EINVAL)
        if len(i2c_msgs) > I2C_RDWR_IOCTL_MAX_MSGS or any(m.len > I2C_RDWR_MAX_LEN for m in i2c_msgs):
            raise OSError(errno.EINVAL, "Invalid argument (I2C_RDWR: too many messages or a message too long)")
        pointer = None
        for msg in i2c_msgs:
            dev = self._dev(msg.addr)
            if msg.flags & I2C_M_RD:
                data = dev.read_registers(pointer if pointer is not None else dev._pointer, msg.len)
                ctypes.memmove(msg.buf, data, msg.len)
            else:
                payload = bytes(msg)
                if not payload:
                    continue
                pointer = payload[0]
                dev._pointer = pointer
                if len(payload) > 1:
                    dev.write_registers(pointer, payload[1:])

    def close(self) -> None:
        self.closed = True

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class FakeI2CDriver(I2CDriver):
    """The production I2C driver reading ``device`` through a :class:`FakeSMBus`.

    As a spec, ``fake-i2c://0x42?scenario=NAME&seed=N&speed=X&fs=HZ&duration=S&fifo_depth=N&drop=P&ber=P``
    (plus the I2C driver's ``burst_frames``, ``poll_s``, ``tick_hz``, ``latency_budget_s``, ``combined``): an
    in-process logger, the HIL rig without a second process. ``realtime`` (default): the device
    samples in real time from its own thread while the driver is open and the driver sleeps on its
    DRDY line; otherwise the FIFO fills only on bus accesses (tests with a manual clock) and the
    driver polls.
    """

    def __init__(self, device: FakeI2CDevice, *, realtime: bool = True, **options):
        if realtime:
            options.setdefault("data_ready", device.data_ready)
        super().__init__("fake", device.address, smbus_factory=lambda bus: FakeSMBus(device, bus), **options)
        self.device = device
        self.realtime = realtime

    def open(self) -> "FakeI2CDriver":
        super().open()
        if self.realtime:
            self.device.start_sampling()
        return self

    def close(self) -> None:
        super().close()
        self.device.stop_sampling()

    @classmethod
    def from_spec(cls, spec: DriverSpec) -> "FakeI2CDriver":
        opts = take_options(spec, {
            "scenario": str, "seed": int, "speed": float, "fs": float, "duration": float,
            "fifo_depth": int, "drop": float, "ber": float, "burst_frames": int, "poll_s": float,
            "tick_hz": float, "latency_budget_s": float, "realtime": boolean_option,
            "combined": boolean_option,
        })
        address_text = (spec.host or spec.path).strip("/")
        try:
            address = int(address_text or str(DEFAULT_ADDRESS), 0)
        except ValueError:
            raise DriverError(f"fake I2C address {address_text!r} is not a number like 0x42 "
                              f"(fake-i2c://0x42?scenario=pattern)") from None
        try:
            source = scenario_source(opts.pop("scenario", PATTERN), seed=opts.get("seed", 0),
                                     fs=opts.pop("fs", 200.0), duration=opts.pop("duration", 3600.0))
            device = FakeI2CDevice(source.blocks, source.fs, address=address, speed=opts.pop("speed", 1.0),
                                   fifo_depth=opts.pop("fifo_depth", 32),
                                   faults=Faults(ber=opts.pop("ber", 0.0), drop=opts.pop("drop", 0.0),
                                                 seed=opts.pop("seed", 0)))
        except ValueError as exc:
            raise DriverError(f"fake I2C device: {exc}") from None
        return cls(device, **{**realtime_options(device), **opts})


REALTIME_MIN_FILL_S = 0.1


def realtime_options(device: FakeI2CDevice) -> dict:
    """FakeI2CDriver options for ``device``: real-time sampling with DRDY unless its FIFO fills in less than
    REALTIME_MIN_FILL_S (a time-lapse outruns a loaded host's thread scheduling); then it fills on access
    and the driver polls at a quarter of the fill time."""
    fill = device.depth / (device.rate * device.speed)
    if fill >= REALTIME_MIN_FILL_S:
        return {}
    return {"realtime": False, "poll_s": max(0.001, fill / 4)}
