"""CAN driver (python-can): one sample = four classic CAN frames, paired by a sequence byte.

Layout (standard 11-bit identifiers from ``base_id``, default 0x100; all fields little-endian)::

    id       name          dlc  bytes
    base+0   TIMING        8    seq u16, tick u32, gyro u16
    base+1   CHIP_A        7    seq_lo u8, T1 ax u16, T1 ay u16, T2 chip A u16
    base+2   CHIP_B        7    seq_lo u8, T1 az u16, T1 ax2 u16, T2 chip B u16
    base+3   HOUSEKEEPING  5    seq_lo u8, temp_raw u16, vsupply_raw u16 (12-bit ADC codes)

The logger sends them in this order. Every frame carries the sample's sequence number
(TIMING the full 16 bits, the others its low byte), so frames of one sample are paired even
when some are lost. Missing frames:

- TIMING lost: the sample cannot be placed (no seq, no tick) and is dropped; its other frames
  are counted as ``orphan_frames``; the next sample carries FLAG_GAP_BEFORE.
- CHIP_A / CHIP_B / HOUSEKEEPING lost: the sample is delivered with FLAG_PARTIAL; the missing
  T1/T2 are 0 (so ``duty_ratios`` gives NaN) and a missing temp/vsupply is NaN.

Any python-can interface works: ``socketcan`` on real hardware (the production path), ``slcan``
for USB-serial adapters (also over the emulator's pty; served by drivers/slcan.py, python-can's
slcan bus with a burst read path; gravcald's C step reads its common case, see
:meth:`CanDriver.fast_entry`), ``virtual`` in-process. The bit errors of a real bus never reach
the host (the controller's CRC rejects the frame), so only whole frames go missing.
"""
from __future__ import annotations

import errno
import os
import struct
import time
from typing import Any

import can
import numpy as np
import serial

from ..core.samples import FLAG_GAP_BEFORE, FLAG_PARTIAL, SAMPLE_DTYPE
from .base import PERMISSION_ERRNOS, Backoff, Driver, DriverError, DriverSpec, permission_hint, take_options
from .slcan import BufferedSlcanBus
from .codec import (
    ADC_MISSING,
    TICK_HZ,
    SeqUnwrapper,
    temp_from_raw,
    to_wire,
    vsupply_from_raw,
)

DEFAULT_BASE_ID = 0x100
SLCAN_SAMPLE_BYTES = 78  # one sample's four slcan lines "tIIIL<2*dlc hex>\r" (22 + 20 + 20 + 16 bytes)
TIMING, CHIP_A, CHIP_B, HOUSEKEEPING = range(4)
FRAME_NAMES = ("TIMING", "CHIP_A", "CHIP_B", "HOUSEKEEPING")
FRAME_DLC = (8, 7, 7, 5)
_ALL = (1 << 4) - 1

# Packed little-endian payload layouts (numpy views: pack/unpack whole blocks at once).
_TIMING = np.dtype([("seq", "<u2"), ("tick", "<u4"), ("gyro", "<u2")])
_CHIP = np.dtype([("seq_lo", "u1"), ("t1a", "<u2"), ("t1b", "<u2"), ("t2", "<u2")])
_HK = np.dtype([("seq_lo", "u1"), ("temp_raw", "<u2"), ("vsupply_raw", "<u2")])
_RECORD = np.dtype(
    [("seq", "<u2"), ("tick", "<u4"), ("gyro", "<u2"), ("t1", "<u2", (4,)), ("t2", "<u2", (2,)),
     ("temp_raw", "<u2"), ("vsupply_raw", "<u2"), ("present", "u1")]
)


