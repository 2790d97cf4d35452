"""BLAS limited to one thread for a calibration's small products (windows x 3, 3 x 3, 3 x 3P)."""
from __future__ import annotations

import functools
import os
from typing import Any

import numpy as np


def blas_started_single_threaded() -> bool:
    """numpy's OpenBLAS was started with one thread: OPENBLAS_NUM_THREADS=1 in the environment, which
    ``gravcal calibrate`` sets before numpy loads (cli/main.py ``console``). Then nothing needs
    limiting, and threadpoolctl's import and library scan (~14 ms) are skipped."""
    if os.environ.get("OPENBLAS_NUM_THREADS", "").strip() != "1":
        return False
    try:
        return "openblas" in str(np.__config__.CONFIG["Build Dependencies"]["blas"]["name"]).lower()
    except (AttributeError, KeyError, TypeError):  # another numpy build: ask threadpoolctl
        return False


def single_threaded_blas(fn: Any) -> Any:
    """Run ``fn`` with BLAS limited to one thread. Every BLAS product of a calibration is small
    (windows x 3, 3 x 3, 3 x 3P): OpenBLAS's threads cost more in hand-off and spinning than they
    save (the week's fit: 3.6 -> 1.4 CPU-s), and the block pass runs its own two threads."""

    @functools.wraps(fn)
    def run(*args: Any, **kwargs: Any) -> Any:
        if blas_started_single_threaded():
            return fn(*args, **kwargs)
        try:
            from threadpoolctl import threadpool_limits
        except ImportError:  # pragma: no cover - a dependency; without it BLAS keeps its threads
            return fn(*args, **kwargs)
        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return run
