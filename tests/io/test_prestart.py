"""io/prestart.py: the block statistics' memory of `gravcal calibrate FILE.npy`, faulted in early.

What must hold: the reading pass's statistics are bit for bit those of a pass that allocates its own
arrays (with the prepared memory, and when the guess does not fit); the memory is used when the guess
fits; nothing is prepared for command lines or files it does not cover; populate never leaves its buffer.
"""
from __future__ import annotations

import json
import mmap
import os
import subprocess
import sys

import numpy as np
import pytest

from gravcal.core import fastdetect
from gravcal.io import prestart
from gravcal.io._pages import populate
from gravcal.cli.main import build_parser
from gravcal.io.recordings import read_recording


def _write(path, n=200_000, fs=100.0, temp=False, seed=0, first_fs=None, dtype_f=np.float32, align=False):
    """A structured .npy: t [s] (at ``first_fs`` for its first 5 000 rows when given), a random walk
    of duty cycles with still stretches, optional temp."""
    rng = np.random.default_rng(seed)
    fields = [("t", "<f8"), ("ax", dtype_f), ("ay", dtype_f), ("az", dtype_f)] + ([("temp", "<f4")] if temp else [])
    dt = np.dtype(fields, align=align)
    steps = np.full(n - 1, 1.0 / fs)
    if first_fs is not None:
        steps[:5000] = 1.0 / first_fs
    arr = np.zeros(n, dtype=dt)
    arr["t"] = np.concatenate([[1000.0], 1000.0 + np.cumsum(steps)])
    walk = np.cumsum(rng.normal(0, 1e-3, (n, 3)) * (rng.random((n, 1)) < 0.5), axis=0)
    for i, c in enumerate(("ax", "ay", "az")):
        arr[c] = 0.5 + 0.04 * np.sin(walk[:, i]) + rng.normal(0, 2e-4, n)
    if temp:
        arr["temp"] = 25 + 0.01 * rng.normal(size=n).cumsum() / 100
    np.save(path, arr)
    return arr


def _blocks(path):
    rec = read_recording(path, exclude_filler=True, blocks=True)
    assert rec.blocks is not None
    return rec.blocks


def _from_arena(a: np.ndarray) -> bool:
    base = a
    while getattr(base, "base", None) is not None:
        base = base.base
    return isinstance(base, (memoryview, mmap.mmap))


