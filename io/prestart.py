"""`gravcal calibrate FILE.npy`: the block statistics' memory faulted in while the interpreter imports.

The reading pass (core.datapass) writes ~50 bytes of block statistics per block (mean, scatter,
aux means, usable: ~290 MB for a week at 100 Hz). Fresh anonymous memory is zeroed by the kernel on
its first write, and in the pass that happens inside its two reading threads (0.1-0.7 s of system
time on the week, at this VM's zeroing rate of well under 1 GB/s). Their size is known from the
file's header and a few of its first time stamps, before numpy is even imported; and while the
interpreter imports numpy and gravcal (~0.25 s) one core is idle. So ``start`` (called by
cli/main.py ``console`` before anything imports numpy) maps that memory and a background thread
faults it in (io/_pages.c ``populate``, GIL released) in the order the pass will write it;
``claim`` hands it to the reading pass as its output arrays. The pass never waits: a page the thread
has not reached yet is faulted in by the pass's write as before, and either way the arrays' values
are what the pass writes (every element is written; nothing is read before).

Only the plain case is prepared: one structured .npy (a little-endian float64 t field), no --columns
mapping, not a --lab session, no supply-voltage field (those read without block statistics). The
block length is a guess from the first 4 096 time steps; when the pass's own sample rate gives
another one (an irregular start), the arrays do not match and the pass allocates its own.
This module imports no numpy until ``claim``'s arrays are made.
"""
from __future__ import annotations

import ast
import math
import mmap
import os
import struct
import threading
from pathlib import Path
from typing import Any, Callable, Sequence

BLOCK_S = 0.1  # core.fastdetect.BLOCK_S (not imported: it loads numpy; tests/daemon/test_prestart.py checks they agree)
GUESS_ROWS = 4097  # time stamps read for the block length's guess
POPULATE_BLOCKS = 1 << 16  # blocks per populate call and row: the pass's 16 chunks of 4 096 blocks
ALIGN = 4096
HEADER_MAX = 1 << 16  # bytes of .npy header read at most

# `gravcal calibrate`'s options as the prestart reads its command line (tests check them against the parser)
GLOBAL_FLAGS = frozenset({"-v", "-vv", "-vvv", "--verbose", "--debug"})
VALUE_OPTIONS = frozenset({"--columns", "--out", "--workers", "--scheduler", "--model", "--lab-calibration",
                           "--detector", "--folds", "--start", "--save", "--write", "--write-dir", "--write-format",
                           "--report"})
FLAG_OPTIONS = frozenset({"--quiet", "--lab", "--json", "--no-saturation-check"})
# no block statistics, or a study
NOT_PREPARED = frozenset({"--columns", "--lab", "--out", "--workers", "--scheduler", "--write-dir", "--report"})

_pending: list["Arena"] = []  # at most one: the arena ``start`` prepared, until ``claim`` takes it


def calibrate_file(argv: Sequence[str]) -> Path | None:
    """The one recording of a plain ``gravcal calibrate FILE [options]`` command line, else None (any
    option it does not know, a study, a mapping or a lab session: nothing is prepared)."""
    args = list(argv)
    while args and args[0] in GLOBAL_FLAGS:
        args.pop(0)
    if not args or args[0] != "calibrate":
        return None
    files: list[str] = []
    i = 1
    while i < len(args):
        a = args[i]
        name = a.split("=", 1)[0]
        if a == "--":
            files += args[i + 1:]
            break
        if name in NOT_PREPARED:
            return None
        if a.startswith("-"):
            if name in VALUE_OPTIONS:
                i += 1 if "=" in a else 2
                continue
            if a not in FLAG_OPTIONS:
                return None
        else:
            files.append(a)
        i += 1
    return Path(files[0]) if len(files) == 1 else None


def _field_size(typestr: Any, shape: Any = ()) -> int | None:
    if not isinstance(typestr, str) or len(typestr) < 3 or typestr[1] not in "fiubcV" or not typestr[2:].isdigit():
        return None
    count = 1
    for s in (shape if isinstance(shape, tuple) else (shape,)):
        if not isinstance(s, int) or s < 0:
            return None
        count *= s
    return int(typestr[2:]) * count


def npy_layout(path: Path) -> tuple[int, int, int, dict[str, tuple[str, int]]] | None:
    """(rows, byte offset of row 0, record size, {field: (type string, offset in the record)}) of a
    one-dimensional structured .npy with plain fields, read without numpy; None for anything else."""
    try:
        with open(path, "rb") as f:
            head = f.read(HEADER_MAX)
    except OSError:
        return None
    if head[:6] != b"\x93NUMPY" or len(head) < 10:
        return None
    major = head[6]
    if major == 1:
        (hlen,), start = struct.unpack_from("<H", head, 8), 10
    elif major in (2, 3):
        if len(head) < 12:
            return None
        (hlen,), start = struct.unpack_from("<I", head, 8), 12
    else:
        return None
    if start + hlen > len(head):
        return None
    try:
        header = ast.literal_eval(head[start:start + hlen].decode("latin1"))
    except (ValueError, SyntaxError, MemoryError, RecursionError):
        return None
    if not isinstance(header, dict) or header.get("fortran_order") is not False:
        return None
    shape, descr = header.get("shape"), header.get("descr")
    if not (isinstance(shape, tuple) and len(shape) == 1 and isinstance(shape[0], int) and isinstance(descr, list)):
        return None
    fields: dict[str, tuple[str, int]] = {}
    offset = 0
    for entry in descr:
        if not (isinstance(entry, tuple) and len(entry) in (2, 3) and isinstance(entry[0], str)):
            return None
        size = _field_size(*entry[1:])
        if size is None:
            return None
        fields[entry[0]] = (entry[1], offset)
        offset += size
    return shape[0], start + hlen, offset, fields


