"""A client's bounded queue of encoded lines: the oldest go first when it is full, and are counted."""
from __future__ import annotations


class OutputQueue:
    """A client's output queue, bounded in messages and in bytes; the oldest are dropped beyond either.

    The queued lines are one ``bytearray``, each message one line ending in b"\\n": queueing a block is one
    C-level append, dropping the oldest is a search for a newline and a deletion from the front (amortised
    constant in CPython: the buffer's start moves, and it is compacted and shrunk once less than half of it is
    in use). No Python object is kept per message or per block: a departed slow client's queue is one
    allocation that goes back whole (large ones are malloc's own mmaps, or trimmed by the server), where
    tens of thousands of small objects would leave pymalloc's arenas part-used and resident. The byte count
    is the bytes queued; the buffer holds at most about twice that (its free front and growth margin).
    """

    __slots__ = ("buf", "size", "limit", "max_bytes")

    def __init__(self, limit: int, max_bytes: int | None = None):
        self.buf = bytearray()
        self.size = 0  # messages queued
        self.limit = int(limit)
        self.max_bytes = int(max_bytes) if max_bytes is not None else None

    def __len__(self) -> int:
        return self.size

    @property
    def nbytes(self) -> int:
        """Bytes queued."""
        return len(self.buf)

    def clear(self) -> None:
        """Drop everything and release the buffer (a departing client)."""
        self.buf = bytearray()
        self.size = 0

    def put(self, lines: list[bytes], joined: bytes | None = None) -> int:
        """Queue ``lines`` (``joined`` = b"".join(lines) if already at hand); as :meth:`put_joined`."""
        if not lines:
            return 0
        return self.put_joined(b"".join(lines) if joined is None else joined, len(lines))

    def put_joined(self, data: bytes, n: int) -> int:
        """Queue ``n`` messages, ``data`` (whole lines); returns how many of the oldest queued messages were
        dropped to stay within the limits."""
        if n <= 0:
            return 0
        buf = self.buf
        buf += data
        self.size += n
        excess_msgs = self.size - self.limit
        excess_bytes = len(buf) - self.max_bytes if self.max_bytes is not None else 0
        if excess_msgs <= 0 and excess_bytes <= 0:
            return 0
        cut = buf.find(b"\n", excess_bytes - 1) + 1 if excess_bytes > 0 else 0  # whole messages covering the bytes
        if excess_msgs > 0:
            pos = -1
            for _ in range(excess_msgs):  # at most a block's messages beyond a full queue
                pos = buf.find(b"\n", pos + 1)
            cut = max(cut, pos + 1)
        lost = buf.count(b"\n", 0, cut)
        del buf[:cut]
        self.size -= lost
        return lost

    def take(self, max_bytes: int) -> tuple[list[bytes], int]:
        """Whole lines, oldest first, about ``max_bytes`` (at least one line): ([the bytes], messages)."""
        buf = self.buf
        if not buf:
            return [], 0
        if len(buf) <= max_bytes:
            data, n = bytes(buf), self.size
            self.clear()
            return [data], n
        cut = buf.rfind(b"\n", 0, max_bytes) + 1 or buf.find(b"\n") + 1
        with memoryview(buf) as view:
            data = bytes(view[:cut])
        del buf[:cut]
        n = data.count(b"\n")
        self.size -= n
        return [data], n
