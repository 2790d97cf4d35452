"""What a file holds, from its first bytes (and a zip's member names), never from its name alone.

Every message that quotes a file goes through :func:`excerpt`: at most a short, printable, quoted
piece, so garbage input cannot flood a terminal or inject escape sequences.
"""
from __future__ import annotations

import gzip
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

HEAD_BYTES = 1 << 16
"""Bytes read to recognise a format (bounded: a 1 GB file costs the same as a 1 kB one)."""
EXCERPT_CHARS = 40

FORMATS = ("csv", "csv.gz", "npy", "parquet", "gt3x", "agdc", "cwa", "bin")
"""The recording formats ``read_recording`` accepts."""

EXTRA_FOR = {"gt3x": ("pygt3x", "formats"), "agdc": ("pygt3x", "formats"),
             "cwa": ("skdh", "formats"), "bin": ("skdh", "formats")}
"""Format -> (module its reader needs, the pip extra that installs it)."""


@dataclass(frozen=True)
class Sniffed:
    """``kind``: one of FORMATS, or "zip", "npz", "binary", "empty" (not a recording); ``what``: for the user."""

    kind: str
    what: str


def excerpt(data: bytes | str, limit: int = EXCERPT_CHARS) -> str:
    """A short, printable, quoted excerpt: control and non-ASCII characters become '?'."""
    if isinstance(data, bytes):
        data = data[: limit * 4].decode("utf-8", errors="replace")
    text = "".join(c if (c.isprintable() and c.isascii()) else "?" for c in data[:limit])
    return repr(text) + ("..." if len(data) > limit else "")


def _zip_kind(path: Path) -> Sniffed:
    try:
        with zipfile.ZipFile(path) as z:
            names = z.namelist()[:1000]
    except Exception:  # noqa: BLE001 - zipfile's directory parser: BadZipFile, NotImplementedError (a version
        return Sniffed("binary", "a damaged zip archive")  # or method it lacks), OSError, ValueError, ...
    if "info.txt" in names and ("log.bin" in names or "activity.bin" in names):
        if path.suffix.lower() == ".agdc":
            return Sniffed("agdc", "an ActiGraph .agdc file")
        return Sniffed("gt3x", "an ActiGraph .gt3x file")
    if names and all(n.endswith(".npy") for n in names):
        return Sniffed("npz", "a NumPy .npz archive")
    shown = ", ".join(excerpt(n, 24) for n in names[:5]) or "(no members)"
    return Sniffed("zip", f"a zip archive that is no ActiGraph file (members: {shown})")


def _looks_binary(head: bytes) -> bool:
    if not head:
        return False
    if b"\x00" in head:
        return True
    text = head.decode("utf-8", errors="replace")
    odd = sum(1 for c in text if c == "\ufffd" or (not c.isprintable() and c not in "\r\n\t"))
    return odd > 0.05 * len(text)


def sniff(path: Path) -> Sniffed:
    """Recognise ``path`` by content (bounded read)."""
    with open(path, "rb") as f:
        head = f.read(HEAD_BYTES)
    if not head:
        return Sniffed("empty", "an empty file")
    if head.startswith(b"\x93NUMPY"):
        return Sniffed("npy", "a NumPy .npy file")
    if head.startswith(b"PAR1"):
        return Sniffed("parquet", "an Apache Parquet file")
    if head.startswith(b"PK\x03\x04") or head.startswith(b"PK\x05\x06"):
        return _zip_kind(path)
    if head.startswith(b"\x1f\x8b"):
        try:
            with gzip.open(path, "rb") as g:
                inner = g.read(4096)
        except (OSError, EOFError, gzip.BadGzipFile, zlib.error):  # zlib.error: a damaged deflate stream
            return Sniffed("binary", "a damaged gzip file")
        if _looks_binary(inner):
            return Sniffed("binary", "a gzip file holding binary data, not a CSV")
        return Sniffed("csv.gz", "a gzip-compressed CSV")
    if head[:2] == b"MD" and len(head) >= 4 and int.from_bytes(head[2:4], "little") in (0xFFFF, 1020):
        return Sniffed("cwa", "an Axivity .cwa file")
    if head.startswith(b"Device Identity") and b"GENEActiv" in head[:4096]:
        return Sniffed("bin", "a GENEActiv .bin file")
    if _looks_binary(head):
        if not head.strip(b"\x00"):
            return Sniffed("binary", "binary data (only zero bytes at its start: a sparse or blank file)")
        return Sniffed("binary", f"binary data of no known recording format (starts {excerpt(head, 16)})")
    return Sniffed("csv", "text")
