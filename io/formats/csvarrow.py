"""The fast path of a CSV recording: pyarrow's CSV parser on every core, into float64 columns (``t``,
the (N, 3) triad, any optional channel) that hold nothing twice.

A plain file is cut at line ends into one byte range per core; each thread parses its range in
segments of SEGMENT_BYTES (pyarrow works without the GIL) into its own columns, and the ranges are
then joined in order. A gzip file is one stream, parsed by one thread. Memory stays near the
output's size: each segment's bytes and Arrow arrays are dropped once copied; columns live in
anonymous memory maps that grow and shrink in place (mremap: no page copied or written, and
capacity not yet written costs no RSS); a range is moved into the first one from its end, a piece
at a time, its map shrinking as it goes.

Only clean files take this path. Anything pyarrow will not convert (text in a number, a line with
too few or too many fields, a comment line with delimiters in it, quoting) raises :class:`Fallback`,
and csvtext reads the file the exact way instead, which names the line and column. Plain ``#``
comment lines and blank lines are skipped here too.
"""
from __future__ import annotations

import codecs
import gzip
import math
import mmap
import os
import sys
import zlib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

SEGMENT_BYTES = 32 << 20
"""Bytes parsed at a time by one thread: its bytes and arrays (~1.8x) are all a thread holds besides
its columns."""
BLOCK_BYTES = 4 << 20  # pyarrow's block within a segment: its parse buffers stay in the cache
MAX_THREADS = 8
MOVE_ROWS = 1 << 20  # rows moved at a time when the ranges are joined
TRIAD = ("ax", "ay", "az")


class Fallback(Exception):
    """The file is not one this reader takes as it is: read it the exact way."""


def available() -> bool:
    try:
        import pyarrow.csv  # noqa: F401
    except ImportError:
        return False
    return True


def _utf8(data) -> bool:
    """Whether ``data`` is UTF-8 text (ASCII first: one pass over the bytes, 0.2-2 % of parsing them)."""
    if not len(data) or int(np.frombuffer(data, np.uint8).max()) < 0x80:
        return True
    try:
        codecs.utf_8_decode(data, "strict", True)
    except UnicodeDecodeError:
        return False
    return True


def _skip_comment(row) -> str:
    """pyarrow's invalid-row handler: a ``#`` comment line is skipped, any other odd line is an error."""
    return "skip" if row.text.lstrip().startswith("#") else "error"


_NORESERVE = getattr(mmap, "MAP_NORESERVE", 0x4000 if sys.platform.startswith("linux") else 0)


class _Growable:
    """A float64 array of ``width`` columns in an anonymous memory map: it grows and shrinks with mremap,
    which moves no page and writes none (``ndarray.resize`` would zero-fill the new rows, touching them),
    and rows not yet written cost no RSS."""

    def __init__(self, rows: int, width: int) -> None:
        self.width = width
        self.mm = mmap.mmap(-1, self._bytes(rows), flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | _NORESERVE)

    def _bytes(self, rows: int) -> int:
        return max(rows, 1) * self.width * 8

    def view(self) -> np.ndarray:
        a = np.frombuffer(self.mm, dtype=np.float64)
        return a.reshape(-1, self.width) if self.width > 1 else a

    def resize(self, rows: int) -> None:
        self.mm.resize(self._bytes(rows))  # no view of it may be alive


