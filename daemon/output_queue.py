"""A client's bounded queue of encoded lines: the oldest go first when it is full, and are counted."""
from __future__ import annotations

import collections


class OutputQueue:
    """A client's bounded output queue, in messages; the oldest are dropped beyond ``limit``.

    Entries are runs of encoded lines ``[lines, start, joined]``: a block's IMU lines are
    encoded once and the same list (and, for full-rate clients, the same pre-joined bytes) is
    queued for every client, so queueing and sending cost one C-level join per block and
    client, never a Python step per line. Dropping a part of a run advances ``start``.
    """

    __slots__ = ("entries", "size", "limit")

    def __init__(self, limit: int):
        self.entries: collections.deque = collections.deque()
        self.size = 0  # messages queued
        self.limit = int(limit)

    def __len__(self) -> int:
        return self.size

    def put(self, lines: list[bytes], joined: bytes | None = None) -> int:
        """Queue ``lines`` (``joined`` = b"".join(lines) if already at hand); returns how many
        of the oldest queued messages were dropped to stay within the limit."""
        n = len(lines)
        if n == 0:
            return 0
        self.entries.append([lines, 0, joined])
        self.size += n
        lost = 0
        while self.size > self.limit:
            e = self.entries[0]
            avail = len(e[0]) - e[1]
            excess = self.size - self.limit
            if avail <= excess:
                self.entries.popleft()
                self.size -= avail
                lost += avail
            else:
                e[1] += excess
                e[2] = None
                self.size -= excess
                lost += excess
        return lost

    def take(self, max_bytes: int) -> tuple[list[bytes], int]:
        """Whole runs, oldest first, until about ``max_bytes``: (byte strings, messages)."""
        out: list[bytes] = []
        n = size = 0
        entries = self.entries
        while entries and size < max_bytes:
            lines, start, joined = entries.popleft()
            data = joined if joined is not None else b"".join(lines[start:] if start else lines)
            out.append(data)
            n += len(lines) - start
            size += len(data)
        self.size -= n
        return out, n
