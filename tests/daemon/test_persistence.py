"""Calibration state on disk: atomic writes, crash safety, corruption handling, lab files."""
import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from gravcal.core.calibration import Calibration
from gravcal.errors import InputError
from gravcal.daemon import persistence
from gravcal.daemon.persistence import (
    CalibrationState,
    RateLimitedSaver,
    StateStore,
    atomic_write_bytes,
    load_lab_calibration,
    read_state,
    write_state,
)

NAMES = ["s_x", "s_y", "s_z", "o_x", "o_y", "o_z"]


def make_cal(seed=0, n_windows=12):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(6, 6)) * 1e-4
    return Calibration(model="6", offset=0.5 + rng.normal(scale=0.01, size=3),
                       sensitivity=np.diag(0.125 + rng.normal(scale=0.003, size=3)),
                       covariance=A @ A.T, param_names=NAMES, n_windows=n_windows, message="ok")


def test_roundtrip_keeps_everything(tmp_path):
    st = CalibrationState(make_cal(1), revision=17, updated=1.7e9, accepted=True,
                          extra={"p": np.arange(3.0), "note": "x", "nan": float("nan")})
    path = tmp_path / "state.json"
    write_state(path, st)
    back = read_state(path)
    assert back.revision == 17 and back.updated == 1.7e9 and back.accepted is True and back.model == "6"
    np.testing.assert_array_equal(back.calibration.offset, st.calibration.offset)
    np.testing.assert_array_equal(back.calibration.sensitivity, st.calibration.sensitivity)
    np.testing.assert_array_equal(back.calibration.covariance, st.calibration.covariance)
    assert back.calibration.param_names == NAMES and back.calibration.n_windows == 12
    assert back.extra == {"p": [0.0, 1.0, 2.0], "note": "x", "nan": None}
    assert not [n for n in os.listdir(tmp_path) if n.endswith(".tmp")]  # no temp file left


def test_atomic_write_failure_leaves_old_file_and_no_temp(tmp_path, monkeypatch):
    path = tmp_path / "f.json"
    atomic_write_bytes(path, b"old")

    def boom(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="No space"):
        atomic_write_bytes(path, b"new")
    assert path.read_bytes() == b"old"
    assert os.listdir(tmp_path) == ["f.json"]


CRASH_WRITER = textwrap.dedent(
    """
    import json, sys, numpy as np
    from gravcal.core.calibration import Calibration
    from gravcal.daemon.persistence import CalibrationState, StateStore, atomic_write_bytes
    store = StateStore(sys.argv[1])
    rev = int(sys.argv[2])
    # A 4 MB state (the padding makes each write long enough to be interrupted); the JSON is
    # encoded once and only the fixed-width revision changes, so the loop is all file I/O.
    st = CalibrationState(Calibration.nominal(np.full(3, 0.5), 0.125, model="6"), 0, 0.0, True, {"pad": "x" * (1 << 22)})
    text = json.dumps(st.to_dict()).replace('"revision": 0,', '"revision": @@@@@@@@@@@@@@@,')
    head, tail = text.encode().split(b"@@@@@@@@@@@@@@@")
    print("go", flush=True)
    while True:
        rev += 1
        atomic_write_bytes(store.path, head + b"%15d" % rev + tail)
    """
)


def test_state_always_loads_after_kill_mid_write(tmp_path):
    # SIGKILL a process that rewrites the state in a tight loop at random moments: the file
    # on disk must always load, never go backwards, and never be set aside as corrupt.
    rng = np.random.default_rng(7)
    store = StateStore(tmp_path)
    last, torn, kills = 0, 0, 8
    for _ in range(kills):
        proc = subprocess.Popen([sys.executable, "-c", CRASH_WRITER, str(tmp_path), str(last)],
                                stdout=subprocess.PIPE, text=True)
        assert proc.stdout.readline().strip() == "go"
        time.sleep(rng.uniform(0.05, 0.3))
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        proc.stdout.close()
        torn += bool([n for n in os.listdir(tmp_path) if n.endswith(".tmp")])
        res = store.load()
        assert res.state is not None, res.notes
        assert res.moved_to is None
        assert res.state.revision >= last
        assert len(res.state.extra["pad"]) == 1 << 22  # complete, not torn
        last = res.state.revision
        assert not [n for n in os.listdir(tmp_path) if n.endswith(".tmp")]  # load() cleaned leftovers
    assert last > kills  # the writer really was writing several times per run
    # Evidence that kills did land inside writes (a temp file was left behind). Each kill
    # interrupts a write with probability ~ write time / loop time (> 0.5 here), so all 8
    # missing has probability < 0.5^8 = 0.4 %.
    print(f"{torn} of {kills} kills inside a write, last revision {last}")
    assert torn >= 1, "no kill landed inside a write"


