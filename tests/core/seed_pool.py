"""Independent per-seed sessions of the statistical tests, spread over the machine's cores.

Each seed's session is deterministic and independent of the others, so the results (and the assertions on
them) are the same as a plain loop; only the wall time changes. ``GRAVCAL_TEST_WORKERS=1`` forces the loop
(e.g. under pytest-xdist, which already uses the cores). The mapped function must be module-level and return
plain picklable values.
"""
from __future__ import annotations

import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor


def workers() -> int:
    if os.environ.get("PYTEST_XDIST_WORKER"):
        return 1
    env = os.environ.get("GRAVCAL_TEST_WORKERS")
    if env:
        return max(1, int(env))
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return min(2, cores)  # the suite's reference machine has two cores; more would only oversubscribe it


_BLAS_LIMIT = None  # a worker's threadpoolctl limit, kept for the worker's life


def one_blas_thread() -> None:
    """Pool initializer: BLAS limited to one thread in the worker. The workers already fill the cores, and the
    sessions' products are small (windows x parameters): OpenBLAS's own threads only spin against the other
    worker (measured: a diagnosis session 1.3-1.5 CPU-s with two BLAS threads, 0.8-1.1 with one, the same wall
    time alone; the 316 diagnose outputs of the diagnosis tests' sessions are identical bit for bit)."""
    global _BLAS_LIMIT
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # a dependency; without it BLAS keeps its threads
        return
    _BLAS_LIMIT = threadpool_limits(limits=1, user_api="blas")


def pmap(fn, args: list[tuple]) -> list:
    """``[fn(*a) for a in args]``, in order, on up to ``workers()`` forked processes (one BLAS thread each)."""
    n = min(workers(), len(args))
    if n <= 1 or "fork" not in mp.get_all_start_methods():
        return [fn(*a) for a in args]
    with ProcessPoolExecutor(n, mp_context=mp.get_context("fork"), initializer=one_blas_thread) as pool:
        return list(pool.map(fn, *zip(*args)))
