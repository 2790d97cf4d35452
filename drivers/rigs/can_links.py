"""The emulator's CAN links: the logger's four CAN frames per sample (drivers/can.py layout).

- :class:`SlcanPtyLink`: a pty speaking the LAWICEL/slcan ASCII protocol on the master side
  (answers the open/close/bitrate commands python-can sends, emits ``t`` frames while the
  channel is open), so python-can's ``slcan`` interface opens it like a USB adapter;
- :class:`PythonCanLink`: any in-process python-can interface, e.g. ``virtual``.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import can
import numpy as np

from ..can import DEFAULT_BASE_ID, FRAME_DLC, TIMING, pack_frames
from .emulator import CLOSED, DROPPED, OVERRUN, PARTIAL, SENT, Link, PtyLink


class SlcanPtyLink(PtyLink):
    """An slcan (LAWICEL) USB-CAN adapter on a pty: python-can's ``slcan`` interface opens it.

    Answers C/O/L/S/s/V/v/N/F/Z/W commands with CR (BELL for unknown ones), acknowledges host
    transmissions with z/Z, and emits received bus traffic as ``tIIILDD..`` lines while the
    channel is open. A CAN frame hit by a bit error is lost (the controller rejects it).
    """

    name = "slcan"
    frames_per_sample = 4

    def __init__(self, link: str | Path | None = None, base_id: int | None = None, bitrate: int = 1_000_000):
        if link is None:
            link = Path(tempfile.mkdtemp(prefix="gravcal-emu-")) / "ttyGRAVCAN0"
        super().__init__(link)

        self.base_id = DEFAULT_BASE_ID if base_id is None else base_id
        self.bitrate = bitrate
        self.channel_open = False
        self._line = bytearray()
        self.commands: list[str] = []

    @property
    def spec(self) -> str:
        return f"can://slcan{self.link}?bitrate={self.bitrate}"

    def connect(self) -> None:
        self.channel_open = False
        self._line.clear()
        super().connect()

    def on_input(self, data: bytes) -> None:
        self._line.extend(data)
        while True:
            i = self._line.find(b"\r")
            if i < 0:
                break
            cmd = self._line[:i].decode("ascii", "replace")
            del self._line[: i + 1]
            self.commands.append(cmd)
            self.write(self._answer(cmd).encode(), blocking=True)

    def _answer(self, cmd: str) -> str:
        if not cmd:
            return "\r"
        c = cmd[0]
        if c in "OL":
            self.channel_open = True
            return "\r"
        if c == "C":
            self.channel_open = False
            return "\r"
        if c in "SsZWM m":
            return "\r"
        if c == "V":
            return "V1013\r"
        if c == "v":
            return "v1013\r"
        if c == "N":
            return "NGRAV\r"
        if c == "F":
            return "F00\r"
        if c in "tr":
            return "z\r"
        if c in "TR":
            return "Z\r"
        return "\a"

    def send(self, samples, faults, blocking):
        n = samples.shape[0]
        if not self.channel_open:
            return np.full(n, CLOSED, np.uint8), np.zeros((n, 4), bool)
        payloads = pack_frames(samples)
        frames = np.ones((n, 4), bool)
        if faults.drop:
            frames &= faults.rng.random((n, 4)) >= faults.drop
        if faults.ber:
            # Each frame's ~(47 + 8*dlc) bits: one error loses the frame (one-shot mode).
            bits = 47 + 8 * np.asarray(FRAME_DLC)
            frames &= faults.rng.random((n, 4)) >= 1 - (1 - faults.ber) ** bits
        lines = []
        for i, parts in enumerate(payloads):
            for k, data in enumerate(parts):
                if frames[i, k]:
                    lines.append(f"t{self.base_id + k:03X}{len(data)}{data.hex().upper()}\r")
        written = self.write("".join(lines).encode("ascii"), blocking)
        status = np.where(frames.all(axis=1), SENT, np.where(frames[:, TIMING], PARTIAL, DROPPED)).astype(np.uint8)
        if written < sum(len(x) for x in lines):
            status[:] = OVERRUN  # rare (host not reading for a while): whole batch marked
            frames[:] = False
        return status, frames


class PythonCanLink(Link):
    """Frames onto an in-process python-can bus (e.g. ``interface="virtual"``)."""

    name = "can"
    frames_per_sample = 4

    def __init__(self, interface: str = "virtual", channel: str = "gravcal0", base_id: int | None = None):
        self.interface, self.channel = interface, channel
        self.base_id = DEFAULT_BASE_ID if base_id is None else base_id
        self.bus = None

    @property
    def spec(self) -> str:
        return f"can://{self.interface}/{self.channel}"

    def connect(self) -> None:
        self.bus = can.Bus(interface=self.interface, channel=self.channel)

    def disconnect(self) -> None:
        if self.bus is not None:
            self.bus.shutdown()
            self.bus = None

    def send(self, samples, faults, blocking):
        n = samples.shape[0]
        frames = np.ones((n, 4), bool)
        if faults.drop:
            frames &= faults.rng.random((n, 4)) >= faults.drop
        for i, parts in enumerate(pack_frames(samples)):
            for k, data in enumerate(parts):
                if frames[i, k]:
                    self.bus.send(can.Message(arbitration_id=self.base_id + k, data=data, is_extended_id=False))
        status = np.where(frames.all(axis=1), SENT, np.where(frames[:, TIMING], PARTIAL, DROPPED)).astype(np.uint8)
        return status, frames