@pytest.mark.parametrize(
    "content, why",
    [
        (b'{"schema": "gravcal.state/1", "revision": 3, "calibr', "not valid JSON"),
        (b"\x00\x00\x00\x00", "not valid JSON"),
        (b'{"schema": "something/else"}', "not a gravcal state file"),
        (b'{"schema": "gravcal.state/1", "revision": 1}', "no 'calibration'"),
        (b'{"schema": "gravcal.state/1", "revision": -1, "calibration": {}}', "calibration"),
        (b"[1, 2]", "must be a JSON object"),
        pytest.param(b"[" * 100_000, "nested deeper than 64 levels", id="100k ["),
        pytest.param(b'{"schema": "gravcal.state/1", "extra": ' + b'{"a":' * 5000, "nested deeper than 64 levels", id="deep extra"),
        pytest.param(b'{"revision": 1' + b"1" * 5000 + b"}", "not usable JSON", id="5000 digits"),
    ],
)
def test_corrupt_state_is_moved_aside_and_reported(tmp_path, content, why):
    store = StateStore(tmp_path)
    (tmp_path / "state.json").write_bytes(content)
    res = store.load()
    assert res.state is None
    assert res.moved_to is not None and os.path.basename(res.moved_to).startswith("state.json.corrupt-")
    assert open(res.moved_to, "rb").read() == content  # kept, not deleted
    assert not (tmp_path / "state.json").exists()
    assert why in res.notes[0] and "starting from defaults" in res.notes[0] and res.moved_to in res.notes[0]
    # a second corrupt file gets its own name
    (tmp_path / "state.json").write_bytes(content)
    res2 = store.load()
    assert res2.moved_to != res.moved_to and os.path.exists(res.moved_to) and os.path.exists(res2.moved_to)


def test_a_state_naming_an_unknown_term_is_refused_with_the_registry_terms(tmp_path):
    from gravcal.core.model.terms import CALIBRATION_TERMS

    store = StateStore(tmp_path)
    store.save(CalibrationState(make_cal(), 3, 1.0, True, {}))
    d = json.loads((tmp_path / "state.json").read_text())
    d["calibration"]["model"] = "6+bogus_term"
    (tmp_path / "state.json").write_text(json.dumps(d))
    res = store.load()
    assert res.state is None and res.moved_to is not None  # moved aside, kept
    assert "'bogus_term'" in res.notes[0] and all(t in res.notes[0] for t in CALIBRATION_TERMS)
    path = tmp_path / "lab.json"
    path.write_text(json.dumps(d["calibration"]))
    with pytest.raises(InputError, match="unknown term"):
        load_lab_calibration(str(path))


def test_missing_state_is_not_an_error(tmp_path):
    res = StateStore(tmp_path / "sub").load()
    assert res.state is None and res.moved_to is None and "no saved state" in res.notes[0]


def test_unreadable_state_is_moved_aside(tmp_path, monkeypatch):
    p = tmp_path / "state.json"
    write_state(p, CalibrationState(make_cal()))
    p.chmod(0)
    if os.geteuid() == 0:
        # root reads a mode-0 file anyway (CI runs as root): refuse it at the module's open() instead,
        # as the kernel would for the service's own user
        import builtins

        import gravcal.daemon.persistence as persistence

        def refusing_open(file, *args, **kwargs):
            if os.fspath(file) == os.fspath(p):
                raise PermissionError(13, "Permission denied", os.fspath(file))
            return builtins.open(file, *args, **kwargs)

        monkeypatch.setattr(persistence, "open", refusing_open, raising=False)
    res = StateStore(tmp_path).load()
    assert res.state is None and "Permission denied" in res.notes[0]


