"""A .gt3x whose members declare far more than its recording can hold (a zip bomb: 2 MB on disk, 2 GiB of zeros
inside) is refused from the zip's directory and info.txt alone, in one line, before anything is decompressed."""
from __future__ import annotations

import struct
import subprocess
import sys
import textwrap
import time
import zlib

import pytest

pytest.importorskip("pygt3x")

TICKS_PER_S = 10_000_000  # .NET ticks in info.txt
INFO = """Serial Number: TAS1E42150038
Device Type: Link
Firmware: 1.7.2
Sample Rate: 30
Start Date: 637517662200000000
Stop Date: {stop}
Last Sample Time: {stop}
Acceleration Scale: 256.0
"""


def deflated_zeros(n_mib: int) -> bytes:
    """A raw deflate stream of ``n_mib`` MiB of zeros, built from one fully flushed MiB repeated (a full flush
    resets the window, so the copies decode independently): a few kB per MiB, written in milliseconds."""
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    one = c.compress(bytes(1 << 20)) + c.flush(zlib.Z_FULL_FLUSH)
    end = zlib.compressobj(9, zlib.DEFLATED, -15)
    return one * n_mib + end.flush(zlib.Z_FINISH)


def write_zip(path, members: list[tuple[str, bytes, int, int]]) -> None:
    """A zip of (name, deflated data, uncompressed size, crc) members, written by hand (zipfile would deflate
    gigabytes to make it)."""
    out, central = bytearray(), bytearray()
    for name, data, size, crc in members:
        offset, raw = len(out), name.encode()
        out += struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, 8, 0, 0x21, crc, len(data), size, len(raw), 0)
        out += raw + data
        central += struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, 8, 0, 0x21, crc, len(data), size,
                               len(raw), 0, 0, 0, 0, 0, offset) + raw
    eocd = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, len(members), len(members), len(central), len(out), 0)
    path.write_bytes(bytes(out + central + eocd))


def deflated(data: bytes) -> tuple[bytes, int, int]:
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    return c.compress(data) + c.flush(), len(data), zlib.crc32(data)


def bomb(path, *, log_mib: int = 2048, seconds: float = 300.0, dated: bool = True) -> None:
    text = INFO.format(stop=637517662200000000 + int(seconds * TICKS_PER_S))
    if not dated:
        text = "\n".join(line for line in text.splitlines() if "Date" not in line and "Time" not in line)
    members = [("info.txt", *deflated(text.encode()))]
    members.append(("log.bin", deflated_zeros(log_mib), log_mib << 20, 0))
    write_zip(path, members)


def read_in_child(path, limit_s: float) -> tuple[int, str, float]:
    """read_recording(path) in a child process killed after ``limit_s``: (status, stderr, seconds); -9 when
    it had to be killed."""
    code = textwrap.dedent(f"""
        import sys
        from gravcal.errors import InputError
        from gravcal.io.recordings import read_recording
        try:
            read_recording({str(path)!r})
        except InputError as exc:
            print(exc, file=sys.stderr)
            sys.exit(2)
    """)
    t0 = time.monotonic()
    try:
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=limit_s)
    except subprocess.TimeoutExpired:
        return -9, "", time.monotonic() - t0
    return r.returncode, r.stderr, time.monotonic() - t0


def test_a_gt3x_zip_bomb_is_refused_in_one_line_quickly(tmp_path):
    p = tmp_path / "bomb.gt3x"
    bomb(p)
    assert p.stat().st_size < 8 << 20  # small on disk
    status, err, took = read_in_child(p, limit_s=30.0)
    assert status == 2, (status, err[-300:], took)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{p}: ") and "log.bin" in lines[0], err
    assert "log.bin 2048 MiB" in lines[0] and "300 s at 30 Hz" in lines[0] and took < 10, (lines[0], took)


def test_the_bound_is_checked_before_decompressing(tmp_path, monkeypatch):
    """In process: no member of a refused file is ever opened for reading (the refusal costs the directory)."""
    import zipfile

    from gravcal.errors import InputError
    from gravcal.io.recordings import read_recording

    p = tmp_path / "bomb.gt3x"
    bomb(p, log_mib=64, seconds=60.0)
    opened = []
    real_open = zipfile.ZipFile.open
    monkeypatch.setattr(zipfile.ZipFile, "open", lambda self, name, *a, **k: (opened.append(
        getattr(name, "filename", name)), real_open(self, name, *a, **k))[1])
    t0 = time.monotonic()
    with pytest.raises(InputError, match="more than 60 s at 30 Hz can hold"):
        read_recording(p)
    assert time.monotonic() - t0 < 2.0
    assert "log.bin" not in opened, opened


def test_without_a_readable_info_txt_the_bound_is_the_compression_ratio(tmp_path):
    from gravcal.errors import InputError
    from gravcal.io.recordings import read_recording

    p = tmp_path / "bomb.gt3x"
    bomb(p, log_mib=512, dated=False)
    with pytest.raises(InputError, match="log.bin 512 MiB.*more than 50x its compressed size"):
        read_recording(p)