def pack_frames(samples: np.ndarray) -> list[list[bytes]]:
    """The four payloads (TIMING, CHIP_A, CHIP_B, HOUSEKEEPING) for each sample."""
    w = to_wire(samples)  # same range checks and ADC conversions as the serial frame
    n = w.shape[0]
    tm = np.zeros(n, _TIMING)
    tm["seq"], tm["tick"], tm["gyro"] = w["seq"], w["tick"], w["gyro"]
    lo = (w["seq"] & 0xFF).astype(np.uint8)
    ca = np.zeros(n, _CHIP)
    ca["seq_lo"], ca["t1a"], ca["t1b"], ca["t2"] = lo, w["t1"][:, 0], w["t1"][:, 1], w["t2"][:, 0]
    cb = np.zeros(n, _CHIP)
    cb["seq_lo"], cb["t1a"], cb["t1b"], cb["t2"] = lo, w["t1"][:, 2], w["t1"][:, 3], w["t2"][:, 1]
    hk = np.zeros(n, _HK)
    hk["seq_lo"], hk["temp_raw"], hk["vsupply_raw"] = lo, w["temp_raw"], w["vsupply_raw"]
    parts = [a.tobytes() for a in (tm, ca, cb, hk)]
    sizes = [a.itemsize for a in (tm, ca, cb, hk)]
    return [[parts[k][i * sizes[k] : (i + 1) * sizes[k]] for k in range(4)] for i in range(n)]


def to_messages(samples: np.ndarray, base_id: int = DEFAULT_BASE_ID) -> list[can.Message]:
    """python-can messages for a block of samples, in transmission order."""
    out = []
    for payloads in pack_frames(samples):
        for k, data in enumerate(payloads):
            out.append(can.Message(arbitration_id=base_id + k, data=data, is_extended_id=False))
    return out


_TIMING_S = struct.Struct("<HIH")
_CHIP_S = struct.Struct("<BHHH")
_HK_S = struct.Struct("<BHH")
# Pending sample as a plain list (cheaper than numpy per frame): indices into _RECORD order.
_SEQ, _TICK, _GYRO, _T1, _T2, _TEMP, _VSUP, _PRESENT = 0, 1, 2, 3, 7, 9, 10, 11


class SampleAssembler(can.Listener):
    """Pairs the four frames of each sample (a python-can Listener: attach it to a Notifier
    or feed it from ``bus.recv``). Completed samples accumulate until ``take()``.
    """

    def __init__(self, base_id: int = DEFAULT_BASE_ID, *, partial_timeout: float = 0.05):
        self.base_id = base_id
        self.partial_timeout = partial_timeout
        self._pending: list[int] | None = None
        self._since = 0.0
        self._ready: list[tuple] = []
        self.counters = {"can_frames": 0, "orphan_frames": 0, "bad_frames": 0, "partial": 0,
                         "error_frames": 0, "foreign_frames": 0, "garbled_lines": 0}
        self.garbled_kinds: dict[str, int] = {}  # garbled_lines by the parser's exception

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self.counters["error_frames"] += 1
            return
        k = msg.arbitration_id - self.base_id
        if msg.is_extended_id or msg.is_remote_frame or not 0 <= k < 4:
            self.counters["foreign_frames"] += 1
            return
        data = bytes(msg.data)
        if len(data) != FRAME_DLC[k]:
            self.counters["bad_frames"] += 1
            return
        self.counters["can_frames"] += 1
        if k == TIMING:
            self._finish()
            seq, tick, gyro = _TIMING_S.unpack(data)
            self._pending = [seq, tick, gyro, 0, 0, 0, 0, 0, 0, ADC_MISSING, ADC_MISSING, 1]
            self._since = time.monotonic()
            return
        p = self._pending
        if p is None or data[0] != (p[_SEQ] & 0xFF) or p[_PRESENT] & (1 << k):
            self.counters["orphan_frames"] += 1
            return
        if k == HOUSEKEEPING:
            _, p[_TEMP], p[_VSUP] = _HK_S.unpack(data)
        else:
            i = 0 if k == CHIP_A else 2
            _, p[_T1 + i], p[_T1 + i + 1], p[_T2 + k - 1] = _CHIP_S.unpack(data)
        p[_PRESENT] |= 1 << k
        if p[_PRESENT] == _ALL:
            self._finish()

    def count_garbled(self, kind: str) -> None:
        """One interface line lost to its parser, which raised ``kind`` (an exception's class name)."""
        self.counters["garbled_lines"] += 1
        self.garbled_kinds[kind] = self.garbled_kinds.get(kind, 0) + 1

    def on_error(self, exc: Exception) -> None:  # Notifier hook
        self.counters["error_frames"] += 1

    def poll(self, now: float | None = None) -> None:
        """Deliver a pending incomplete sample once ``partial_timeout`` has passed."""
        if self._pending is not None:
            if (now if now is not None else time.monotonic()) - self._since > self.partial_timeout:
                self._finish()

    def _finish(self) -> None:
        p, self._pending = self._pending, None
        if p is not None:
            if p[_PRESENT] != _ALL:
                self.counters["partial"] += 1
            self._ready.append((p[0], p[1], p[2], p[3:7], p[7:9], p[9], p[10], p[11]))

    @property
    def ready(self) -> bool:
        """Some sample is assembled and waiting for ``take()``."""
        return bool(self._ready)

    def take(self) -> np.ndarray:
        """Assembled records so far (raw fields + ``present`` bit mask), oldest first."""
        out = np.array(self._ready, dtype=_RECORD) if self._ready else np.zeros(0, _RECORD)
        self._ready = []
        return out

    def reset(self) -> None:
        self._pending = None