def test_state_directory_errors_name_the_directory(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(InputError, match=f"state directory {f}/sub: cannot create it"):
        StateStore(f / "sub").ensure_directory()


def test_rate_limited_saver_writes_latest_and_limits_rate(tmp_path):
    store = StateStore(tmp_path)
    saver = RateLimitedSaver(store, min_interval_s=30.0)
    try:
        for rev in range(1, 51):
            saver.offer(CalibrationState(make_cal(), rev, float(rev), True))
        time.sleep(0.3)
        # the first offer may be written at once; the 49 after it wait for the interval
        assert saver.saves <= 1
        assert saver.flush()
        assert 1 <= saver.saves <= 2
        assert read_state(store.path).revision == 50  # the newest, not the first
        saver.offer(CalibrationState(make_cal(), 51, 51.0, True))
        time.sleep(0.2)
        assert read_state(store.path).revision == 50  # still within the interval
    finally:
        assert saver.close()
    assert read_state(store.path).revision == 51  # close() flushes


def test_saver_survives_write_errors_and_retries(tmp_path):
    store = StateStore(tmp_path / "gone")  # directory does not exist: every save fails
    saver = RateLimitedSaver(store, min_interval_s=0.0)
    saver.offer(CalibrationState(make_cal(), 1))
    assert not saver.flush()
    assert saver.failures >= 1 and "No such file or directory" in saver.last_error
    os.makedirs(tmp_path / "gone")
    assert saver.flush()  # the failed state is still pending and is written now
    assert read_state(store.path).revision == 1
    saver.close()


def test_lab_calibration_formats(tmp_path):
    cal = make_cal(3)
    a = tmp_path / "cal.json"
    a.write_text(cal.to_json())
    got = load_lab_calibration(a)
    np.testing.assert_array_equal(got.offset, cal.offset)
    np.testing.assert_array_equal(got.covariance, cal.covariance)
    # the `gravcal calibrate --json` report: either embeds the calibration ...
    b = tmp_path / "report.json"
    b.write_text(json.dumps({"heldout_rms_mg": 1.2, "calibration": cal.to_dict()}))
    np.testing.assert_array_equal(load_lab_calibration(b).sensitivity, cal.sensitivity)
    # ... or has the fields at top level, stds only
    c = tmp_path / "flat.json"
    std = {n: 1e-3 * (i + 1) for i, n in enumerate(NAMES)}
    c.write_text(json.dumps({"model": "6", "offset": cal.offset.tolist(), "sensitivity": cal.sensitivity.tolist(),
                             "std": std, "n_windows": 40}))
    flat = load_lab_calibration(c)
    assert flat.n_windows == 40 and flat.param_names == NAMES
    np.testing.assert_allclose(np.sqrt(np.diag(flat.covariance)), [1e-3 * (i + 1) for i in range(6)])


@pytest.mark.parametrize(
    "content, message",
    [
        ("{not json", "not valid JSON"),
        pytest.param("[" * 100_000, "nested deeper than 64 levels", id="100k ["),
        ('{"hello": 1}', "not a gravcal calibration"),
        ('{"model": "6", "offset": [0, 0], "sensitivity": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}', "malformed"),
        ('{"schema": "gravcal.calibration/1", "model": "6", "offset": [0.5, 0.5, 0.5], "sensitivity": [[0, 0, 0], [0, 0, 0], [0, 0, 0]]}', "singular"),
    ],
)
def test_bad_lab_calibration_names_the_file(tmp_path, content, message):
    p = tmp_path / "lab.json"
    p.write_text(content)
    with pytest.raises(InputError, match=message) as e:
        load_lab_calibration(p)
    assert str(p) in str(e.value)
    with pytest.raises(InputError, match="no such calibration file"):
        load_lab_calibration(tmp_path / "missing.json")


def test_the_first_save_makes_the_new_directories_durable(tmp_path, monkeypatch):
    """A state directory created by the first save is an entry in its parent: the parent of every directory
    created is fsynced (top down) before the file's own rename is, or a power cut could lose the directory
    and the state with it."""
    synced = []
    real = persistence.fsync_dir
    monkeypatch.setattr(persistence, "fsync_dir", lambda d: (synced.append(os.path.abspath(d)), real(d)))
    store = StateStore(tmp_path / "a" / "b")
    store.check_directory()
    assert not (tmp_path / "a").exists()
    store.save(CalibrationState(make_cal(), 1, 1.0, True, {}))
    assert synced == [str(tmp_path), str(tmp_path / "a"), str(tmp_path / "a" / "b")]
    synced.clear()
    store.save(CalibrationState(make_cal(), 2, 2.0, True, {}))  # the directory exists: only the rename
    assert synced == [str(tmp_path / "a" / "b")]


@pytest.mark.parametrize("line", ["[" * 100_000, "[1, 2]", '{"class": "WINDOW", "start": ' + "1" * 5000 + "}"],
                         ids=["100k [", "a list", "5000 digits"])
def test_a_hostile_window_log_line_is_named_not_raised(tmp_path, line):
    from gravcal.daemon.window_log import read_windows

    p = tmp_path / "w.jsonl"
    p.write_text(line + "\n")
    with pytest.raises(ValueError, match="line 1 is not a window record"):
        read_windows(p)
