"""The windows gravcald fed to the online calibrator, one JSON line each (``gravcald --record-windows``).

Replaying them through ``OnlineCalibrator.feed`` in process makes the service's decisions again: the
policy is in core, the daemon only feeds windows (tests/system/test_replay_decisions.py holds it to that).
Floats are written with ``repr`` precision (JSON), so a replay sees the very same numbers.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import IO

import numpy as np

from ..core.windows import Window
from ..jsonbounds import loads as bounded_loads

log = logging.getLogger("gravcal.gravcald")

WINDOW_CLASS = "WINDOW"


def window_record(w: Window) -> dict:
    return {"class": WINDOW_CLASS, "start": int(w.start), "end": int(w.end), "t_start": float(w.t_start),
            "t_end": float(w.t_end), "mean": np.asarray(w.mean, float).tolist(),
            "cov": np.asarray(w.cov, float).tolist(), "aux_mean": np.asarray(w.aux_mean, float).tolist()}


def window_from_record(d: dict) -> Window:
    return Window(int(d["start"]), int(d["end"]), float(d["t_start"]), float(d["t_end"]),
                  np.asarray(d["mean"], float), np.asarray(d["cov"], float), np.asarray(d["aux_mean"], float))


class WindowRecorder:
    """Appends each window as one line and flushes it, so a stopped or killed daemon leaves whole lines.
    A write that fails (disk full) is logged once and recording stops; the service goes on."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._file: IO[str] | None = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 (closed in close())

    def __call__(self, w: Window) -> None:
        if self._file is None:
            return
        try:
            self._file.write(json.dumps(window_record(w)) + "\n")
            self._file.flush()
        except OSError as exc:
            log.error("recording windows to %s stopped: %s", self.path, exc)
            self.close()

    def close(self) -> None:
        if self._file is not None:
            try:
                self._file.close()
            except OSError:
                pass
            self._file = None


def read_windows(path: str | Path) -> list[Window]:
    """The recorded windows in order; a line that is not a whole WINDOW record (a torn last line) ends the
    list with a ValueError naming its number."""
    out = []
    with open(path, encoding="utf-8") as f:
        for i, line in enumerate(f, 1):
            try:
                d = bounded_loads(line)  # a JSONInputError is a ValueError
                if not isinstance(d, dict) or d.get("class") != WINDOW_CLASS:
                    raise ValueError("not a WINDOW record")
                out.append(window_from_record(d))
            except (ValueError, KeyError, TypeError) as exc:
                raise ValueError(f"{path}: line {i} is not a window record ({type(exc).__name__})") from None
    return out