class _Columns:
    """t, the (N, 3) triad and the other wanted channels, grown in place as segments arrive."""

    def __init__(self, others: list[str], capacity: int = 0) -> None:
        self.capacity = max(int(capacity), 1024)
        self.n = 0
        self.store = {"t": _Growable(self.capacity, 1), "_triad": _Growable(self.capacity, 3),
                      **{c: _Growable(self.capacity, 1) for c in others}}

    def resize(self, cap: int) -> None:
        for g in self.store.values():
            g.resize(cap)
        self.capacity = cap

    def add(self, table, picked: dict[str, str]) -> None:
        k = table.num_rows
        if self.n + k > self.capacity:
            self.resize(max(self.n + k, int(self.capacity * 1.5)))
        for c, g in self.store.items():
            into = g.view()
            if c == "_triad":
                for j, axis in enumerate(TRIAD):
                    _put(into[:, j], self.n, table.column(picked[axis]))
            else:
                _put(into, self.n, table.column(picked[c]))
            del into
        self.n += k

    def append_moving(self, more: "_Columns") -> None:
        """Append ``more``'s rows, moving them from its end a piece at a time and shrinking it as they go."""
        n0, total = self.n, self.n + more.n
        if total > self.capacity:
            self.resize(total)
        end = more.n
        while end > 0:
            start = max(0, end - MOVE_ROWS)
            for c, g in self.store.items():
                into, src = g.view(), more.store[c].view()
                into[n0 + start:n0 + end] = src[start:end]
                del into, src
            more.resize(start)
            end = start
        self.n = total

    def finish(self) -> dict[str, np.ndarray]:
        self.resize(self.n)
        cols = {c: g.view()[:self.n] for c, g in self.store.items()}
        for j, c in enumerate(TRIAD):
            cols[c] = cols["_triad"][:, j]
        return cols


def _put(into: np.ndarray, at: int, column) -> None:
    """Copy an Arrow float64 column into ``into`` from row ``at``, chunk by chunk (each a view when it
    has no nulls); an empty field (null) is NaN, which the NaN policy handles."""
    for chunk in column.chunks:
        k = len(chunk)
        into[at:at + k] = chunk.to_numpy(zero_copy_only=False)
        at += k


def _data_offset(head: bytes, header_line: int, head_bytes: int) -> int:
    """The byte offset just past the first ``header_line`` lines of ``head`` (at most ``head_bytes`` read;
    lines end in \\n, \\r\\n or \\r, as the text reader that found the header counts them)."""
    lines = head.splitlines(keepends=True)
    cut = sum(len(x) for x in lines[:header_line])
    if len(lines) < header_line or (len(head) >= head_bytes and cut >= len(head) - 1):
        raise Fallback("the header ends past the bytes read for it")  # multi-byte text in many comment lines
    return cut


class _Parser:
    def __init__(self, delim: str, n_fields: int, usecols: list[int], wanted: list[str]) -> None:
        import pyarrow as pa
        import pyarrow.csv as pacsv

        names = [f"f{i}" for i in range(n_fields)]
        self.picked = {c: names[j] for c, j in zip(wanted, usecols)}
        self.others = [c for c in wanted if c != "t" and c not in TRIAD]
        self.read = pacsv.ReadOptions(column_names=names, block_size=BLOCK_BYTES, use_threads=False)
        self.parse = pacsv.ParseOptions(delimiter=delim, quote_char=False, invalid_row_handler=_skip_comment)
        self.convert = pacsv.ConvertOptions(include_columns=list(self.picked.values()),
                                            column_types={p: pa.float64() for p in self.picked.values()},
                                            null_values=[""], strings_can_be_null=False, check_utf8=False)
        self.errors = (pa.ArrowException, OSError, EOFError, zlib.error)  # damaged gzip data too

    def segment(self, data: bytes, into: _Columns | None, expected_bytes: int) -> _Columns:
        import pyarrow as pa
        import pyarrow.csv as pacsv

        if not _utf8(data):  # pyarrow cannot hand such an odd line to _skip_comment: it prints a traceback
            raise Fallback("not UTF-8 text")
        table = pacsv.read_csv(pa.py_buffer(data), read_options=self.read, parse_options=self.parse,
                               convert_options=self.convert)
        if into is None:  # capacity from the first segment's bytes per row
            into = _Columns(self.others, math.ceil(1.05 * expected_bytes * table.num_rows / max(len(data), 1)) + 1024)
        into.add(table, self.picked)
        return into

    def stream(self, readinto, expected_bytes: int, rest: bytes = b"") -> _Columns:
        """Parse what ``readinto(buffer)`` fills, in segments ending at line ends. One buffer is read into
        again and again: a fresh one per segment would cost its pages' faults and zeroing every time."""
        cols = None
        buf = bytearray(min(SEGMENT_BYTES, max(1 << 16, expected_bytes + 1)))  # 32 MiB zeroed: ~10-70 ms a file
        whole = memoryview(buf)
        while True:
            k = readinto(whole)
            if not k:
                if rest:
                    cols = self.segment(rest, cols, expected_bytes)
                return cols if cols is not None else _Columns(self.others)
            cut = buf.rfind(b"\n", 0, k)
            if cut < 0:
                if len(rest) + k > 4 * SEGMENT_BYTES:
                    raise Fallback("no line end in a whole segment")  # e.g. lines ending in \r alone
                rest += whole[:k]
                continue
            first = 0
            if rest:  # the line cut at the last segment's end, completed: parsed on its own (short)
                first = buf.find(b"\n", 0, k) + 1
                cols = self.segment(rest + whole[:first], cols, expected_bytes)
            if cut >= first:
                cols = self.segment(whole[first:cut + 1], cols, expected_bytes)  # parsed where it was read
            rest = bytes(whole[cut + 1:k])


