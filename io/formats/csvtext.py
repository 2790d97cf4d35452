"""CSV (plain or gzip-compressed) recordings: a header row naming the columns, one sample per line.

Reads are bounded where a file could be anything: the header search reads at most MAX_HEADER_BYTES,
a line longer than MAX_LINE_CHARS is refused, and messages quote the file only through
:func:`~.sniff.excerpt`.
"""
from __future__ import annotations

import csv
import gzip
import io
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Iterator

import numpy as np

from ...errors import InputError
from . import csvarrow
from .sniff import excerpt

REQUIRED = ("t", "ax", "ay", "az")
OPTIONAL = ("gx", "gy", "gz", "temp", "vsupply")
MAX_HEADER_BYTES = 1 << 20  # comment lines plus the header row
MAX_LINE_CHARS = 1 << 16  # no sample line of a recording is this long
MAX_NAMES_SHOWN = 12


def open_text(path: Path, gz: bool) -> IO[str]:
    raw = gzip.open(path, "rb") if gz else open(path, "rb")
    return io.TextIOWrapper(raw, encoding="utf-8-sig", errors="replace", newline="")


class _BoundedLines(io.TextIOBase):
    """A text stream np.loadtxt reads through, refusing a line longer than MAX_LINE_CHARS before it
    is held whole: without it one endless 'line' of garbage costs many times its size in memory."""

    def __init__(self, f: IO[str], path: Path) -> None:
        self._f, self._path, self._run = f, path, 0

    def _refuse(self, start: str) -> InputError:
        return InputError(f"{self._path}: a line is longer than {MAX_LINE_CHARS} characters (starts "
                          f"{excerpt(start)}): not a CSV recording")

    def readable(self) -> bool:
        return True

    def readline(self, size: int = -1) -> str:
        line = self._f.readline(MAX_LINE_CHARS + 1)
        if len(line) > MAX_LINE_CHARS:
            raise self._refuse(line)
        return line

    def read(self, size: int = -1) -> str:
        data = self._f.read(size if size and size > 0 else 1 << 20)
        cut = data.rfind("\n")
        self._run = self._run + len(data) if cut < 0 else len(data) - cut - 1
        if self._run > MAX_LINE_CHARS:
            raise self._refuse(data[cut + 1:] if cut >= 0 else data)
        return data


def parse_columns(spec: str | dict[str, str] | None) -> dict[str, str]:
    """``"t=t_unix,ax=x_counts"`` (or a dict) -> {gravcal name: the file's column name}."""
    if not spec:
        return {}
    pairs = spec.items() if isinstance(spec, dict) else (p.partition("=")[::2] for p in spec.split(",") if p.strip())
    out: dict[str, str] = {}
    for ours, theirs in pairs:
        ours, theirs = str(ours).strip().lower(), str(theirs).strip()
        if ours not in REQUIRED + OPTIONAL:
            raise InputError(f"--columns: unknown name {excerpt(ours, 20)}; map any of {', '.join(REQUIRED + OPTIONAL)} "
                             f"to a column of the file, e.g. t=t_unix,ax=x_counts")
        if not theirs:
            raise InputError(f"--columns: {ours}= names no column (write {ours}=<the file's column name>)")
        out[ours] = theirs
    return out


def shown_names(names: list[str]) -> str:
    """The header names for a message: sanitised, at most MAX_NAMES_SHOWN."""
    if not names:
        return "(none)"
    head = ", ".join(excerpt(n, 24)[1:-1] if excerpt(n, 24).startswith("'") else excerpt(n, 24)
                     for n in names[:MAX_NAMES_SHOWN])
    return head + (f" and {len(names) - MAX_NAMES_SHOWN} more" if len(names) > MAX_NAMES_SHOWN else "")


def missing_columns_error(path: Path, found: list[str], what: str = "column") -> InputError:
    missing = [c for c in REQUIRED if c not in found]
    return InputError(
        f"{path}: missing {what}{'s' if len(missing) > 1 else ''} {', '.join(missing)}; found: {shown_names(found)} "
        f"(need {', '.join(REQUIRED)}; optional {', '.join(OPTIONAL)}; map other names with --columns t=...,ax=...)"
    )


