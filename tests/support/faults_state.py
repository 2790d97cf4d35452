"""kill -9 while the calibration state is written: every load afterwards finds a whole state."""
from __future__ import annotations

import os
import signal
import tempfile
import time
from pathlib import Path

import numpy as np


def _state(revision: int, rng: np.random.Generator):
    from gravcal.core.calibration import Calibration
    from gravcal.daemon.persistence import CalibrationState

    cal = Calibration.nominal(0.5 + 0.01 * rng.standard_normal(3), 0.04 * (1 + 0.01 * rng.standard_normal(3)), model="6")
    # a realistic size: the estimator's extra state (a 12x12 covariance and a window pool)
    extra = {"cov": rng.standard_normal((12, 12)).tolist(), "pool": rng.standard_normal((300, 4)).tolist()}
    return CalibrationState(cal, revision=revision, updated=time.time(), accepted=True, extra=extra)


def run_state_kill(kills: int = 60, *, seed: int = 0, directory: str | None = None, max_delay_s: float = 0.03) -> dict:
    """Fork a writer that saves revisions 1, 2, 3, ... through StateStore in a loop; SIGKILL it
    at a random moment; load. Every load must give a complete state whose revision is the last
    one the writer finished or the one it was writing (old or new), never a corrupt file; the
    temp file an interrupted save leaves is removed by the next load (never accumulates)."""
    from gravcal.daemon.persistence import StateStore

    rng = np.random.default_rng(seed)
    tmp = tempfile.TemporaryDirectory(prefix="gravcal-kill-") if directory is None else None
    root = Path(directory or tmp.name)
    store = StateStore(root)
    store.save(_state(1, rng))
    progress = root / "progress"  # the writer notes each revision it finished (O_APPEND, 8 bytes)
    figures = {"kills": 0, "loads_ok": 0, "loads_corrupt": 0, "loaded_old": 0, "loaded_new": 0,
               "temps_left_by_kills": 0, "max_temps_seen": 0, "temps_after_load": 0, "moved_aside": 0,
               "revision_out_of_range": 0, "writes_completed": 0}
    revision = 1
    states = [_state(r, rng) for r in range(8)]  # pre-built: the child only serialises and writes
    for k in range(kills):
        start_rev = revision + 1
        pid = os.fork()
        if pid == 0:  # the writer: never returns
            try:
                fd = os.open(progress, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
                r = start_rev
                while True:
                    st = states[r % len(states)]
                    st.revision = r
                    store.save(st)
                    os.write(fd, r.to_bytes(8, "little"))
                    r += 1
            finally:
                os._exit(1)
        time.sleep(float(rng.uniform(0, max_delay_s)))
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        figures["kills"] += 1
        done = progress.read_bytes() if progress.exists() else b""
        finished = int.from_bytes(done[-8:], "little") if len(done) >= 8 else revision
        if progress.exists():
            progress.unlink()
        figures["writes_completed"] += max(0, finished - revision)
        temps = [n for n in os.listdir(root) if n.startswith(".state.json.") and n.endswith(".tmp")]
        figures["temps_left_by_kills"] += bool(temps)
        figures["max_temps_seen"] = max(figures["max_temps_seen"], len(temps))
        res = store.load()
        if res.state is None:
            figures["loads_corrupt"] += 1
            figures["moved_aside"] += res.moved_to is not None
            store.save(_state(finished, rng))  # carry on from a good file
            revision = finished
            continue
        figures["loads_ok"] += 1
        got = res.state.revision
        # old = the last revision whose write returned; new = the one being written (its rename
        # may have happened just before the kill, after which the progress note was not written)
        if got == finished:
            figures["loaded_old"] += 1
        elif got == finished + 1:
            figures["loaded_new"] += 1
        else:
            figures["revision_out_of_range"] += 1
        revision = got
        figures["temps_after_load"] += sum(1 for n in os.listdir(root) if n.endswith(".tmp"))
    if tmp is not None:
        tmp.cleanup()
    return figures
