"""`gravcal calibrate DIR|FILES --out results.csv`: one row per file (a broken one is a row with its
error), the same numbers as one-file calibrate, resume, Ctrl-C leaves a valid file, Dask or not."""
from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from gravcal.cli.main import main
from gravcal.io.study import FIELDS

N_GOOD = 4
N_LINKED = 12


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    d = tmp_path_factory.mktemp("study")
    (d / "site2").mkdir()
    for seed in range(N_GOOD):
        where = d / "site2" if seed == 3 else d
        assert main(["simulate", "--scenario", "six_position", "--seed", str(seed), "--duration", "240",
                     "--out", str(where / f"s{seed}.npy")]) == 0
    (d / "broken.csv").write_bytes(b"\x1b[2J" + os.urandom(2000))
    (d / "notes.txt").write_text("not a recording")  # unknown suffix: not picked up from a directory
    return d


def rows_of(path):
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        assert tuple(reader.fieldnames) == FIELDS
        return list(reader)


def test_rows_match_single_file_calibration(study, tmp_path, capsys):
    out = tmp_path / "results.csv"
    assert main(["calibrate", str(study), "--out", str(out), "--workers", "0", "--quiet"]) == 2  # an error row
    rows = rows_of(out)
    assert len(rows) == N_GOOD + 1
    by_name = {os.path.basename(r["file"]): r for r in rows}
    assert by_name["broken.csv"]["status"] == "error" and "binary data" in by_name["broken.csv"]["message"]
    assert "\x1b" not in by_name["broken.csv"]["message"]
    capsys.readouterr()
    for seed in range(N_GOOD):
        row = by_name[f"s{seed}.npy"]
        assert row["status"] == "ok", row
        assert main(["calibrate", row["file"], "--json"]) == 0
        one = json.loads(capsys.readouterr().out)
        assert row["model"] == one["model"] and int(row["n_windows"]) == one["n_windows"]
        assert float(row["heldout_rms_mg"]) == pytest.approx(one["heldout_rms_mg"], rel=1e-9)
        assert np.allclose([float(row[f"offset_{a}"]) for a in "xyz"], one["offset"], rtol=1e-12)
        k = np.array([[float(row[f"sensitivity_{a}{b}"]) for b in "xyz"] for a in "xyz"])
        assert np.allclose(k, one["sensitivity"], rtol=1e-12)


def test_resume_skips_done_files_and_redoes_a_torn_row(study, tmp_path, capsys):
    out = tmp_path / "results.csv"
    files = [str(study / "s0.npy"), str(study / "s1.npy")]
    assert main(["calibrate", *files, "--out", str(out), "--workers", "0"]) == 0
    first = rows_of(out)
    assert [r["file"] for r in first] == files
    with open(out, "a") as f:
        f.write(f"{study / 'broken.csv'},ok,6,1.0")  # a row cut short by a kill
    assert main(["calibrate", str(study), "--out", str(out), "--workers", "0"]) == 2
    err = capsys.readouterr().err
    assert "2 of 5 files already done" in err
    rows = rows_of(out)
    assert len(rows) == N_GOOD + 1 and len({r["file"] for r in rows}) == N_GOOD + 1
    assert rows[:2] == first
    assert {os.path.basename(r["file"]): r["status"] for r in rows}["broken.csv"] == "error"


def test_bad_study_requests_say_so(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["calibrate", str(tmp_path / "empty"), "--out", str(tmp_path / "r.csv")]) == 2
    assert "no recordings in this directory" in capsys.readouterr().err
    assert main(["calibrate", str(tmp_path / "empty")]) == 2
    assert "--out RESULTS.csv" in capsys.readouterr().err
    other = tmp_path / "other.csv"
    other.write_text("a,b\n1,2\n")
    (tmp_path / "x.csv").write_text("t,ax,ay,az\n")
    assert main(["calibrate", str(tmp_path / "x.csv"), "--out", str(other), "--workers", "0"]) == 2
    assert "not a gravcal results file" in capsys.readouterr().err


