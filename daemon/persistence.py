"""The daemon's calibration state on disk: atomic, rate-limited, corruption-tolerant.

File: ``<state dir>/state.json`` (schema "gravcal.state/1")::

    {"schema": "gravcal.state/1", "revision": 12, "updated": 1717171717.2, "saved": ...,
     "accepted": true, "model": "6", "calibration": {<gravcal.calibration/1>}, "extra": {...}}

Writes are atomic (temp file in the same directory, fsync, rename over, fsync the
directory), so a crash or power cut at any instant leaves either the old or the new file,
never a torn one. A file that cannot be read or parsed is moved aside to
``state.json.corrupt-<UTC time>`` and the daemon starts from its defaults, saying so.
Writes happen in a background thread at most once per ``min_interval_s``: an SD card that
stalls on fsync delays the save, never the samples.
"""
from __future__ import annotations

import json
import logging
import os
import tempfile
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ..core.calibration import SCHEMA as CALIBRATION_SCHEMA
from ..core.calibration import Calibration
from ..errors import InputError
from ..jsonbounds import MAX_BYTES, JSONInputError
from ..jsonbounds import loads as bounded_loads

log = logging.getLogger("gravcal.persistence")

STATE_SCHEMA = "gravcal.state/1"
STATE_FILENAME = "state.json"


class StateError(ValueError):
    """The state file is unusable (the message says why)."""


@dataclass
class CalibrationState:
    """What survives a restart: the calibration (parameters, covariance, model order),
    its revision (incremented on every accepted update), the Unix time [s] of the last
    update, and any extra JSON-able data (e.g. the estimator's internal state)."""

    calibration: Calibration
    revision: int = 0
    updated: float | None = None
    accepted: bool = False
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def model(self) -> str:
        return self.calibration.model

    def to_dict(self) -> dict[str, Any]:
        return {
            "schema": STATE_SCHEMA,
            "revision": int(self.revision),
            "updated": self.updated,
            "saved": time.time(),
            "accepted": bool(self.accepted),
            "model": self.calibration.model,
            "calibration": self.calibration.to_dict(),
            "extra": _jsonable(self.extra),
        }

    @classmethod
    def from_dict(cls, d: Any) -> "CalibrationState":
        if not isinstance(d, dict):
            raise StateError("state must be a JSON object")
        if d.get("schema") != STATE_SCHEMA:
            raise StateError(f"not a gravcal state file (schema {d.get('schema')!r}, expected {STATE_SCHEMA!r})")
        try:
            cal = Calibration.from_dict(d["calibration"])
        except KeyError:
            raise StateError("state has no 'calibration'") from None
        except (ValueError, TypeError) as exc:
            raise StateError(f"state calibration: {exc}") from exc
        revision, updated, extra = d.get("revision", 0), d.get("updated"), d.get("extra", {})
        if isinstance(revision, bool) or not isinstance(revision, int) or revision < 0:
            raise StateError(f"state 'revision' must be a non-negative integer, got {revision!r}")
        if updated is not None and (isinstance(updated, bool) or not isinstance(updated, (int, float))):
            raise StateError(f"state 'updated' must be a Unix time or null, got {updated!r}")
        if not isinstance(extra, dict):
            raise StateError("state 'extra' must be an object")
        return cls(cal, revision, None if updated is None else float(updated), bool(d.get("accepted", False)), extra)


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return _jsonable(x.item())
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


# -- atomic files --------------------------------------------------------------------


def fsync_dir(directory: str) -> None:
    """Make a rename in ``directory`` durable."""
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def make_directories_durable(directory: str | os.PathLike, mode: int = 0o750) -> None:
    """``os.makedirs(directory, exist_ok=True)``, then fsync the parent of each directory it created, top
    down: a new directory is an entry in its parent, lost in a power cut like an unsynced rename."""
    path = os.path.abspath(directory)
    created = []
    while not os.path.isdir(path) and os.path.dirname(path) != path:
        created.append(path)
        path = os.path.dirname(path)
    os.makedirs(directory, mode=mode, exist_ok=True)
    for new in reversed(created):
        fsync_dir(os.path.dirname(new))