def _range_reader(path: Path, start: int, stop: int):
    fd = os.open(path, os.O_RDONLY)
    pos = [start]

    def readinto(view: memoryview) -> int:
        k = min(len(view), stop - pos[0])
        if k <= 0:
            return 0
        got = os.preadv(fd, [view[:k]], pos[0])
        pos[0] += got
        return got
    return fd, readinto


def _split_points(path: Path, start: int, size: int, parts: int) -> list[int]:
    """``parts`` + 1 offsets from ``start`` to ``size``, each after a line end."""
    points = [start]
    with open(path, "rb") as f:
        for k in range(1, parts):
            f.seek(max(points[-1], start + (size - start) * k // parts))
            f.readline()  # to the next line end
            pos = f.tell()
            if pos >= size:
                break
            points.append(pos)
    return points + [size]


def read_columns(path: Path, *, gz: bool, delim: str, n_fields: int, usecols: list[int], wanted: list[str],
                 header_line: int, head_bytes: int) -> dict[str, np.ndarray]:
    """The wanted columns (by field index ``usecols``) of the data after line ``header_line`` (found in
    the first ``head_bytes``), as float64 (``_triad``: the (N, 3) ax, ay, az; ``ax``, ``ay``, ``az``: its
    column views). Raises Fallback."""
    parser = _Parser(delim, n_fields, usecols, wanted)
    size = path.stat().st_size
    try:
        if gz:
            with gzip.open(path, "rb") as raw:
                head = raw.read(head_bytes)
                cut = _data_offset(head, header_line, head_bytes)
                cols = parser.stream(raw.readinto, 8 * size, rest=head[cut:])  # numbers gzip ~4-8x; more grows
            return cols.finish()
        with open(path, "rb") as f:
            start = _data_offset(f.read(head_bytes), header_line, head_bytes)
        threads = max(1, min(MAX_THREADS, os.cpu_count() or 1, (size - start) // SEGMENT_BYTES))
        points = _split_points(path, start, size, threads)

        def one(k: int) -> _Columns:
            fd, readinto = _range_reader(path, points[k], points[k + 1])
            try:
                return parser.stream(readinto, points[k + 1] - points[k])
            finally:
                os.close(fd)

        if len(points) == 2:
            parts = [one(0)]
        else:
            with ThreadPoolExecutor(len(points) - 1) as pool:
                parts = list(pool.map(one, range(len(points) - 1)))
    except parser.errors as exc:
        raise Fallback(str(exc)) from None
    cols = parts.pop(0)
    while parts:
        cols.append_moving(parts.pop(0))
    return cols.finish()
