"""The hardware-in-the-loop emulator: the logger board, minus the hardware.

It paces a sample source (sensor model, recording, test pattern) in real time or ``speed``
times faster and puts the frames on a bus the real drivers open unchanged:

- serial: a pty pair; the slave is reachable through a stable symlink (``link``), like a
  udev ``/dev/serial/by-id`` name, so a driver reconnects by path after a disconnect;
- slcan and python-can buses: see ``can_links``;
- I2C: see ``fake_i2c.FakeI2CDevice`` (pull-based: the FIFO fills with time).

Fault injection (:class:`Faults`): bit-error rate, dropped frames, disconnects at given stream
times. Every sample's fate is written to a :class:`SentLog` (what went on the wire, wire-exact),
which tests and HIL users compare with what the host received.
"""
from __future__ import annotations

import logging
import math
import os
import select
import tempfile
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from ...core.samples import SAMPLE_DTYPE
from ..codec import FRAME_LEN, encode_frames, wire_roundtrip

log = logging.getLogger(__name__)

# Fate of each sample (SentLog.status).
SENT = 0  # on the wire intact
DROPPED = 1  # not sent (injected drop); CAN: TIMING frame dropped
CORRUPTED = 2  # sent with bit errors (the receiver must reject it)
OFFLINE = 3  # produced while the device was disconnected
OVERRUN = 4  # the link's buffer was full (nobody reading): lost
CLOSED = 5  # CAN channel not opened by the host: not sent
PARTIAL = 6  # CAN: TIMING sent, some other frame of the sample dropped
FIFO_FULL = 7  # I2C: lost because the FIFO was full
STATUS_NAMES = ("sent", "dropped", "corrupted", "offline", "overrun", "closed", "partial", "fifo_full")


@dataclass
class Faults:
    """Fault injection. Times are stream seconds (sample time), independent of ``speed``."""

    ber: float = 0.0  # bit-error rate on the serial byte stream / I2C bursts; CAN: frame loss
    drop: float = 0.0  # probability that a frame is not sent at all
    disconnects: Sequence[tuple[float, float]] = ()  # (start, duration) pairs
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0.0 <= self.ber < 1.0:
            raise ValueError(f"bit-error rate must be in [0, 1), got {self.ber}")
        if not 0.0 <= self.drop < 1.0:
            raise ValueError(f"drop probability must be in [0, 1), got {self.drop}")
        for start, dur in self.disconnects:
            if start < 0 or dur <= 0:
                raise ValueError(f"disconnect {start}:{dur}: start must be >= 0 and duration > 0")
        self.disconnects = tuple(sorted((float(a), float(b)) for a, b in self.disconnects))
        self.rng = np.random.default_rng(self.seed)

    def offline(self, t: np.ndarray) -> np.ndarray:
        """Mask of stream times inside a disconnect window."""
        m = np.zeros(t.shape, bool)
        for start, dur in self.disconnects:
            m |= (t >= start) & (t < start + dur)
        return m

    def flip_bits(self, data: bytearray) -> np.ndarray:
        """Flip bits of ``data`` in place at rate ``ber``; returns the flipped byte offsets."""
        nbits = len(data) * 8
        if self.ber <= 0 or nbits == 0:
            return np.zeros(0, np.int64)
        k = self.rng.binomial(nbits, self.ber)
        if k == 0:
            return np.zeros(0, np.int64)
        bits = np.unique(self.rng.integers(0, nbits, k))
        for b in bits.tolist():
            data[b >> 3] ^= 1 << (b & 7)
        return bits >> 3


@dataclass
class SentLog:
    """Every produced sample (wire-exact values) with its fate; ``frames`` per CAN frame."""

    blocks: list = field(default_factory=list)
    status: list = field(default_factory=list)
    frames: list = field(default_factory=list)  # CAN: (N, 4) bool delivered masks

    def add(self, samples: np.ndarray, status: np.ndarray, frames: np.ndarray | None = None) -> None:
        self.blocks.append(wire_roundtrip(samples))
        self.status.append(np.asarray(status, np.uint8))
        if frames is not None:
            self.frames.append(frames)

    def arrays(self) -> dict[str, np.ndarray]:
        out = {
            "samples": np.concatenate(self.blocks) if self.blocks else np.zeros(0, SAMPLE_DTYPE),
            "status": np.concatenate(self.status) if self.status else np.zeros(0, np.uint8),
        }
        if self.frames:
            out["frames"] = np.concatenate(self.frames)
        return out

    def save(self, path: str | Path) -> None:
        """Write an .npz (samples, status[, frames]); readable with ``load_sent_log``."""
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez(tmp, **self.arrays())
        os.replace(tmp, path)

    def counts(self) -> dict[str, int]:
        st = self.arrays()["status"]
        return {name: int((st == i).sum()) for i, name in enumerate(STATUS_NAMES) if (st == i).any()}


