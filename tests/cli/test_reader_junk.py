"""A reader that cannot be knocked over: generated junk of any size gives one short error line that
quotes at most a short printable excerpt (no control characters, no escape sequences), quickly and
without holding the file (the 1 GB files are sparse: no disk used)."""
from __future__ import annotations

import gzip
import os
import zipfile

import numpy as np
import pytest

from gravcal.cli.main import main

MAX_MESSAGE = 400
ESCAPES = b"\x1b[2J\x1b]0;pwned\x07\x1b[31m\r\x08\x00"


def error_line(capsys, path, *extra) -> str:
    code = main(["calibrate", str(path), *extra])
    out, err = capsys.readouterr()
    assert code == 2, (code, out, err[:500])
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("gravcal: error: "), err[:500]
    msg = lines[0]
    assert len(msg) < MAX_MESSAGE + len(str(path)), len(msg)
    assert not any(ord(c) < 32 or ord(c) == 127 for c in msg), repr(msg)
    assert "\x1b" not in msg and "pwned\x07" not in msg and "Traceback" not in err
    return msg


def sparse(path, size: int, head: bytes = b"") -> None:
    with open(path, "wb") as f:
        f.write(head)
        f.truncate(size)


@pytest.mark.parametrize("name", ["huge.csv", "huge.npy", "huge.gt3x", "huge"])
def test_a_sparse_gigabyte_is_refused_in_one_short_line(capsys, tmp_path, name):
    p = tmp_path / name
    sparse(p, 1 << 30)
    msg = error_line(capsys, p)
    assert "zero bytes" in msg or "not a readable" in msg


def test_a_header_then_a_sparse_gigabyte(capsys, tmp_path):
    p = tmp_path / "header.csv"
    sparse(p, 1 << 30, b"t,ax,ay,az\n1,2,3,4\n")
    assert "binary data" in error_line(capsys, p)


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("suffix", [".csv", ".npy", ".gt3x", ".cwa", ".bin", ".csv.gz"])
def test_random_bytes_with_escape_sequences(capsys, tmp_path, seed, suffix):
    rng = np.random.default_rng(seed)
    junk = rng.integers(0, 256, 20_000, dtype=np.uint8).tobytes()
    p = tmp_path / f"junk{suffix}"
    p.write_bytes(ESCAPES + junk[:5000] + ESCAPES + junk[5000:])
    error_line(capsys, p)


def test_text_with_escape_sequences_in_the_header_is_sanitised(capsys, tmp_path):
    p = tmp_path / "names.csv"
    p.write_text("t,\x1b[31mred\x1b[0m,ay,az\n" + "0,1,2,3\n" * 100)
    msg = error_line(capsys, p)
    assert "missing column ax" in msg and "?[31mred?[0m" in msg


def test_an_endless_line_is_refused_without_holding_it(capsys, tmp_path):
    p = tmp_path / "long.csv"
    p.write_text("t,ax,ay,az\n" + "1,2,3,4\n" * 100 + "9" * (4 << 20))
    msg = error_line(capsys, p)
    assert "longer than" in msg and "'9999" in msg


def test_a_line_of_text_among_numbers_is_quoted_short(capsys, tmp_path):
    p = tmp_path / "word.csv"
    p.write_text("t,ax,ay,az\n" + "".join(f"{i / 100},1,2,3\n" for i in range(100)) + "1,\x1b[2J" + "x" * 5000 + ",2,3\n")
    msg = error_line(capsys, p)
    assert "line 102, column 'ax'" in msg and "?[2Jxxx" in msg


def test_archives_and_damaged_files_say_what_they_are(capsys, tmp_path):
    z = tmp_path / "other.gt3x"
    with zipfile.ZipFile(z, "w") as f:
        f.writestr("readme\x1b[2J.txt", "hello")
    assert "zip archive that is no ActiGraph file" in error_line(capsys, z)
    fake = tmp_path / "fake.gt3x"
    with zipfile.ZipFile(fake, "w") as f:
        f.writestr("info.txt", "Serial Number: X\n")
        f.writestr("log.bin", os.urandom(300))
    msg = error_line(capsys, fake)
    assert "pygt3x cannot read" in msg or "holding no acceleration samples" in msg
    npz = tmp_path / "arrays.csv"
    np.savez(npz.with_suffix(".npz"), a=np.zeros(3))
    npz.with_suffix(".npz").rename(npz)
    assert "NumPy .npz archive" in error_line(capsys, npz)
    gz = tmp_path / "cut.csv.gz"
    gz.write_bytes(gzip.compress(b"t,ax,ay,az\n" + b"1,2,3,4\n" * 1000)[:60])
    error_line(capsys, gz)