def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, mode: int = 0o640) -> None:
    """Replace ``path`` with ``data`` atomically: temp file in the same directory, fsync,
    rename over the target, fsync the directory."""
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(dir=directory, prefix="." + os.path.basename(path) + ".", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    fsync_dir(directory)


def write_state(path: str | os.PathLike, state: CalibrationState) -> None:
    data = json.dumps(state.to_dict(), indent=1, allow_nan=False).encode() + b"\n"
    atomic_write_bytes(path, data)


def read_state(path: str | os.PathLike) -> CalibrationState:
    """Parse a state file; StateError (or OSError for I/O) when unusable."""
    with open(path, "rb") as fh:
        raw = fh.read(MAX_BYTES + 1)
    try:
        d = bounded_loads(raw)
    except JSONInputError as exc:
        raise StateError(str(exc)) from None
    return CalibrationState.from_dict(d)


# -- lab calibration -----------------------------------------------------------------


def calibration_from_json_dict(d: Any, source: str) -> Calibration:
    """A Calibration from a gravcal calibration JSON object, a state file, or the
    ``gravcal calibrate --json`` report (which holds the calibration itself, or the
    model/offset/sensitivity fields at top level)."""
    if not isinstance(d, dict):
        raise InputError(f"{source}: expected a JSON object with a calibration")
    try:
        if d.get("schema") == CALIBRATION_SCHEMA:
            return Calibration.from_dict(d)
        if d.get("schema") == STATE_SCHEMA:
            return CalibrationState.from_dict(d).calibration
        inner = d.get("calibration")
        if isinstance(inner, dict) and inner.get("schema") == CALIBRATION_SCHEMA:
            return Calibration.from_dict(inner)
        if {"model", "offset", "sensitivity"} <= d.keys():
            # A report without the embedded object: rebuild it, stds as a diagonal covariance.
            std = d.get("std") or {}
            names = list(std) if isinstance(std, dict) else []
            cov = np.diag([float(std[n]) ** 2 for n in names]) if names else np.zeros((0, 0))
            return Calibration.from_dict(
                {
                    "schema": CALIBRATION_SCHEMA,
                    "model": d["model"],
                    "offset": d["offset"],
                    "sensitivity": d["sensitivity"],
                    "param_names": names,
                    "covariance": cov.tolist(),
                    "n_windows": d.get("n_windows", 0),
                    "converged": d.get("converged", True),
                    "observable": d.get("observable", True),
                    "message": d.get("message", ""),
                    "metadata": d.get("metadata", {}),
                }
            )
    except (ValueError, TypeError, StateError) as exc:
        raise InputError(f"{source}: {exc}") from exc
    raise InputError(
        f"{source}: not a gravcal calibration (expected the JSON of `gravcal calibrate --lab --json` "
        f"or a {CALIBRATION_SCHEMA} object)"
    )


def load_lab_calibration(path: str | os.PathLike) -> Calibration:
    """The calibration in a file written by ``gravcal calibrate --lab --json``."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as fh:
            text = fh.read(MAX_BYTES + 1)
    except FileNotFoundError:
        raise InputError(f"{path}: no such calibration file") from None
    except PermissionError:
        raise InputError(f"{path}: permission denied") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a directory, expected a calibration JSON file") from None
    try:
        d = bounded_loads(text)
    except JSONInputError as exc:
        raise InputError(f"{path}: {exc}") from None
    return calibration_from_json_dict(d, path)


# -- the store -----------------------------------------------------------------------


@dataclass
class LoadResult:
    """``state`` is None when nothing usable was found; ``notes`` say what happened."""

    state: CalibrationState | None
    notes: list[str] = field(default_factory=list)
    moved_to: str | None = None


class StateStore:
    """``<directory>/state.json``: load at start (tolerating corruption), save atomically."""

    def __init__(self, directory: str | os.PathLike, filename: str = STATE_FILENAME):
        self.directory = os.fspath(directory)
        self.path = os.path.join(self.directory, filename)
        self._create_on_save = False

    def ensure_directory(self) -> None:
        self._create_on_save = False
        try:
            make_directories_durable(self.directory, mode=0o750)
        except OSError as exc:
            raise InputError(f"state directory {self.directory}: cannot create it: {exc.strerror or exc}") from exc
        if not os.access(self.directory, os.W_OK | os.X_OK):
            raise InputError(f"state directory {self.directory}: not writable by this user")

    def check_directory(self) -> None:
        """Fail now if the directory could not be written, without creating it: a start that fails
        later (no device, socket in use) leaves nothing behind; the first save creates it."""
        path = os.path.abspath(self.directory)
        self._create_on_save = not os.path.isdir(path)
        if os.path.isdir(path):
            if not os.access(path, os.W_OK | os.X_OK):
                raise InputError(f"state directory {self.directory}: not writable by this user")
            return
        parent = path
        while not os.path.exists(parent):
            parent = os.path.dirname(parent)
        if not os.path.isdir(parent):
            raise InputError(f"state directory {self.directory}: cannot create it: {parent} is not a directory")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise InputError(f"state directory {self.directory}: cannot create it: {parent} is not writable by this user")

    def _remove_leftover_temps(self) -> None:
        prefix = "." + os.path.basename(self.path) + "."
        try:
            names = os.listdir(self.directory)
        except OSError:
            return
        for name in names:
            if name.startswith(prefix) and name.endswith(".tmp"):
                try:
                    os.unlink(os.path.join(self.directory, name))
                    log.info("removed %s left by an interrupted save", name)
                except OSError:
                    pass

    def load(self) -> LoadResult:
        """The saved state, or None with notes. A corrupt file is moved aside, never deleted."""
        self._remove_leftover_temps()
        try:
            state = read_state(self.path)
        except FileNotFoundError:
            return LoadResult(None, [f"no saved state at {self.path}"])
        except (StateError, OSError) as exc:
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            aside = self._move_aside()
            if aside:
                note = f"state file {self.path} is unusable ({why}); moved it to {aside}; starting from defaults"
            else:
                note = f"state file {self.path} is unusable ({why}) and could not be moved aside; starting from defaults"
            log.warning("%s", note)
            return LoadResult(None, [note], aside)
        note = f"resumed calibration revision {state.revision} (model {state.model}) from {self.path}"
        return LoadResult(state, [note])

    def _move_aside(self) -> str | None:
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        target = f"{self.path}.corrupt-{stamp}"
        n = 1
        while os.path.lexists(target):
            n += 1
            target = f"{self.path}.corrupt-{stamp}-{n}"
        try:
            os.rename(self.path, target)
        except OSError as exc:
            log.error("cannot move unusable state file %s aside: %s", self.path, exc)
            return None
        return target

    def save(self, state: CalibrationState) -> None:
        if self._create_on_save:  # checked at start, created now; one that vanishes later is an error
            self.ensure_directory()
            self._create_on_save = False
        write_state(self.path, state)


class RateLimitedSaver:
    """Saves the newest offered state at most once per ``min_interval_s``, in its own thread.

    ``offer`` never blocks on disk. ``flush`` (at shutdown) writes what is pending now and
    waits for it. Failed writes are logged and retried at the next interval.
    """

    def __init__(self, store: StateStore, min_interval_s: float = 60.0, *, clock: Callable[[], float] = time.monotonic):
        self.store = store
        self.min_interval_s = float(min_interval_s)
        self._clock = clock
        self._cond = threading.Condition()
        self._pending: CalibrationState | None = None
        self._last_save = -float("inf")
        self._writing = False
        self._closed = False
        self.saves = 0
        self.failures = 0
        self.last_error: str | None = None
        self._thread = threading.Thread(target=self._run, name="gravcal-saver", daemon=True)
        self._thread.start()

    def offer(self, state: CalibrationState) -> None:
        with self._cond:
            self._pending = state
            self._cond.notify()

    def _write(self, state: CalibrationState) -> None:
        try:
            self.store.save(state)
            self.saves += 1
            self.last_error = None
        except Exception as exc:  # disk full, read-only fs: keep running, retry later
            self.failures += 1
            self.last_error = str(exc)
            log.error("cannot save state to %s: %s", self.store.path, exc)
            with self._cond:
                if self._pending is None:
                    self._pending = state

    def _run(self) -> None:
        with self._cond:
            while not self._closed:
                if self._pending is None:
                    self._cond.wait()
                    continue
                wait = self._last_save + self.min_interval_s - self._clock()
                if wait > 0:
                    self._cond.wait(wait)
                    continue
                state, self._pending = self._pending, None
                self._writing = True
                self._last_save = self._clock()
                self._cond.release()
                try:
                    self._write(state)
                finally:
                    self._cond.acquire()
                    self._writing = False
                    self._cond.notify_all()

    def flush(self, timeout: float = 10.0) -> bool:
        """Write the pending state now (ignoring the interval); True when nothing is left unsaved."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._writing:
                if not self._cond.wait(max(0.0, deadline - time.monotonic())):
                    return False
            state, self._pending = self._pending, None
            if state is None:
                return True
            self._writing = True
        try:
            self._write(state)
        finally:
            with self._cond:
                self._writing = False
                self._last_save = self._clock()
                self._cond.notify_all()
        return self.last_error is None

    def close(self, timeout: float = 10.0) -> bool:
        ok = self.flush(timeout)
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        self._thread.join(timeout)
        return ok