def records_to_samples(rec: np.ndarray, unwrapper: SeqUnwrapper) -> np.ndarray:
    """SAMPLE_DTYPE from assembled records: seq unwrapped, FLAG_GAP_BEFORE / FLAG_PARTIAL set."""
    out = np.zeros(rec.shape[0], SAMPLE_DTYPE)
    out["t"] = np.nan
    out["tick"], out["gyro"], out["t1"], out["t2"] = rec["tick"], rec["gyro"], rec["t1"], rec["t2"]
    out["temp"] = temp_from_raw(rec["temp_raw"])
    out["vsupply"] = vsupply_from_raw(rec["vsupply_raw"])
    out["flags"][rec["present"] != _ALL] |= FLAG_PARTIAL
    keep, seq, gap = unwrapper.unwrap(rec["seq"], rec["tick"])
    out = out[keep]
    out["seq"] = seq
    out["flags"][gap] |= FLAG_GAP_BEFORE
    return out


class CanDriver(Driver):
    """Samples from a CAN bus through python-can (``can.Bus(interface=..., channel=...)``)."""

    bus = "can"
    transient_errors = (can.CanError, OSError, serial.SerialException)

    def __init__(
        self,
        interface: str,
        channel: str,
        *,
        bitrate: int | None = None,
        base_id: int = DEFAULT_BASE_ID,
        partial_timeout: float = 0.05,
        latency_budget_s: float = 0.0,
        tick_hz: float | None = TICK_HZ,
        backoff: Backoff | None = None,
        **bus_kwargs: Any,
    ):
        super().__init__(tick_hz=tick_hz, backoff=backoff)
        if not latency_budget_s >= 0:
            raise DriverError(f"latency_budget_s must be >= 0, got {latency_budget_s}")
        self.latency_budget_s = float(latency_budget_s)
        if not interface or not channel:
            raise DriverError("CAN driver needs an interface and a channel, e.g. can://socketcan/can0")
        if not 0 <= base_id <= 0x7FF - 3:
            raise DriverError(f"CAN base_id 0x{base_id:X} leaves no room for 4 standard identifiers")
        self.interface = interface
        self.channel = channel
        self.bitrate = bitrate
        self.base_id = base_id
        self.bus_kwargs = bus_kwargs
        if interface == "slcan":
            # python-can sleeps 2 s after opening for Arduino-style resets; USB adapters and the
            # emulator's pty need none. Reads wait on the port's descriptor (drivers/slcan.py); the
            # serial timeout only paces ports without one (pyserial URLs).
            self.bus_kwargs.setdefault("sleep_after_open", 0.0)
            self.bus_kwargs.setdefault("timeout", 0.01)
        self.assembler = SampleAssembler(base_id, partial_timeout=partial_timeout)
        self.unwrapper = SeqUnwrapper()
        self._bus: can.BusABC | None = None
        self._deferred: BaseException | None = None

    @classmethod
    def from_spec(cls, spec: DriverSpec) -> "CanDriver":
        opts = take_options(
            spec,
            {"bitrate": int, "base_id": lambda v: int(v, 0), "partial_timeout": float, "latency_budget_s": float,
             "tick_hz": float, "tty_baudrate": int, "sleep_after_open": float, "timeout": float},
        )
        interface = spec.host
        # slcan channels are device paths (keep the slash); socketcan/virtual names are not.
        channel = spec.path if interface == "slcan" else spec.path.lstrip("/")
        return cls(interface, channel, **opts)

    @property
    def description(self) -> str:
        return f"{self.interface}:{self.channel}"

    def _connect(self, *, first: bool) -> None:
        if self.interface == "slcan" and "://" not in self.channel:
            _check_device_path(self.channel.split("@")[0])
        kwargs = dict(self.bus_kwargs)
        if self.bitrate is not None:
            kwargs["bitrate"] = self.bitrate
        try:
            if self.interface == "slcan":  # python-can's slcan with a read path that does not cost a call per byte
                bus = BufferedSlcanBus(channel=self.channel, **kwargs)
            else:
                bus = can.Bus(interface=self.interface, channel=self.channel, **kwargs)
        except (can.CanError, OSError, serial.SerialException, ValueError) as exc:
            raise _open_error(self.interface, self.channel, exc) from None
        try:
            bus.set_filters([{"can_id": self.base_id, "can_mask": 0x7FC, "extended": False}])
        except (can.CanError, NotImplementedError):
            pass  # python-can filters in software then
        self._bus = bus

    def _disconnect(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None:
            try:
                bus.shutdown()
            finally:
                # slcan's shutdown writes "C" first; on a vanished adapter that raises before
                # the port is closed, so close it here or the fd leaks on every reconnect.
                port = getattr(bus, "serialPortOrig", None)
                if port is not None:
                    port.close()

    def _after_reconnect(self) -> None:
        self.assembler.reset()

    def _unwrapper(self):
        return self.unwrapper

    def _codec_stats(self):
        out = dict(self.assembler.counters)
        out["garbled_kinds"] = dict(self.assembler.garbled_kinds)
        out.update(frames=out["can_frames"], gaps=self.unwrapper.gaps, missing=self.unwrapper.missing,
                   restarts=self.unwrapper.restarts,
                   duplicates=self.unwrapper.duplicates, strays=self.unwrapper.strays)
        return out

    # -- the daemon's latency path (daemon/fastpath.py), slcan with a port descriptor only ------------
    @property
    def fast_can_base_id(self) -> int:
        """The daemon's C step reads this bus's slcan lines as CAN samples from this base id."""
        return self.base_id

    def fast_entry(self) -> tuple[int, int, int, float] | None:
        """(fd, raw seq, output seq, last t) when the next bytes may go to the daemon's C step
        (daemon/_fastpath.c), which takes only reads that are whole samples (four standard-frame lines of
        base_id..base_id+3) each continuing the stream by one, and hands anything else back unparsed
        (:meth:`unread`); None: they go through :meth:`read` and python-can (socketcan, virtual, a pyserial
        URL, an outage or a reconnect in hand, a line or a sample part-read, samples waiting, a latency
        budget, a sequence question open)."""
        bus, asm = self._bus, self.assembler
        if (not isinstance(bus, BufferedSlcanBus) or not self._connected or self._closing.is_set()
                or self._pending.shape[0] or self._holding or self._flag_reconnect
                or self._deferred is not None
                or self.latency_budget_s > 0 or asm._pending is not None or asm._ready):
            return None
        fd = bus.fast_fd()
        nxt = self.unwrapper.next_frame() if fd is not None else None
        if nxt is None:
            return None
        bus.wake_at(SLCAN_SAMPLE_BYTES)
        return fd, nxt[0], nxt[1], self._last_t

    def unread(self, data: bytes) -> None:
        """Bytes the C step read but did not take: python-can parses them next, as if just read."""
        self._bus.unread(data)

    def _count_fast_frames(self, n: int) -> None:
        self.assembler.counters["can_frames"] += 4 * n

    def _recv(self, timeout: float) -> can.Message | None:
        """bus.recv, with a line the interface cannot parse counted and skipped: python-can's slcan parser
        raises whatever its indexing and int()/fromhex()/Message() checks raise on a garbled ASCII line (bytes
        lost on the USB link: ``t12`` IndexError, ``t10G8`` ValueError, non-ASCII UnicodeDecodeError), after
        consuming it, so the next call reads on from the following line. One lost line, counted in
        ``garbled_lines`` and by kind in ``garbled_kinds``; not a bus failure: no reconnect. Only the
        interface's own failures (transient_errors: the port, the adapter) reach read()'s reconnect."""
        try:
            return self._bus.recv(timeout=timeout)
        except self.transient_errors:
            raise
        except Exception as exc:
            self.assembler.count_garbled(type(exc).__name__)
            return None

    def _read_block(self, deadline: float) -> np.ndarray:
        if self._deferred is not None:
            exc, self._deferred = self._deferred, None
            raise exc
        asm = self.assembler
        msg = self._recv(max(0.0, deadline - time.monotonic()))
        if msg is not None:
            asm.on_message_received(msg)
            hold = time.monotonic() + self.latency_budget_s  # frames within the budget go out together
            buffered = getattr(self._bus, "has_buffered_line", None)
            try:
                for _ in range(4096):  # drain what is already there, bounded
                    if asm.ready and time.monotonic() >= hold and buffered is not None and not buffered():
                        break  # a sample is complete: publish it rather than read on while more arrives
                    msg = self._recv(max(0.0, hold - time.monotonic()))
                    if msg is None:
                        break
                    asm.on_message_received(msg)
            except self.transient_errors as exc:
                # Deliver what was assembled before the bus died; the error is raised next call
                # so the reconnect flag lands on the first sample after the outage.
                self._deferred = exc
        asm.poll()
        return records_to_samples(asm.take(), self.unwrapper)


def _check_device_path(path: str) -> None:
    try:
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError as exc:
        raise _open_error("slcan", path, exc) from None
    os.close(fd)


def _root_errno(exc: BaseException) -> int | None:
    while exc is not None:
        code = getattr(exc, "errno", None)
        if isinstance(code, int):
            return code
        exc = exc.__cause__ or exc.__context__
    return None


def _open_error(interface: str, channel: str, exc: BaseException) -> DriverError:
    code = _root_errno(exc)
    if code in PERMISSION_ERRNOS:
        return DriverError(permission_hint(channel, "dialout"))
    if code == errno.ENOENT:
        return DriverError(f"CAN adapter {channel} does not exist (is the USB-CAN adapter plugged in?)")
    if code == errno.ENODEV:
        return DriverError(f"CAN interface {channel} does not exist (see ip link show)")
    if code == errno.ENETDOWN:
        return DriverError(f"CAN interface {channel} is down (sudo ip link set {channel} up type can bitrate ...)")
    if code == errno.EAFNOSUPPORT:
        return DriverError(f"cannot open CAN {interface} channel {channel}: this kernel has no SocketCAN "
                           f"support (use a slcan adapter: can://slcan/dev/ttyACM0)")
    return DriverError(f"cannot open CAN {interface} channel {channel}: {exc}")