def guess_block_n(path: Path, n: int, data_offset: int, itemsize: int, t_offset: int) -> int | None:
    """The block length core.fastdetect.block_length gives for the sample rate of the first GUESS_ROWS
    time stamps' median step (float64 little-endian t); None when they give none."""
    rows = min(n, GUESS_ROWS)
    try:
        fd = os.open(path, os.O_RDONLY)
        try:
            data = os.pread(fd, rows * itemsize, data_offset)
        finally:
            os.close(fd)
    except OSError:
        return None
    rows = len(data) // itemsize
    t = [struct.unpack_from("<d", data, i * itemsize + t_offset)[0] for i in range(rows)]
    steps = sorted(b - a for a, b in zip(t, t[1:]))
    if not steps:
        return None
    m = len(steps) // 2
    step = steps[m] if len(steps) % 2 else 0.5 * (steps[m - 1] + steps[m])
    if not (math.isfinite(step) and step > 0):
        return None
    fs = float(f"{1.0 / step:.9g}")  # as core.datapass.fs_from rounds it (FS_DIGITS)
    return max(1, int(round(BLOCK_S * fs)))  # as block_length(fs)


class Arena:
    """Anonymous memory laid out as core.fastdetect.BlockPass's arrays for ``nb`` blocks and ``k`` aux
    channels, faulted in by a background thread in the pass's order (block ranges, every array)."""

    def __init__(self, key: tuple[int, ...], nb: int, k: int):
        self.key, self.nb = key, nb
        # (shape, dtype string) -> byte offset, in the order BlockPass asks for them
        self.parts: list[tuple[tuple[int, ...], str, int, int]] = []  # shape, dtype, offset, item size
        size = 0
        for shape, dtype, item in (((3, nb), "<f8", 8), ((6, nb), "<f4", 4), ((k, nb), "<f8", 8), ((nb,), "|b1", 1)):
            self.parts.append((shape, dtype, size, item))
            rows = shape[0] if len(shape) == 2 else 1
            size += -(-rows * nb * item // ALIGN) * ALIGN
        # private: shared anonymous memory (mmap's default) is shmem, without transparent huge pages
        self.mm = mmap.mmap(-1, max(size, 1), flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
        if hasattr(mmap, "MADV_HUGEPAGE"):  # as numpy asks for its large arrays
            self.mm.madvise(mmap.MADV_HUGEPAGE)
        self.given: set[int] = set()
        self.populated: bool | None = None  # populate's answer (False: the kernel lacks MADV_POPULATE_WRITE)
        self.thread = threading.Thread(target=self._populate, name="gravcal-prestart", daemon=True)

    def _populate(self) -> None:
        ok = True
        try:
            from ..core.accelerator import kernels

            populate = kernels("gravcal.io._pages").populate

            for lo in range(0, self.nb, POPULATE_BLOCKS):
                hi = min(lo + POPULATE_BLOCKS, self.nb)
                for shape, _, offset, item in self.parts:
                    for r in range(shape[0] if len(shape) == 2 else 1):
                        ok = populate(self.mm, offset + (r * self.nb + lo) * item, (hi - lo) * item) and ok
                if not ok:
                    break
        except (ImportError, OSError):  # no helper built, or no memory now: the pass's writes fault the pages in
            ok = False
        self.populated = ok

    def allocate(self, shape: tuple[int, ...], dtype: Any) -> Any:
        """An array of ``shape`` and ``dtype`` in this memory when it is one of the prepared ones (each
        once), else a fresh np.empty."""
        import numpy as np

        dt = np.dtype(dtype)
        for i, (s, d, offset, _) in enumerate(self.parts):
            if i not in self.given and tuple(shape) == s and dt == np.dtype(d):
                self.given.add(i)
                count = 1
                for x in s:
                    count *= x
                return np.frombuffer(self.mm, dtype=dt, count=count, offset=offset).reshape(s)
        return np.empty(shape, dtype=dt)


def _key(path: Path) -> tuple[int, ...] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns


def prepare(path: Path) -> Arena | None:
    """The arena for ``path`` when it is a plain structured .npy the reading pass will compute block
    statistics for (its population started), else None."""
    key = _key(path)
    layout = npy_layout(path) if key is not None else None
    if layout is None:
        return None
    n, data_offset, itemsize, fields = layout
    lower = {name.lower(): name for name in fields}
    if "vsupply" in lower or not all(c in lower for c in ("t", "ax", "ay", "az")):
        return None
    t_type, t_offset = fields[lower["t"]]
    if t_type != "<f8" or n * itemsize + data_offset > key[2]:
        return None
    block_n = guess_block_n(path, n, data_offset, itemsize, t_offset)
    if block_n is None or n // block_n == 0:
        return None
    try:
        arena = Arena(key, n // block_n, 1 if "temp" in lower else 0)
        arena.thread.start()
    except (OSError, ValueError, OverflowError, RuntimeError):  # no memory or no thread: the pass allocates
        return None
    return arena


def start(argv: Sequence[str]) -> bool:
    """Prepare the arena of a plain ``gravcal calibrate FILE.npy`` command line (``console``, before
    numpy loads). True when one was prepared."""
    path = calibrate_file(argv)
    arena = prepare(path) if path is not None else None
    _pending[:] = [arena] if arena is not None else []
    return arena is not None


def claim(path: str | Path) -> Callable[[tuple[int, ...], Any], Any] | None:
    """The prepared arena's allocator for the reading pass of ``path`` (the same file, unchanged since),
    once; None when none was prepared for it."""
    if not _pending:
        return None
    arena = _pending[0]
    if _key(Path(path)) != arena.key:
        return None
    _pending.clear()
    return arena.allocate
