"""The pyarrow path of CSV reading (io/formats/csvarrow.py) against the exact path it accelerates
(np.loadtxt, then the line-by-line parser): the same float64 columns for every layout the format
allows, cut into many segments and byte ranges so every seam is crossed; anything it will not take
falls back to the exact path and its line-and-column message."""
from __future__ import annotations

import gzip

import numpy as np
import pytest

from gravcal.errors import InputError
from gravcal.io.formats import csvarrow, csvtext
from gravcal.io.formats.csvtext import line_of_data_row, load_csv, data_lines
from gravcal.io.recordings import read_recording

import pyarrow  # noqa: E402,F401  (a dependency: its absence is a failure, not a skip)


def _layout(rng, n):
    """A random but valid CSV: delimiter, line ends, comment and blank lines, extra and optional columns."""
    delim = rng.choice([",", ";", "\t"])
    nl = rng.choice(["\n", "\r\n"])
    names = ["t", "ax", "ay", "az"]
    if rng.random() < 0.5:
        names.insert(int(rng.integers(0, 5)), "note")  # a column gravcal ignores
    if rng.random() < 0.5:
        names.append("temp")
    lines = ["# exported by a logger"] * int(rng.integers(0, 3)) + [delim.join(names)]
    t = 3.0 + np.cumsum(rng.uniform(0.005, 0.015, n))
    for i in range(n):
        r = rng.random()
        if r < 0.01:
            lines.append("# a comment line")
        elif r < 0.02:
            lines.append("")
        vals = {"t": f"{t[i]:.6f}", "ax": repr(rng.normal()), "ay": f"{rng.normal():.4e}", "az": f"{rng.normal():.9g}",
                "temp": f"{25 + rng.normal():.3f}", "note": "x"}
        if rng.random() < 0.005:
            vals["ay"] = ""  # a missing value: NaN on both paths
        lines.append(delim.join(vals[c] for c in names))
    return nl.join(lines) + (nl if rng.random() < 0.8 else "")


def _exact(path, gz, monkeypatch):
    with monkeypatch.context() as m:
        m.setattr(csvarrow, "available", lambda: False)
        return load_csv(path, gz=gz)


@pytest.mark.parametrize("seed", range(12))
def test_fast_path_gives_the_exact_paths_columns(tmp_path, monkeypatch, seed):
    rng = np.random.default_rng(seed)
    text = _layout(rng, int(rng.integers(1, 3000)))
    gz = seed % 3 == 2
    path = tmp_path / ("rec.csv.gz" if gz else "rec.csv")
    path.write_bytes(gzip.compress(text.encode()) if gz else text.encode())
    ref, _, ref_names = _exact(path, gz, monkeypatch)
    calls = []
    real = csvarrow.read_columns
    monkeypatch.setattr(csvarrow, "read_columns", lambda *a, **k: calls.append(1) or real(*a, **k))
    # small segments, pieces and blocks, and more ranges than this machine has cores: every seam is crossed
    monkeypatch.setattr(csvarrow, "SEGMENT_BYTES", int(rng.integers(40, 5000)))
    monkeypatch.setattr(csvarrow, "BLOCK_BYTES", int(rng.integers(30, 3000)))
    monkeypatch.setattr(csvarrow, "MOVE_ROWS", int(rng.integers(1, 500)))
    monkeypatch.setattr(csvarrow.os, "cpu_count", lambda: 5)
    got, _, names = load_csv(path, gz=gz)
    assert calls, "the fast path was not tried"
    assert names == ref_names and set(got) >= set(ref) - {"_triad"}
    for c, v in ref.items():
        np.testing.assert_array_equal(got[c], v, err_msg=c)  # both round each decimal to the nearest float64
    assert got["_triad"].shape == (len(ref["t"]), 3) and got["_triad"].flags.c_contiguous


def test_fast_path_falls_back_and_names_line_and_column(tmp_path, monkeypatch):
    rows = [f"{i / 100:.2f},0.5,0.5,{0.5 + i * 1e-4:.6f}" for i in range(5000)]
    rows[4321] = "43.21,0.5,abc,0.5"
    path = tmp_path / "bad.csv"
    path.write_text("t,ax,ay,az\n" + "\n".join(rows) + "\n")
    monkeypatch.setattr(csvarrow, "SEGMENT_BYTES", 4096)
    fell = []
    real = csvarrow.read_columns

    def spy(*a, **k):
        try:
            return real(*a, **k)
        except csvarrow.Fallback:
            fell.append(1)
            raise
    monkeypatch.setattr(csvarrow, "read_columns", spy)
    with pytest.raises(InputError, match=r"line 4323, column 'ay': 'abc' is not a number"):
        read_recording(path)
    assert fell


def test_time_backwards_is_placed_on_its_line_by_the_block_count(tmp_path):
    n = 200_000
    t = np.arange(n) / 100.0
    t[n - 10] = t[n - 12]  # backwards, near the end
    body = "\n".join(f"{x:.2f},0.5,{0.5 + 1e-3 * np.sin(i):.6f},0.5" for i, x in enumerate(t))
    path = tmp_path / "back.csv"
    path.write_text("# logger v1\nt,ax,ay,az\n" + body + "\n")
    with pytest.raises(InputError, match=rf"time goes backwards at line {n - 10 + 3}\b"):
        read_recording(path)


@pytest.mark.parametrize("seed", range(4))
def test_line_of_data_row_counts_as_data_lines_does(tmp_path, seed):
    rng = np.random.default_rng(seed)
    lines = ["# c", "t,ax"]
    for i in range(400):
        r = rng.random()
        lines.append("" if r < 0.05 else "# x" if r < 0.1 else "  " if r < 0.12 else f"{i},{i}")
    nl = ["\n", "\r\n", "\r"][seed % 3]
    path = tmp_path / "f.csv"
    path.write_bytes((nl.join(lines) + nl).encode())
    ref = [ln for ln, _ in data_lines(path, 2)]
    for row in range(len(ref) + 1):
        expected = ref[row] if row < len(ref) else None
        assert line_of_data_row(path, 2, False, row, chunk=int(rng.integers(3, 200))) == expected


def test_whitespace_separated_file_takes_the_exact_path(tmp_path, monkeypatch):
    path = tmp_path / "ws.csv"
    path.write_text("t ax ay az\n" + "\n".join(f"{i / 100:.2f} 0.5 {0.5 + i * 1e-4:.6f} 0.5" for i in range(100)) + "\n")
    monkeypatch.setattr(csvarrow, "read_columns", lambda *a, **k: pytest.fail("pyarrow cannot split on runs of spaces"))
    cols, _, _ = csvtext.load_csv(path)
    assert cols["ay"][99] == pytest.approx(0.5099)
