"""The per-sample engine's common case in one C call per wake-up (daemon/_fastpath.c), and the Python around it.

At 200 Hz the per-sample cost of gravcald is its Python calls (driver.read, decoder, unwrapper, stamp,
correction, publish, fanout), each several µs once other processes have evicted the interpreter's caches
between samples. The C step does, for whole intact frames that continue the stream, what those calls do,
in pipeline order (bus bytes -> frames -> correction -> IMU lines -> sockets), and returns to Python at the
latest every HOUSEKEEPING_S (or once a block for the analysis is staged) for the rest: the counters of
the driver, the unwrapper, the processor and the server, which are applied here from its results.

The step owns the bus's reads: a tty's (serial, slcan: ``step``) or the I2C FIFO's through the I2C_RDWR ioctl
(``i2c_step``, daemon/_i2cpoll.c). Events come back by its return, the one channel: (leftover bytes, the
snapshot of a stopped delivery) and a reason code in ``ist`` (on I2C also the ``bus`` array: transfers, a FIFO
overflow, a failed transfer's errno), applied here; nothing calls back into Python from the loop.

Everything else takes the Python path, exactly as without the C step: the step hands back undecoded the
bytes of any read that is not such frames (a gap, a stray, a restart, a CRC error, a partial frame; the
driver decodes them in its next read; on CAN over slcan a "frame" is a sample's four slcan lines, and
python-can parses what is handed back), is not called while the driver has a question open (a reconnect,
a partial frame, samples waiting, a latency budget, a pyserial URL) or while a watcher is decimated
(``server.fast_watchers`` is None), and a delivery it cannot finish (output queued for a client, a full
socket, a changed policy) is finished by the server's fanout. Every calibration is corrected in C: the step
and the Python path's blocks (Processor.correct) use the same engine and its parameters (processor.engine,
set by the processor through Engine.set_params).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..core.samples import SAMPLE_DTYPE
from ._fastpath import i2c_step, latest, step
from .protocol import ImuBlock

HOUSEKEEPING_S = 0.25  # the longest the C step runs before the Python loop's housekeeping

# The state arrays shared with the C step (the slot names are its enums)
IST_EXPECT, IST_SEQ, IST_FRAMES, IST_TICK, IST_UNKNOWN, IST_REASON, IST_CLIENT, IST_SENT, IST_BATCH, \
    IST_STAGE_LIMIT, IST_CAN, IST_NOGIL, IST_N = range(13)
FST_LAST_T, FST_TICK_HZ, FST_T_RECV, FST_TICK_PERIOD, FST_N = range(5)
R_DUE, R_BYTES, R_DELIVERY, R_NOT_PLAIN, R_EOF, R_ERROR = range(6)
# i2c_step's bus array (daemon/_i2cpoll.h)
IB_ADDRESS, IB_FIRST, IB_BURST, IB_COMBINED, IB_POLL_NS, IB_DRDY_FD, IB_NEXT_POLL_NS, IB_POLLS, IB_BURSTS, \
    IB_OVERFLOW, IB_ERRNO, IB_N = range(12)


class FastPath:
    """The C step for one driver, processor and server. ``taken``: samples it has delivered."""

    def __init__(self, driver: Any, processor: Any, server: Any, *, max_frames: int, stage_bytes: int):
        self.driver, self.processor, self.server = driver, processor, server
        self.max_frames = int(max_frames)
        self.ist = np.zeros(IST_N, dtype=np.int64)
        self.fst = np.zeros(FST_N, dtype=np.float64)
        self.ist[IST_STAGE_LIMIT] = stage_bytes
        # the bytes' records: the serial frame codec's (0), or CAN samples in slcan lines (1 + their base id)
        can_base = getattr(driver, "fast_can_base_id", None)
        self.ist[IST_CAN] = 0 if can_base is None else 1 + can_base
        # the newest batch, as the step wrote it (rows, acc [m/s²], gyro [rad/s], static codes)
        self.rows = np.zeros(self.max_frames, dtype=SAMPLE_DTYPE)
        self.acc = np.zeros((self.max_frames, 3))
        self.gyro = np.zeros(self.max_frames)
        self.codes = np.zeros(self.max_frames, dtype=np.int8)
        self.bus = np.zeros(IB_N, dtype=np.int64)
        self.latest = _Latest(self)
        self.taken = 0
        self.nogil = 0  # batches the step delivered without taking the GIL

    @classmethod
    def for_driver(cls, driver: Any, *args: Any, **kwargs: Any) -> "FastPath | None":
        """A FastPath when the driver offers the C step its descriptor: a tty's (drivers/serial.py and, for
        slcan, drivers/can.py ``fast_entry``) or the I2C bus's with its transfers (drivers/i2c.py ``fast_bus``);
        else None."""
        ok = hasattr(driver, "fast_entry") or hasattr(driver, "fast_bus")
        return cls(driver, *args, **kwargs) if ok else None

    def run(self, staged: bytearray, seconds: float = HOUSEKEEPING_S) -> tuple[int, bool]:
        """Run the C step for up to ``seconds``, appending the records to ``staged``: (samples taken, whether
        the Python path reads next: bytes or a case the step does not take are waiting)."""
        if self.server.fast_watchers is None:
            return 0, True
        if hasattr(self.driver, "fast_bus"):
            return self._run_i2c(staged, seconds)
        entry = self.driver.fast_entry()
        if entry is None:
            return 0, True
        fd, raw, seq, last_t = entry
        self._start(raw, seq, last_t)
        stopped = None
        try:
            leftover, stopped = step(fd, seconds, self.max_frames, self.ist, self.fst, staged, self.server.fast_box,
                                     self.processor.engine, self.rows, self.acc, self.gyro, self.codes)
        finally:
            self.nogil += int(self.ist[IST_NOGIL])
            try:
                n = self._account(int(self.ist[IST_FRAMES]), int(self.ist[IST_UNKNOWN]))
            finally:  # a stopped delivery holds a client's lock: it is finished (and released) whatever happened
                self._finish(stopped)
        if leftover:
            self.driver.unread(leftover)
        return n, int(self.ist[IST_REASON]) != R_DUE

    def _run_i2c(self, staged: bytearray, seconds: float) -> tuple[int, bool]:
        """As :meth:`run` for the logger's FIFO on /dev/i2c-N: the C step polls it too (``i2c_step``), as the
        driver's read does; what the driver must decide (a FIFO overflow, a failed transfer) goes back to it."""
        drv = self.driver
        entry, bus = drv.fast_ready(), drv.fast_bus()
        if entry is None or bus is None:
            return 0, True
        fd, address, first, burst, combined, poll_s, drdy_fd, next_poll_at = bus
        b = self.bus
        b[:IB_POLLS] = (address, first, burst, int(combined), round(poll_s * 1e9), drdy_fd,
                        round(next_poll_at * 1e9) if math.isfinite(next_poll_at) else 0)
        self._start(*entry)
        stopped, leftover = None, b""
        try:
            leftover, stopped = i2c_step(fd, seconds, self.max_frames, b, self.ist, self.fst, staged,
                                         self.server.fast_box, self.processor.engine, self.rows, self.acc, self.gyro,
                                         self.codes)
        finally:
            self.nogil += int(self.ist[IST_NOGIL])
            try:
                n = self._account(int(self.ist[IST_FRAMES]), int(self.ist[IST_UNKNOWN]))
            finally:
                self._finish(stopped)
                if leftover:  # first: after a failed transfer these come before the reconnect's
                    drv.unread([leftover])
                drv.fast_polled(int(b[IB_POLLS]), int(b[IB_BURSTS]), int(b[IB_NEXT_POLL_NS]) * 1e-9,
                                bool(b[IB_OVERFLOW]), int(b[IB_ERRNO]))
        return n, int(self.ist[IST_REASON]) != R_DUE

    def _start(self, raw: int, seq: int, last_t: float) -> None:
        ist, fst = self.ist, self.fst
        ist[IST_EXPECT], ist[IST_SEQ], ist[IST_FRAMES] = raw, seq, 0
        fst[FST_LAST_T], fst[FST_TICK_HZ], fst[FST_TICK_PERIOD] = last_t, self.driver.tick_hz or 0.0, math.nan

    def _finish(self, stopped: Any) -> None:
        """A delivery the step stopped: the server's fanout delivers the rest of the batch."""
        if stopped is None:
            return
        index = int(self.ist[IST_CLIENT])
        try:
            k = int(self.ist[IST_BATCH])
            block = ImuBlock(self.rows[:k].copy(), self.acc[:k].copy(), self.gyro[:k].copy(), self.codes[:k].copy())
        except BaseException:
            stopped[index][0].lock.release()  # the lock the step left held: that client must not stay locked out
            raise
        self.server.finish_publish(block, stopped, index, int(self.ist[IST_SENT]))

    def _account(self, n: int, unknown: int) -> int:
        """What the Python path counts per sample, for the ``n`` samples the step took."""
        ist, fst = self.ist, self.fst
        if n <= 0:
            return 0
        period = float(fst[FST_TICK_PERIOD])
        self.driver.fast_consumed(n, int(ist[IST_TICK]), None if math.isnan(period) else period,
                                  float(fst[FST_LAST_T]), float(fst[FST_T_RECV]))
        self.processor.corrected_seq = int(ist[IST_SEQ]) - 1
        self.processor.static_unknown += unknown
        self.server.count_published(n, self.latest)
        self.taken += n
        return n


class _Latest:
    """?POLL's newest sample while the C step publishes: copied out of the arrays the step writes under its
    lock (it writes them without the GIL), then encoded."""

    __slots__ = ("fast",)

    def __init__(self, fast: FastPath):
        self.fast = fast

    def last_message(self, raw: bool = False) -> dict[str, Any] | None:
        f = self.fast
        one = (np.zeros(1, dtype=SAMPLE_DTYPE), np.zeros((1, 3)), np.zeros(1), np.zeros(1, dtype=np.int8))
        if not latest(f.ist, f.rows, f.acc, f.gyro, f.codes, *one):
            return None
        return ImuBlock(*one).last_message(raw)
