"""`gravcal calibrate FILE`: a progress bar on a terminal's stderr only; reading reports its chunks."""
from __future__ import annotations

import fcntl
import os
import pty
import struct
import subprocess
import sys
import termios
import threading

import pytest
import tqdm  # noqa: F401  the bar's library: the [study] extra, which [test] installs

import gravcal.io.recordings as recordings
from gravcal.core.simulate import simulate
from gravcal.io.recordings import read_recording, write_recording



@pytest.fixture(scope="module")
def rec_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("progress") / "rec.npy"
    write_recording(path, simulate("loetters", seed=4, duration=600.0).samples)
    return path


def _run(path, *extra, stderr_tty: bool):
    cmd = [sys.executable, "-m", "gravcal.cli.main", "calibrate", str(path), *extra]
    if not stderr_tty:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
        return r.returncode, r.stdout, r.stderr
    master, slave = pty.openpty()
    # a terminal's size: tqdm draws nothing on a 0-column one (a fresh pty's)
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))
    chunks: list[bytes] = []

    def drain() -> None:
        while True:
            try:
                data = os.read(master, 4096)
            except OSError:  # EIO: the child closed its side
                return
            if not data:
                return
            chunks.append(data)

    reader = threading.Thread(target=drain)
    reader.start()
    try:
        r = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=slave, text=True, timeout=120)
    finally:
        os.close(slave)
        reader.join(10)
        os.close(master)
    return r.returncode, r.stdout, b"".join(chunks).decode("utf-8", "replace")


def test_no_bar_when_stderr_is_a_pipe(rec_path):
    code, out, err = _run(rec_path, stderr_tty=False)
    assert code == 0, err
    assert "recording" in out
    assert "calibrating" not in err and "reading" not in err and "%|" not in err


def test_bar_on_a_terminal(rec_path):
    code, out, err = _run(rec_path, stderr_tty=True)
    assert code == 0, err
    assert "recording" in out  # the summary still goes to stdout alone
    assert "reading" in err and "calibrating" in err and "%|" in err


@pytest.mark.parametrize("flag", ["--quiet", "--json"])
def test_quiet_and_json_show_no_bar_on_a_terminal(rec_path, flag):
    code, out, err = _run(rec_path, flag, stderr_tty=True)
    assert code == 0, err
    assert "%|" not in err and "calibrating" not in err


def test_reading_reports_each_chunk_of_the_scan(rec_path, monkeypatch):
    monkeypatch.setattr(recordings, "SCAN_CHUNK", 5000)
    calls = []
    rec = read_recording(rec_path, progress=lambda d, n: calls.append((d, n)))
    n_chunks = -(-rec.n_samples // 5000)
    assert [d for d, _ in calls] == list(range(1, n_chunks + 1)) and {n for _, n in calls} == {n_chunks}


def test_python_api_progress_true_draws_bars_and_false_none(rec_path, capsys):
    import gravcal

    quiet = gravcal.calibrate(rec_path)
    assert "%|" not in capsys.readouterr().err
    shown = gravcal.calibrate(rec_path, progress=True)
    err = capsys.readouterr().err
    assert "reading" in err and "calibrating" in err and "%|" in err
    assert shown.offset.tolist() == quiet.offset.tolist()
