"""A fixed-capacity ring buffer of structured numpy rows.

Acquisition pushes blocks, processing pops them. It never grows: when full, a push
overwrites the oldest rows and counts them in ``overwritten``, so a slow consumer loses
the oldest data (counted, reported) rather than blocking the driver or exhausting memory.
"""
from __future__ import annotations

import threading

import numpy as np

from .samples import SAMPLE_DTYPE


class RingBuffer:
    """Fixed-capacity FIFO of rows of ``dtype`` (default: the sample layout).

    Thread-safe for one producer and any number of consumers.
    """

    def __init__(self, capacity: int, dtype: np.dtype = SAMPLE_DTYPE):
        if int(capacity) <= 0:
            raise ValueError(f"ring buffer capacity must be positive, got {capacity}")
        self.capacity = int(capacity)
        self.dtype = np.dtype(dtype)
        self._data = np.zeros(self.capacity, dtype=self.dtype)
        self._head = 0  # index of the oldest row
        self._size = 0
        self._lock = threading.Lock()
        self.pushed = 0  # rows ever pushed
        self.popped = 0  # rows ever popped
        self.overwritten = 0  # rows lost because the buffer was full

    def __len__(self) -> int:
        return self._size

    @property
    def free(self) -> int:
        return self.capacity - self._size

    def push(self, block: np.ndarray) -> int:
        """Append rows; overwrite the oldest when full. Returns how many old rows were lost."""
        block = np.asarray(block)
        if block.dtype != self.dtype:
            raise TypeError(f"ring buffer holds {self.dtype}, got {block.dtype}")
        n = block.shape[0]
        if n == 0:
            return 0
        with self._lock:
            lost = 0
            if n >= self.capacity:
                # Only the newest `capacity` rows of the block can survive.
                lost = self._size + n - self.capacity
                self._data[:] = block[n - self.capacity :]
                self._head = 0
                self._size = self.capacity
            else:
                lost = max(0, self._size + n - self.capacity)
                if lost:
                    self._head = (self._head + lost) % self.capacity
                    self._size -= lost
                tail = (self._head + self._size) % self.capacity
                first = min(n, self.capacity - tail)
                self._data[tail : tail + first] = block[:first]
                if first < n:
                    self._data[: n - first] = block[first:]
                self._size += n
            self.pushed += n
            self.overwritten += lost
            return lost

    def _copy_out(self, n: int) -> np.ndarray:
        first = min(n, self.capacity - self._head)
        out = np.empty(n, dtype=self.dtype)
        out[:first] = self._data[self._head : self._head + first]
        if first < n:
            out[first:] = self._data[: n - first]
        return out

    def pop(self, max_rows: int | None = None) -> np.ndarray:
        """Remove and return up to ``max_rows`` oldest rows (all when None), as a copy."""
        with self._lock:
            n = self._size if max_rows is None else max(0, min(int(max_rows), self._size))
            out = self._copy_out(n)
            self._head = (self._head + n) % self.capacity
            self._size -= n
            self.popped += n
            return out

    def peek(self, max_rows: int | None = None) -> np.ndarray:
        """Return up to ``max_rows`` oldest rows without removing them (a copy)."""
        with self._lock:
            n = self._size if max_rows is None else max(0, min(int(max_rows), self._size))
            return self._copy_out(n)

    def latest(self, n: int = 1) -> np.ndarray:
        """The newest ``n`` rows (fewer if the buffer holds fewer), oldest first."""
        with self._lock:
            n = max(0, min(int(n), self._size))
            start = (self._head + self._size - n) % self.capacity
            first = min(n, self.capacity - start)
            out = np.empty(n, dtype=self.dtype)
            out[:first] = self._data[start : start + first]
            if first < n:
                out[first:] = self._data[: n - first]
            return out

    def clear(self) -> None:
        with self._lock:
            self.popped += self._size
            self._head = 0
            self._size = 0

    def stats(self) -> dict[str, int]:
        return {
            "capacity": self.capacity,
            "size": self._size,
            "pushed": self.pushed,
            "popped": self.popped,
            "overwritten": self.overwritten,
        }