def load_sent_log(path: str | Path) -> dict[str, np.ndarray]:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


# ---------------------------------------------------------------------------------------
# links
# ---------------------------------------------------------------------------------------
class Link:
    """A bus the emulator writes to. ``send`` returns the status of each sample, and for a bus
    that splits a sample into ``frames_per_sample`` frames, which of them were delivered."""

    name = "link"
    frames_per_sample: int | None = None

    def connect(self) -> None: ...

    def disconnect(self) -> None: ...

    def send(self, samples: np.ndarray, faults: Faults, blocking: bool) -> tuple[np.ndarray, np.ndarray | None]:
        raise NotImplementedError

    def service(self, timeout: float) -> None:
        """Wait up to ``timeout`` s, answering whatever the host sends."""
        if timeout > 0:
            time.sleep(timeout)

    @property
    def spec(self) -> str:
        raise NotImplementedError

    def close(self) -> None:
        self.disconnect()


class PtyLink(Link):
    """A pty pair behind a stable symlink; the host opens the symlink like /dev/ttyUSB0.

    The emulator keeps the slave open itself (raw mode), so the host may open and close it at
    will; ``disconnect`` closes both ends and removes the symlink, which the host sees as an
    unplugged USB adapter; ``connect`` makes a fresh pty behind the same symlink.
    """

    name = "serial"

    def __init__(self, link: str | Path | None = None):
        if link is None:
            link = Path(tempfile.mkdtemp(prefix="gravcal-emu-")) / "ttyGRAVCAL0"
        self.link = Path(link)
        self.link.parent.mkdir(parents=True, exist_ok=True)
        self.master: int | None = None
        self._slave: int | None = None
        self.slave_name = ""

    @property
    def spec(self) -> str:
        return f"serial://{self.link}"

    def connect(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no CR/NL translation: bytes pass unchanged
        os.set_blocking(master, False)
        self.master, self._slave = master, slave
        self.slave_name = os.ttyname(slave)
        tmp = self.link.with_name(self.link.name + ".new")
        if tmp.is_symlink() or tmp.exists():
            tmp.unlink()
        os.symlink(self.slave_name, tmp)
        os.replace(tmp, self.link)  # atomic: the path never points at a dead pty

    def disconnect(self) -> None:
        if self.link.is_symlink():
            self.link.unlink()
        for fd in (self.master, self._slave):
            if fd is not None:
                os.close(fd)
        self.master = self._slave = None

    def write(self, data: bytes, blocking: bool) -> int:
        """Write as much as the pty takes (all of it if ``blocking``); returns bytes written."""
        view, done = memoryview(data), 0
        while done < len(data):
            try:
                done += os.write(self.master, view[done:])
            except BlockingIOError:
                if not blocking:
                    break
                self._drain_input()
                select.select([], [self.master], [], 0.05)
        return done

    def _drain_input(self) -> bytes:
        try:
            return os.read(self.master, 4096)
        except (BlockingIOError, OSError):
            return b""

    def service(self, timeout: float) -> None:
        if self.master is None:
            time.sleep(max(0.0, timeout))
            return
        r, _, _ = select.select([self.master], [], [], max(0.0, timeout))
        if r:
            self.on_input(self._drain_input())

    def on_input(self, data: bytes) -> None:
        """Bytes the host wrote; the serial logger ignores them."""

    def send(self, samples, faults, blocking):
        n = samples.shape[0]
        status = np.full(n, SENT, np.uint8)
        drop = faults.rng.random(n) < faults.drop if faults.drop else np.zeros(n, bool)
        status[drop] = DROPPED
        keep = np.flatnonzero(~drop)
        data = bytearray(encode_frames(samples[keep]))
        flipped = faults.flip_bits(data)
        if flipped.shape[0]:
            status[keep[np.unique(flipped // FRAME_LEN)]] = CORRUPTED
        written = self.write(bytes(data), blocking)
        lost = keep[written // FRAME_LEN :]  # a frame cut short is lost as a whole
        status[lost] = OVERRUN
        return status, None

    def close(self) -> None:
        self.disconnect()
        try:
            self.link.parent.rmdir()
        except OSError:
            pass


# ---------------------------------------------------------------------------------------
# the pacing loop
# ---------------------------------------------------------------------------------------
@dataclass
class Emulator:
    """Paces ``blocks`` (SAMPLE_DTYPE, rate ``fs`` Hz) onto ``link``.

    ``speed`` is the time-lapse factor (1 = real time, ``math.inf`` = as fast as the link
    takes it, with back-pressure instead of overruns). Sends at most every ``min_interval``
    wall seconds, so high rates go out in small batches.
    """

    blocks: Iterable[np.ndarray]
    fs: float
    link: Link
    speed: float = 1.0
    faults: Faults = field(default_factory=Faults)
    log: SentLog | None = None
    min_interval: float = 0.002
    clock: Callable[[], float] = time.monotonic
    stop: threading.Event = field(default_factory=threading.Event)
    on_event: Callable[[str], None] | None = None
    sent_index: int = 0  # samples produced so far

    def run(self) -> int:
        """Run until the source is exhausted or ``stop`` is set; returns samples produced."""
        if self.fs <= 0 or not math.isfinite(self.fs):
            raise ValueError(f"sample rate must be a positive number, got {self.fs}")
        if not self.speed > 0:
            raise ValueError(f"speed must be > 0, got {self.speed}")
        online = True
        self.link.connect()
        t0 = self.clock()
        rate = self.fs * self.speed  # samples per wall second
        try:
            for block in self.blocks:
                j = 0
                while j < block.shape[0]:
                    if self.stop.is_set():
                        return self.sent_index
                    i = self.sent_index
                    if math.isinf(rate):
                        n_due = block.shape[0] - j
                        self.link.service(0.0)  # answer the host: an slcan adapter opens on its "O"
                    else:
                        now = self.clock()
                        n_due = int((now - t0) * rate) + 1 - i
                        if n_due <= 0:
                            self.link.service(max(t0 + i / rate - now, self.min_interval))
                            continue
                    chunk = block[j : j + n_due]
                    ts = (i + np.arange(chunk.shape[0])) / self.fs
                    off = self.faults.offline(ts)
                    # Process runs of equal online state (connect/disconnect at boundaries).
                    edges = np.flatnonzero(np.diff(off.astype(np.int8))) + 1
                    for a, b in zip(np.r_[0, edges], np.r_[edges, off.shape[0]]):
                        part = chunk[a:b]
                        if off[a]:
                            if online:
                                self.link.disconnect()
                                online = False
                                self._event(f"disconnected at t={ts[a]:.3f}s")
                            k = self.link.frames_per_sample
                            self._log(part, np.full(part.shape[0], OFFLINE, np.uint8),
                                      np.zeros((part.shape[0], k), bool) if k else None)
                        else:
                            if not online:
                                self.link.connect()
                                online = True
                                self._event(f"reconnected at t={ts[a]:.3f}s")
                            status, frames = self.link.send(part, self.faults, math.isinf(rate))
                            self._log(part, status, frames)
                            lost = np.flatnonzero(status == OVERRUN)
                            if lost.size:  # a real UART's overflow: the host fell behind; say so
                                self._event(f"overrun at t={ts[a + lost[0]]:.3f}s: {lost.size} samples lost "
                                            "(the host did not read; the link's buffer was full)")
                    self.sent_index += chunk.shape[0]
                    j += chunk.shape[0]
                    if not math.isinf(rate):
                        self.link.service(0.0)
        finally:
            if not online:
                self.link.connect()  # leave a live device behind for lingering
        return self.sent_index

    def linger(self, seconds: float | None) -> None:
        """Keep the link alive (answering the host) until ``stop`` or ``seconds`` pass."""
        end = None if seconds is None else self.clock() + seconds
        while not self.stop.is_set() and (end is None or self.clock() < end):
            self.link.service(0.05)

    def _log(self, part, status, frames) -> None:
        if self.log is not None:
            self.log.add(part, status, frames)

    def _event(self, text: str) -> None:
        log.info("emulator: %s", text)
        if self.on_event is not None:
            self.on_event(text)