def apply_mapping(path: Path, names: list[str], mapping: dict[str, str]) -> list[str]:
    """Rename the file's columns per ``mapping`` (case-insensitive); a mapped column must exist."""
    names = list(names)
    for ours, theirs in mapping.items():
        key = theirs.lower()
        if key not in names:
            raise InputError(f"{path}: --columns {ours}={excerpt(theirs, 24)}: no such column; found: {shown_names(names)}")
        names = [f"_{n}" if n == ours else n for n in names]  # a column already called `ours` yields
        names[names.index(key)] = ours
    return names


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def _sniff_delimiter(header: str) -> str | None:
    for d in (",", ";", "\t"):
        if d in header:
            return d
    return None  # whitespace


def _split(line: str, delim: str | None) -> list[str]:
    if delim is None:
        return line.split()
    return next(csv.reader([line], delimiter=delim))


def _read_header(path: Path, gz: bool) -> tuple[str, int]:
    """(header text, its 1-based line number), reading at most MAX_HEADER_BYTES."""
    used = 0
    with open_text(path, gz) as f:
        lineno = 0
        while used < MAX_HEADER_BYTES:
            line = f.readline(MAX_LINE_CHARS + 1)
            lineno += 1
            if len(line) > MAX_LINE_CHARS:
                raise InputError(f"{path}: line {lineno} is longer than {MAX_LINE_CHARS} characters (starts "
                                 f"{excerpt(line)}): not a CSV recording")
            used += len(line)
            if not line or not line.lstrip().startswith("#"):
                return line, lineno
    raise InputError(f"{path}: no header row within the first {MAX_HEADER_BYTES} bytes (only comment lines)")


def load_csv(path: Path, *, gz: bool = False, mapping: dict[str, str] | None = None
             ) -> tuple[dict[str, np.ndarray], "Where", tuple[str, ...]]:
    header, header_line = _read_header(path, gz)
    if not header.strip():
        raise InputError(f"{path}: no header row (the first line is empty; expected a header like t,ax,ay,az)")
    delim = _sniff_delimiter(header)
    names = [n.strip().strip('"').strip().lower() for n in _split(header.rstrip("\r\n"), delim)]
    if names and all(_is_number(n) for n in names if n):
        raise InputError(
            f"{path}: no header row (the first line holds numbers: {excerpt(header.strip())}); "
            f"expected a header naming the columns, e.g. t,ax,ay,az"
        )
    names = apply_mapping(path, names, mapping or {})
    if any(c not in names for c in REQUIRED):
        raise missing_columns_error(path, names)
    wanted = [c for c in REQUIRED + OPTIONAL if c in names] + (["flags"] if "flags" in names else [])
    dup = [c for c in wanted if names.count(c) > 1]
    if dup:
        raise InputError(f"{path}: column {dup[0]!r} appears {names.count(dup[0])} times in the header")
    usecols = [names.index(c) for c in wanted]
    if delim is not None and csvarrow.available():
        try:
            cols = csvarrow.read_columns(path, gz=gz, delim=delim, n_fields=len(names), usecols=usecols, wanted=wanted,
                                         header_line=header_line, head_bytes=4 * MAX_HEADER_BYTES + MAX_LINE_CHARS)
        except csvarrow.Fallback:
            pass  # not a plain file of numbers: the exact path below names what is wrong
        else:
            if cols["t"].shape[0] == 0:
                raise InputError(f"{path}: empty input: a header but no samples")
            return cols, Where(path=path, csv_header_line=header_line, gz=gz), tuple(names)
    try:
        with warnings.catch_warnings(), open_text(path, gz) as f:
            warnings.simplefilter("ignore")  # "input contained no data": handled below
            data = np.loadtxt(_BoundedLines(f, path), delimiter=delim, skiprows=header_line, usecols=usecols, dtype=np.float64,
                              ndmin=2, comments="#")
    except InputError:
        raise
    except ValueError:
        # Slow path only on trouble: locate the first bad line exactly (and accept empty
        # fields as missing values, which the NaN policy then handles).
        data = _parse_slow(path, gz, delim, names, usecols, header_line)
    if data.shape[0] == 0:
        raise InputError(f"{path}: empty input: a header but no samples")
    cols = {c: np.ascontiguousarray(data[:, i]) for i, c in enumerate(wanted)}
    return cols, Where(path=path, csv_header_line=header_line, gz=gz), tuple(names)