def test_ctrl_c_leaves_valid_results_and_resume_finishes(study, tmp_path):
    # enough files that the run cannot finish between its first row and the signal, however fast
    # a file is calibrated (hard links: the same recordings under other names)
    many = tmp_path / "many"
    many.mkdir()
    for i in range(N_LINKED):
        os.link(study / ("site2" if i % N_GOOD == 3 else "") / f"s{i % N_GOOD}.npy", many / f"r{i:02d}.npy")
    out = tmp_path / "results.csv"
    cmd = [sys.executable, "-m", "gravcal.cli.main", "calibrate", str(many), "--out", str(out), "--workers", "0",
           "--quiet"]
    # SIGINT at its default in the child, as in a terminal: a suite run as a background job (`cmd &` without
    # job control) inherits it ignored, and Python then keeps it ignored
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if out.exists() and out.read_text().count("\n") >= 2:  # header and one row
            break
        time.sleep(0.02)
    assert proc.poll() is None, "finished before it could be interrupted"
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    partial = rows_of(out)
    assert 1 <= len(partial) < N_LINKED
    assert out.read_text().endswith("\n")
    assert subprocess.run(cmd, capture_output=True, timeout=300).returncode == 0
    rows = rows_of(out)
    assert rows[: len(partial)] == partial
    assert sorted(r["file"] for r in rows) == sorted({r["file"] for r in rows}) and len(rows) == N_LINKED


def test_dask_workers_give_the_same_rows(study, tmp_path):
    seq, par = tmp_path / "seq.csv", tmp_path / "par.csv"
    assert main(["calibrate", str(study), "--out", str(seq), "--workers", "0", "--quiet"]) == 2
    assert main(["calibrate", str(study), "--out", str(par), "--workers", "2", "--quiet"]) == 2
    key = (lambda r: r["file"])
    assert sorted(rows_of(seq), key=key) == sorted(rows_of(par), key=key)


def test_the_daemon_never_imports_dask():
    code = ("import sys, gravcal.daemon.gravcald, gravcal.daemon.service, gravcal.cli.main; "
            "print([m for m in ('dask', 'distributed', 'tqdm') if m in sys.modules])")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == "[]", (r.stdout, r.stderr[-500:])


def test_an_existing_scheduler_runs_the_study(study, tmp_path, capsys):
    import dask.distributed as distributed  # the [study] extra, which [test] installs
    seq, par = tmp_path / "seq.csv", tmp_path / "sched.csv"
    files = [str(study / "s0.npy"), str(study / "broken.csv")]
    assert main(["calibrate", *files, "--out", str(seq), "--workers", "0", "--quiet"]) == 2
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0") as cluster:
        assert main(["calibrate", *files, "--out", str(par), "--scheduler", cluster.scheduler_address]) == 2
        assert f"(1 error, 1 ok; 2 on the scheduler at {cluster.scheduler_address})" in capsys.readouterr().err
    key = (lambda r: r["file"])
    assert sorted(rows_of(seq), key=key) == sorted(rows_of(par), key=key)


def test_a_task_that_dies_is_an_error_row_not_the_end(study, tmp_path, monkeypatch):
    import dask.distributed as distributed  # the [study] extra, which [test] installs
    from gravcal.io import study as study_mod

    real = study_mod.calibrate_file

    def dies_on_s1(path, opts):
        if path.endswith("s1.npy"):
            raise MemoryError("worker ran out of memory")
        return real(path, opts)

    monkeypatch.setattr(study_mod, "calibrate_file", dies_on_s1)
    out = tmp_path / "r.csv"
    files = [str(study / f"s{i}.npy") for i in range(3)]
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0") as cluster:
        assert main(["calibrate", *files, "--out", str(out), "--scheduler", cluster.scheduler_address, "--quiet"]) == 2
    status = {os.path.basename(r["file"]): (r["status"], r["message"]) for r in rows_of(out)}
    assert status["s1.npy"] == ("error", "MemoryError: worker ran out of memory")
    assert status["s0.npy"][0] == status["s2.npy"][0] == "ok"


def test_a_rerun_retries_error_rows_keys_by_resolved_path_and_starts_nothing_when_done(study, tmp_path, monkeypatch,
                                                                                      capsys):
    import shutil

    from gravcal.io import study as study_mod

    d = tmp_path / "d"
    d.mkdir()
    shutil.copy(study / "s0.npy", d / "a.npy")
    (d / "b.npy").write_bytes(b"not a recording at all")
    out = tmp_path / "r.csv"
    monkeypatch.chdir(d)  # relative paths, as typed in the study's folder
    assert main(["calibrate", "a.npy", "b.npy", "--out", str(out), "--workers", "0", "--quiet"]) == 2
    rows = rows_of(out)
    assert [(r["file"], r["status"]) for r in rows] == [(str(d / "a.npy"), "ok"), (str(d / "b.npy"), "error")]
    shutil.copy(study / "s1.npy", d / "b.npy")  # the broken file fixed
    monkeypatch.chdir(tmp_path)  # the same study from another folder
    assert main(["calibrate", "d", "--out", str(out), "--workers", "0", "--quiet"]) == 0
    rows = rows_of(out)
    assert [(r["file"], r["status"]) for r in rows] == [(str(d / "a.npy"), "ok"), (str(d / "b.npy"), "ok")]
    capsys.readouterr()
    monkeypatch.setattr(study_mod, "_results", lambda *a, **k: pytest.fail("a cluster for nothing"))
    assert main(["calibrate", str(d), "--out", str(out), "--workers", "2"]) == 0
    assert "0 file(s) calibrated (nothing new)" in capsys.readouterr().err
    assert len(rows_of(out)) == 2


