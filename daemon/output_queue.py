"""A client's bounded queue of encoded lines: the oldest go first when it is full, and are counted."""
from __future__ import annotations

import collections


class OutputQueue:
    """A client's output queue, bounded in messages and in bytes; the oldest are dropped beyond either.

    Entries are runs of encoded lines ``[lines, start, joined, nbytes]``: a block's IMU lines are
    encoded once and the same list (and, for full-rate clients, the same pre-joined bytes) is
    queued for every client, so queueing and sending cost one C-level join per block and
    client, never a Python step per line. Dropping a part of a run advances ``start`` (and lets its
    joined copy go). The byte count is what this queue would hold on its own: the lines, plus the
    joined copy while it is kept (shared lines are counted for every client), so
    ``max_clients * max_bytes`` bounds the daemon's queued memory.
    """

    __slots__ = ("entries", "size", "nbytes", "limit", "max_bytes")

    def __init__(self, limit: int, max_bytes: int | None = None):
        self.entries: collections.deque = collections.deque()
        self.size = 0  # messages queued
        self.nbytes = 0  # bytes queued
        self.limit = int(limit)
        self.max_bytes = int(max_bytes) if max_bytes is not None else None

    def __len__(self) -> int:
        return self.size

    def _over(self) -> tuple[int, int]:
        """(messages, bytes) above the limits."""
        extra_bytes = self.nbytes - self.max_bytes if self.max_bytes is not None else 0
        return max(0, self.size - self.limit), max(0, extra_bytes)

    def put(self, lines: list[bytes], joined: bytes | None = None) -> int:
        """Queue ``lines`` (``joined`` = b"".join(lines) if already at hand); returns how many
        of the oldest queued messages were dropped to stay within the limits."""
        n = len(lines)
        if n == 0:
            return 0
        size = 2 * len(joined) if joined is not None else sum(map(len, lines))  # the lines and their joined copy
        self.entries.append([lines, 0, joined, size])
        self.size += n
        self.nbytes += size
        lost = 0
        excess_msgs, excess_bytes = self._over()
        while excess_msgs or excess_bytes:
            e = self.entries[0]
            avail = len(e[0]) - e[1]
            if avail <= excess_msgs or e[3] <= excess_bytes:
                self.entries.popleft()
                drop, drop_bytes = avail, e[3]
            else:  # part of the oldest run: its joined copy, and enough of its first lines to cover both excesses
                freed = len(e[2]) if e[2] is not None else 0
                drop, drop_bytes = excess_msgs, sum(map(len, e[0][e[1]:e[1] + excess_msgs]))
                while drop_bytes + freed < excess_bytes:
                    drop_bytes += len(e[0][e[1] + drop])
                    drop += 1
                e[1] += drop
                e[2] = None
                drop_bytes += freed
                e[3] -= drop_bytes
            self.size -= drop
            self.nbytes -= drop_bytes
            lost += drop
            excess_msgs, excess_bytes = self._over()
        return lost

    def take(self, max_bytes: int) -> tuple[list[bytes], int]:
        """Whole runs, oldest first, until about ``max_bytes``: (byte strings, messages)."""
        out: list[bytes] = []
        n = size = held = 0
        entries = self.entries
        while entries and size < max_bytes:
            lines, start, joined, nbytes = entries.popleft()
            data = joined if joined is not None else b"".join(lines[start:] if start else lines)
            out.append(data)
            n += len(lines) - start
            size += len(data)
            held += nbytes
        self.size -= n
        self.nbytes -= held
        return out, n