def data_lines(path: Path, header_line: int, gz: bool = False) -> Iterator[tuple[int, str]]:
    """(line number, text) of each data line, skipping blank and comment lines like np.loadtxt."""
    with open_text(path, gz) as f:
        i = 0
        while True:
            line = f.readline(MAX_LINE_CHARS + 1)
            if not line:
                return
            i += 1
            if len(line) > MAX_LINE_CHARS:
                raise InputError(f"{path}: line {i} is longer than {MAX_LINE_CHARS} characters (starts "
                                 f"{excerpt(line)}): not a CSV recording")
            if i <= header_line:
                continue
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            yield i, line.rstrip("\r\n")


def _parse_slow(path: Path, gz: bool, delim: str | None, names: list[str], usecols: list[int],
                header_line: int) -> np.ndarray:
    rows: list[list[float]] = []
    for lineno, line in data_lines(path, header_line, gz):
        fields = _split(line, delim)
        if len(fields) <= max(usecols):
            raise InputError(
                f"{path}: line {lineno} has {len(fields)} fields, the header has {len(names)} "
                f"(column {names[max(usecols)]!r} is missing on that line)"
            )
        row = []
        for j in usecols:
            s = fields[j].strip()
            if s == "":
                row.append(math.nan)  # a missing value: handled by the NaN/inf policy
                continue
            try:
                row.append(float(s))
            except ValueError:
                raise InputError(f"{path}: line {lineno}, column {names[j]!r}: {excerpt(s)} is not a number") from None
        rows.append(row)
    return np.array(rows, dtype=np.float64).reshape(len(rows), len(usecols))


@dataclass
class Where:
    """Turns a row index into a place a user can find (CSV line number or row index)."""

    path: Path
    csv_header_line: int | None = None
    gz: bool = False

    def __call__(self, row: int) -> str:
        if self.csv_header_line is None:
            return f"row {row}"
        lineno = line_of_data_row(self.path, self.csv_header_line, self.gz, row)
        return f"line {lineno}" if lineno is not None else f"data row {row}"


_ODD_LINES = (b"#", b"\n\n", b"\n\r\n", b"\n ", b"\n\t", b"\r\r")


def line_of_data_row(path: Path, header_line: int, gz: bool, row: int, chunk: int = 1 << 24) -> int | None:
    """The 1-based line number of data row ``row`` (0-based, blank and comment lines not counted, as
    data_lines counts), by counting newlines in binary blocks: a block without comment or blank
    lines is counted whole, so a week's last line is found in about a second."""
    raw = gzip.open(path, "rb") if gz else open(path, "rb")
    with raw:
        lineno, rows, rest = 0, 0, b""
        while True:
            data = raw.read(chunk)
            if not data:
                lines = rest.splitlines()
            else:
                data = rest + data
                cut = data.rfind(b"\n")
                if cut < 0:
                    rest = data
                    continue
                whole, rest = data[:cut + 1], data[cut + 1:]
                n = whole.count(b"\n")
                if lineno >= header_line and rows + n <= row and not any(m in whole for m in _ODD_LINES) \
                        and whole[:1].strip() and whole[:1] != b"#" and whole.count(b"\r") == whole.count(b"\r\n"):
                    lineno, rows = lineno + n, rows + n  # every line of the block is a data line before the one sought
                    continue
                lines = whole.splitlines()
            for line in lines:
                lineno += 1
                if lineno <= header_line:
                    continue
                s = line.strip()
                if not s or s.startswith(b"#"):
                    continue
                if rows == row:
                    return lineno
                rows += 1
            if not data:
                return None