def _same_bits(a, b):
    for name in ("mean", "scatter", "aux", "usable"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert x.tobytes() == y.tobytes(), f"{name} differs"
    assert (a.fs, a.block_n) == (b.fs, b.block_n)


@pytest.mark.parametrize("temp", [False, True])
@pytest.mark.parametrize("fs", [100.0, 50.0, 30.0])
def test_prepared_memory_gives_the_same_statistics(tmp_path, temp, fs):
    path = tmp_path / "rec.npy"
    _write(path, fs=fs, temp=temp)
    own = _blocks(path)
    assert prestart.start(["calibrate", str(path), "--json"])
    arena = prestart._pending[0]
    got = _blocks(path)
    arena.thread.join(30)
    assert not prestart._pending, "the arena is claimed once"
    assert all(_from_arena(getattr(got, n)) for n in ("mean", "scatter", "aux", "usable")), "prepared memory unused"
    assert arena.populated is True
    assert got.block_n == fastdetect.block_length(fs)
    _same_bits(got, own)
    # a second read of the same file allocates its own arrays
    again = _blocks(path)
    assert not _from_arena(again.mean)
    _same_bits(again, own)


def test_a_wrong_guess_falls_back_to_own_arrays(tmp_path):
    """The first 5 000 rows at 50 Hz: the guess gives blocks of 5, the pass (median of sampled chunks) 10."""
    path = tmp_path / "rec.npy"
    _write(path, n=400_000, fs=100.0, first_fs=50.0)
    own = _blocks(path)
    assert prestart.start(["calibrate", str(path)])
    assert prestart._pending[0].nb == 400_000 // 5
    got = _blocks(path)
    assert got.block_n == 10
    assert not _from_arena(got.mean) and not _from_arena(got.scatter)
    _same_bits(got, own)


def test_a_changed_file_is_not_claimed(tmp_path):
    path = tmp_path / "rec.npy"
    _write(path)
    assert prestart.start(["calibrate", str(path)])
    _write(path, n=150_000, seed=1)  # rewritten after the prestart: another size
    got = _blocks(path)
    assert not _from_arena(got.mean)
    assert prestart.claim(tmp_path / "other.npy") is None
    prestart._pending.clear()


def test_npy_layout_reads_numpys_headers(tmp_path):
    for i, (kw, fields) in enumerate([({}, None), ({"temp": True}, None), ({"align": True, "temp": True}, None),
                                      ({"dtype_f": np.float64}, None)]):
        path = tmp_path / f"r{i}.npy"
        arr = _write(path, n=1000, **kw)
        n, offset, itemsize, got = prestart.npy_layout(path)
        assert (n, itemsize) == (1000, arr.dtype.itemsize)
        assert {k: v[1] for k, v in got.items() if k} == {k: arr.dtype.fields[k][1] for k in arr.dtype.names}
        with open(path, "rb") as f:
            f.seek(offset)
            assert f.read(arr.dtype.itemsize) == arr[:1].tobytes()
    np.save(tmp_path / "plain.npy", np.zeros((10, 3)))
    (tmp_path / "junk.npy").write_bytes(b"\x93NUMPY\x01\x00\xff\xff{'descr'")
    (tmp_path / "text.npy").write_text("t,ax,ay,az\n0,1,2,3\n")
    for name in ("plain", "junk", "text", "missing"):
        assert prestart.npy_layout(tmp_path / f"{name}.npy") is None
        assert not prestart.start(["calibrate", str(tmp_path / f"{name}.npy")])


def test_block_length_guess_and_constant_agree_with_fastdetect(tmp_path):
    assert prestart.BLOCK_S == fastdetect.BLOCK_S
    for fs in (12.5, 25.0, 30.0, 64.0, 100.0, 256.0):
        path = tmp_path / "r.npy"
        _write(path, n=10_000, fs=fs)
        n, offset, itemsize, fields = prestart.npy_layout(path)
        # the reading pass's own block length (its sample rate from sampled chunks' median steps)
        assert prestart.guess_block_n(path, n, offset, itemsize, fields["t"][1]) == _blocks(path).block_n


def test_command_lines():
    f = prestart.calibrate_file
    assert str(f(["calibrate", "a.npy"])) == "a.npy"
    assert str(f(["-v", "--debug", "calibrate", "--model", "9", "a.npy", "--json", "--folds=4"])) == "a.npy"
    assert str(f(["calibrate", "--save", "cal.json", "--start", "s.json", "a.npy"])) == "a.npy"
    for argv in (["calibrate", "a.npy", "b.npy"], ["calibrate", "d", "--out", "r.csv"], ["calibrate", "a.npy", "--lab"],
                 ["calibrate", "a.npy", "--columns", "t=x"], ["calibrate", "a.npy", "--frobnicate"],
                 ["simulate", "--out", "a.npy"], ["calibrate"], [], ["calibrate", "-h"]):
        assert f(argv) is None, argv


def test_options_known_to_the_prestart_are_the_parsers():
    parser = build_parser(["calibrate"])
    sub = next(a for a in parser._actions if a.dest == "command").choices["calibrate"]
    flags, values = set(), set()
    for action in sub._actions:
        longs = [o for o in action.option_strings if o.startswith("--")]
        if not longs or "--help" in longs:
            continue
        (flags if action.nargs == 0 else values).update(longs)
    assert values == prestart.VALUE_OPTIONS
    assert flags == prestart.FLAG_OPTIONS


def test_populate_stays_in_its_buffer_and_keeps_contents():
    m = mmap.mmap(-1, 5 * mmap.PAGESIZE)
    m[:] = bytes(range(256)) * (len(m) // 256)
    before = m[:]
    assert populate(m, 0, len(m)) is True
    assert populate(m, 100, 3 * mmap.PAGESIZE) is True
    assert populate(m, len(m), 0) is True
    assert m[:] == before
    for offset, length in ((-1, 10), (0, len(m) + 1), (len(m), 1), (10, -5)):
        with pytest.raises(ValueError, match="outside the buffer"):
            populate(m, offset, length)
    with pytest.raises(TypeError):
        populate(bytes(10), 0, 10)


def test_block_pass_refuses_an_allocator_of_other_arrays():
    t = np.arange(1000) / 100.0
    raw = np.zeros((1000, 3))
    with pytest.raises(ValueError, match="C-contiguous float32 array of shape"):
        fastdetect.BlockPass(t, lambda c, i, j: raw[i:j, c], 1000, 100.0,
                             allocate=lambda shape, dtype: np.empty(shape, dtype=np.float64))


def test_the_program_prepares_and_prints_the_same(tmp_path):
    """`python -m gravcal.cli.main calibrate` (console: prestart) and main() in-process (none) agree."""
    path = tmp_path / "rec.npy"
    from gravcal.core.simulate import simulate
    from gravcal.core.samples import raw_triad

    sim = simulate("daily_living", seed=2, duration=2400.0)
    raw = raw_triad(sim.samples)
    arr = np.zeros(len(raw), dtype=[("t", "<f8"), ("ax", "<f4"), ("ay", "<f4"), ("az", "<f4")])
    arr["t"], arr["ax"], arr["ay"], arr["az"] = sim.samples["t"], raw[:, 0], raw[:, 1], raw[:, 2]
    np.save(path, arr)
    code = ("import sys, json\n"
            "from gravcal.io import prestart; from gravcal.cli import main as cli\n"
            "real = prestart.claim\n"
            "def claim(p):\n"
            "    a = real(p)\n"
            "    print('claimed' if a is not None else 'none', file=sys.stderr)\n"
            "    return a\n"
            "prestart.claim = claim\n"
            "sys.argv = ['gravcal', 'calibrate', sys.argv[1], '--json']\n"
            "cli.console()\n")
    p = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=300)
    assert p.returncode in (0, 3), p.stderr
    assert "claimed" in p.stderr
    from gravcal.cli.main import main
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["calibrate", str(path), "--json"]) == p.returncode
    a, b = json.loads(p.stdout), json.loads(buf.getvalue())
    a.pop("timing_s"), b.pop("timing_s")
    assert a == b


def test_a_failing_populate_only_leaves_the_faults_to_the_pass(tmp_path, monkeypatch, capfd):
    from gravcal.core.accelerator import kernels

    pages = kernels("gravcal.io._pages")  # the module prestart's thread takes populate from

    def fail(*_):
        raise OSError(12, "Cannot allocate memory")

    path = tmp_path / "rec.npy"
    _write(path)
    own = _blocks(path)
    monkeypatch.setattr(pages, "populate", fail)
    assert prestart.start(["calibrate", str(path)])
    arena = prestart._pending[0]
    arena.thread.join(30)
    assert arena.populated is False
    got = _blocks(path)
    assert _from_arena(got.mean)
    _same_bits(got, own)
    assert "Traceback" not in capfd.readouterr().err
