"""Third-party native readers run in a child process (io/formats/isolated.py): a reader that ends its process on a
damaged file costs that file one InputError line naming the file and the reader, never `gravcal calibrate` or a
study. Each death costs a new child (scikit-digital-health's imports, seconds): three here."""
from __future__ import annotations

import csv
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from gravcal.cli.main import main
from gravcal.errors import InputError
from gravcal.io.formats import isolated, wearables
from gravcal.io.formats.sniff import Sniffed
from gravcal.io.recordings import read_recording

# the recording fuzz target's find: byte 0 chose the suffix, the rest is a .cwa cut inside its first block
TRUNCATED_CWA = Path(__file__).parents[1] / "fuzz" / "corpus" / "recording" / "crash_cwa_truncated_fortran_exit"


def _exit_reader(path, found):
    os._exit(3)


def _abort_reader(path, found):
    os.abort()


@pytest.fixture
def truncated_cwa(tmp_path, monkeypatch):
    pytest.importorskip("skdh")
    p = tmp_path / "cut.cwa"
    p.write_bytes(TRUNCATED_CWA.read_bytes()[1:])
    monkeypatch.setattr(wearables, "CWA_HEADER", 0)  # past the early refusal, to the reader itself
    return p


def test_a_fortran_reader_ending_its_process_is_one_line_about_that_file(truncated_cwa):
    with pytest.raises(InputError) as exc:
        read_recording(truncated_cwa)
    text = str(exc.value)
    assert "\n" not in text and text.startswith(f"{truncated_cwa}: an Axivity .cwa file"), text
    assert "scikit-digital-health" in text and "exit status 2" in text and "Fortran runtime error" in text, text


def test_a_reader_exiting_or_aborting_is_said_so(truncated_cwa, monkeypatch):
    monkeypatch.setattr(wearables, "SKDH_READER", f"{__name__}:_exit_reader")
    with pytest.raises(InputError, match=r"its reader ended the process \(exit status 3\); not read$"):
        read_recording(truncated_cwa)


def test_a_study_goes_on_after_a_reader_aborts_and_calibrate_exits_2(truncated_cwa, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(wearables, "SKDH_READER", f"{__name__}:_abort_reader")
    good = tmp_path / "good.npy"
    assert main(["simulate", "--scenario", "six_position", "--seed", "1", "--duration", "240", "--out", str(good)]) == 0
    out = tmp_path / "rows.csv"
    assert main(["calibrate", str(truncated_cwa), str(good), "--out", str(out), "--workers", "0", "--quiet"]) == 2
    with open(out, newline="") as f:
        rows = {Path(r["file"]).name: r for r in csv.DictReader(f)}
    assert rows["cut.cwa"]["status"] == "error", rows["cut.cwa"]
    assert "signal SIGABRT" in rows["cut.cwa"]["message"] and "scikit-digital-health" in rows["cut.cwa"]["message"]
    assert rows["good.npy"]["status"] == "ok", rows["good.npy"]
    # one file alone: one line, exit status 2
    capsys.readouterr()
    assert main(["calibrate", str(truncated_cwa)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "signal SIGABRT" in err and str(truncated_cwa) in err, err
    # and the next good .cwa reads in a new child
    monkeypatch.undo()
    if os.environ.get("GRAVCAL_SKDH_FIXTURES"):
        rec = read_recording(Path(os.environ["GRAVCAL_SKDH_FIXTURES"]) / "ax6_sample.cwa", check_saturation=False)
        assert rec.raw.shape[0] > 0
    assert isolated._CHILD.proc is None or isolated._CHILD.proc.poll() is None


def _buggy_reader(path, found):
    return {}["t"], {}


def test_a_bug_in_the_child_is_raised_not_taken_for_a_damaged_file(truncated_cwa, monkeypatch):
    monkeypatch.setattr(wearables, "SKDH_READER", f"{__name__}:_buggy_reader")
    with pytest.raises(RuntimeError, match=r"_buggy_reader raised KeyError: 't'$"):
        read_recording(truncated_cwa)


def _slow_reader(path, found):
    (path.parent / "started").touch()
    time.sleep(5)
    return {"t": np.arange(3.0)}, {"n": 3}


def _tiny_reader(path, found):
    return {"t": np.arange(2.0)}, {"n": 2}


def test_an_interrupted_read_leaves_no_answer_for_the_next(tmp_path):
    p = tmp_path / "x.bin"
    p.write_bytes(b"x")
    found = Sniffed("bin", "a test file")

    main = threading.get_ident()

    def interrupt_once_started():
        while not (tmp_path / "started").exists():
            time.sleep(0.01)
        # at the main thread, as a Ctrl-C reaches it: a process-directed signal may land on this thread and leave the
        # main thread's read uninterrupted until the child answers
        signal.pthread_kill(main, signal.SIGINT)

    # Ctrl-C's own handler, whatever the test runner's worker installed
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        threading.Thread(target=interrupt_once_started, daemon=True).start()
        with pytest.raises(KeyboardInterrupt):
            isolated.read_in_child(f"{__name__}:_slow_reader", p, found, "a slow reader")
    finally:
        signal.signal(signal.SIGINT, previous)
    cols, meta = isolated.read_in_child(f"{__name__}:_tiny_reader", p, found, "a quick reader")
    assert meta == {"n": 2} and cols["t"].tolist() == [0.0, 1.0]