def test_dask_worker_threads_give_the_same_rows_and_leave_the_log_level(study, tmp_path, monkeypatch, capsys):
    """One file here (the plan's timing), then (any saving worth Dask; its import run in this thread)
    the other three on Dask's two worker threads, two side by side: the rows are the in-process rows, and the gravcal logger's
    level, lowered while any file runs, is what it was before, also when the first of the two to start
    ends first (a per-file save and restore would leave it at the second one's saved ERROR)."""
    import logging
    import threading

    from gravcal.io import study as study_mod
    from gravcal.io import study_plan

    seq, par = tmp_path / "seq.csv", tmp_path / "par.csv"
    files = [str(study / f"s{i}.npy") for i in range(3)] + [str(study / "site2" / "s3.npy")]
    assert main(["calibrate", *files, "--out", str(seq), "--workers", "0", "--quiet"]) == 0
    main_thread, real, entered, lock = threading.get_ident(), study_mod._calibrate_file, [], threading.Lock()
    both_in, first_out = threading.Barrier(2), threading.Event()

    def overlapping(path, *args):  # in place of the part of calibrate_file inside its quiet logging
        if threading.get_ident() == main_thread:
            return real(path, *args)
        with lock:
            entered.append(threading.get_ident())
            k = len(entered)
        if k <= 2:
            both_in.wait(timeout=60)
        if k == 2:
            first_out.wait(timeout=60)
            time.sleep(0.2)  # for the first file's calibrate_file to restore the level after this returned
        try:
            return real(path, *args)
        finally:
            if k == 1:
                first_out.set()

    monkeypatch.setattr(study_plan.DaskStart, "start", study_plan.DaskStart.run)
    monkeypatch.setattr(study_plan, "DASK_START_S", -1.0)
    monkeypatch.setattr(study_plan, "forking", lambda: False)  # threads, where the platform cannot fork
    monkeypatch.setattr(study_mod, "_calibrate_file", overlapping)
    gravcal_log = logging.getLogger("gravcal")
    before = gravcal_log.level
    assert main(["calibrate", *files, "--out", str(par), "--workers", "2"]) == 0
    assert "1 in this process (one to time the plan, then while Dask was imported), 3 on 2 Dask worker threads" in \
        capsys.readouterr().err
    assert len(set(entered)) == 2 and main_thread not in entered
    assert gravcal_log.level == before
    key = (lambda r: r["file"])
    assert sorted(rows_of(seq), key=key) == sorted(rows_of(par), key=key)


def test_forked_dask_worker_processes_give_the_same_rows(study, tmp_path, monkeypatch, capsys):
    """One file here (the plan's timing), three on two worker processes forked from this one: the rows
    are the in-process rows, the broken file's error row included; no worker process is left."""
    import multiprocessing

    from gravcal.io import study_plan

    if not study_plan.forking():
        pytest.skip("worker processes are forked on Linux only")
    seq, par = tmp_path / "seq.csv", tmp_path / "par.csv"
    files = [str(study / f"s{i}.npy") for i in range(2)] + [str(study / "broken.csv"), str(study / "site2" / "s3.npy")]
    assert main(["calibrate", *files, "--out", str(seq), "--workers", "0", "--quiet"]) == 2
    monkeypatch.setattr(study_plan.DaskStart, "start", study_plan.DaskStart.run)
    monkeypatch.setattr(study_plan, "DASK_START_S", -1.0)
    monkeypatch.setattr(study_plan, "only_study_threads", lambda: True)  # earlier tests' Dask threads linger
    assert main(["calibrate", *files, "--out", str(par), "--workers", "2"]) == 2
    assert "1 in this process (one to time the plan, then while Dask was imported), 3 on 2 Dask worker " \
           "processes (forked)" in capsys.readouterr().err
    key = (lambda r: r["file"])
    assert sorted(rows_of(seq), key=key) == sorted(rows_of(par), key=key)
    assert not [p for p in multiprocessing.active_children() if p.name.startswith("ForkProcess")]


def test_workers_are_forked_only_from_a_process_running_no_thread_but_the_studys():
    import threading

    from gravcal.io import study_plan

    release = threading.Event()
    for name, expected in (("gravcal-blocks_0", True), ("a notebook's thread", False)):
        t = threading.Thread(target=release.wait, name=name, daemon=True)
        others = [x for x in threading.enumerate() if x is not threading.main_thread()
                  and not x.name.startswith(("gravcal-", "tqdm_monitor"))]
        t.start()
        try:
            assert study_plan.only_study_threads() is (expected and not others)
        finally:
            release.set()
            t.join()
            release.clear()


def test_a_small_study_runs_here_and_says_so(study, tmp_path, monkeypatch, capsys):
    from gravcal.io import study_plan

    files = [str(study / f"s{i}.npy") for i in range(3)]
    assert main(["calibrate", files[0], "--out", str(tmp_path / "one.csv"), "--workers", "2"]) == 0
    assert "1 file(s) calibrated (1 ok; all in this process: one file)" in capsys.readouterr().err
    monkeypatch.setattr(study_plan.DaskStart, "start", lambda self: pytest.fail("Dask for 0.1 s of work"))
    assert main(["calibrate", *files, "--out", str(tmp_path / "small.csv"), "--workers", "2"]) == 0
    err = capsys.readouterr().err
    saving = float(err.split("all in this process: two files at a time would save ~")[1].split(" s, ")[0])
    assert 0 <= saving < study_plan.DASK_START_S and " s left here, one file keeping " in err
    monkeypatch.setattr(study_plan, "DASK_START_S", -1.0)
    monkeypatch.setattr(study_plan.DaskStart, "start", study_plan.DaskStart.run)
    monkeypatch.setitem(sys.modules, "dask.threaded", None)  # dask not installed
    monkeypatch.setitem(sys.modules, "dask.multiprocessing", None)
    assert main(["calibrate", *files, "--out", str(tmp_path / "three.csv"), "--workers", "2"]) == 0
    err = capsys.readouterr().err
    assert "the study goes on in this process: no Dask: dask is not installed (pip install 'gravcal[study]')" in err
    assert "3 file(s) calibrated (3 ok; all in this process: no Dask: " in err
    assert [r["status"] for r in rows_of(tmp_path / "three.csv")] == ["ok", "ok", "ok"]


def test_the_plan_counts_only_idle_cores():
    """Two cores, one calibration keeping 1.2 busy: with the other 0.8 idle, a second file at a time takes
    them (4 s left -> 4 * 1.2 / 2.0 = 2.4 s, saving 1.6 s); with none idle it saves nothing; with a
    quiet machine and 0.5 core busy, the second thread can add 0.5 at most (saving half)."""
    from gravcal.io import study_plan

    jiffies = 1000.0  # the interval's CPU time over both cores, in jiffies
    saving, words = study_plan._threads_saving((0.0, 0.0, 0.0, 0.0), (1.0, 1.2, 0.4 * jiffies, jiffies), 2, 4.0, cores=2, online=2)
    assert saving == pytest.approx(1.6) and "~4.0 s left here, one file keeping 1.2 of 2 cores busy, 0.8 idle" == words
    saving, _ = study_plan._threads_saving((0.0, 0.0, 0.0, 0.0), (1.0, 1.2, 0.0, jiffies), 2, 4.0, cores=2, online=2)
    assert saving == 0.0
    saving, _ = study_plan._threads_saving((0.0, 0.0, 0.0, 0.0), (2.0, 1.0, 0.75 * 2 * jiffies, 2 * jiffies), 2, 3.0,
                                            cores=2, online=2)
    assert saving == pytest.approx(3.0)  # 6 s left, used 0.5, extra 0.5: half saved


def test_dask_threads_hand_each_row_over_as_it_finishes_and_a_raising_task_is_its_row():
    """worker_rows on threads: file a waits until the study has b's row (rows are written as files finish, so an
    interrupted study keeps them); c raises on its worker thread and becomes its error row."""
    import threading

    from gravcal.io import study_plan

    b_seen = threading.Event()

    def here(f, w):
        if f == "a":
            return {"file": f, "status": "ok", "b_first": b_seen.wait(timeout=30)}
        if f == "c":
            raise RuntimeError("boom")
        return {"file": f, "status": "ok"}

    def failed(f, exc):
        return {"file": f, "status": "error", "message": f"{type(exc).__name__}: {exc}"}

    rows = []
    for row in study_plan.worker_rows([("a", None), ("b", None), ("c", None)], here, 2, failed, processes=False):
        rows.append(row)
        if row["file"] == "b":
            b_seen.set()
    by_file = {r["file"]: r for r in rows}
    assert len(rows) == 3 and by_file["a"]["b_first"] is True
    assert by_file["c"] == {"file": "c", "status": "error", "message": "RuntimeError: boom"}
