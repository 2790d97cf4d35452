"""How a study runs on this machine: Dask worker threads, started while this process calibrates.

A calibration's heavy parts (the reading pass, detection, the fit's sums) run in C and numpy with the GIL
released, so threads of one process calibrate files side by side as well as worker processes would,
without their fixed cost: spawning two worker processes (each starting an interpreter and importing dask
and numpy again) took 1.6 s here and closing them 0.8 s, against 0.01-0.1 s each for a cluster of
threads. What stays fixed is importing dask.distributed: 0.7 s of a core on this machine when it is
quiet, more under load, taken from the calibrations running beside it (DASK_START_S).

The plan is measured, not guessed. The first file is calibrated here (it pays the numerics' imports),
the second here too, timed: its wall time, the CPU this process used (one calibration already keeps
part of a second core busy) and the cores the machine left idle meanwhile (/proc/stat). Calibrating two
files at a time can only use idle cores: the files left would take ``left`` here and about
``left * u / (u + extra)`` on the threads (u: cores one calibration used, extra: the idle cores a second
one could take, at most u). Only when that saving exceeds DASK_START_S does a background thread import
dask.distributed and start a LocalCluster of threads, while this process goes on calibrating files one
by one; once the cluster is up, the files left go to its threads, and a study done before that never
waits for it. One file, two files or one worker run here outright. ``Plan.summary`` says which plan ran
and why (-v logs the figures).
A worker thread that runs out of memory takes this process with it; the rows written so far stay, and a
re-run resumes from them (a cluster of worker processes: ``--scheduler``).
"""
from __future__ import annotations

import logging
import os
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Iterator

log = logging.getLogger(__name__)

Item = tuple[str, "str | None"]  # a recording and where its calibrated samples go (None: not written)
DASK_START_S = 1.0
"""What starting the cluster costs the study [s]: importing dask.distributed (0.7 s of a core on this
2-core machine, quiet; its bytecode holds the GIL the calibrations' Python parts need) and the threads."""


@dataclass
class Plan:
    """What ran where: files calibrated in this process, files on the cluster's threads, and why."""

    in_process: int = 0
    on_cluster: int = 0
    threads: int = 0
    reason: str = ""

    def summary(self) -> str:
        if self.threads:
            return (f"{self.in_process} in this process (two to time the plan, then while Dask started), "
                    f"{self.on_cluster} on {self.threads} Dask worker threads")
        if self.on_cluster:
            return f"{self.on_cluster} {self.reason}"  # an existing cluster: "on the scheduler at ADDRESS"
        return f"all in this process: {self.reason}" if self.reason else "all in this process"


class ClusterStart(threading.Thread):
    """Imports dask.distributed and starts a LocalCluster of ``threads`` worker threads and its client;
    ``ready`` is set when they are up or the start failed (``error``). ``cancel`` closes what started
    and stops a start still under way at its next step (an import cannot be interrupted)."""

    def __init__(self, threads: int) -> None:
        super().__init__(name="gravcal-dask-start", daemon=True)
        self.threads = threads
        self.ready = threading.Event()
        self.client: Any = None
        self.error: BaseException | None = None
        self._lock = threading.Lock()
        self._cancelled = False
        self._parts: list[Any] = []  # client, cluster: closed by cancel

    def run(self) -> None:
        try:
            from dask.distributed import Client, LocalCluster

            if logging.getLogger().level > logging.INFO:  # the cluster's start/stop chatter only with -v
                logging.getLogger("distributed").setLevel(logging.WARNING)
            with self._lock:
                if self._cancelled:
                    return
            cluster = LocalCluster(n_workers=1, threads_per_worker=self.threads, processes=False,
                                   dashboard_address=None)
            client = Client(cluster)
            with self._lock:
                self._parts = [client, cluster]
                if not self._cancelled:
                    self.client = client
                    return
            self._close()
        except BaseException as exc:  # noqa: BLE001 - reported to the study, which goes on without a cluster
            self.error = exc
        finally:
            self.ready.set()

    def cancel(self) -> None:
        with self._lock:
            self._cancelled = True
        self._close()

    def _close(self) -> None:
        with self._lock:
            parts, self._parts, self.client = self._parts, [], None
        for part in parts:
            try:
                part.close()
            except Exception as exc:  # noqa: BLE001 - closing a cluster whose work is done: nothing is lost
                log.debug("closing the study's Dask cluster: %s", exc)


def local_rows(items: list[Item], here: Callable[[str, "str | None"], dict],
               on_cluster: Callable[[Any, list[Item]], Iterator[dict]], workers: int, plan: Plan) -> Iterator[dict]:
    """The results rows of ``items`` (in the order they finish): ``here`` calibrates one in this process,
    ``on_cluster(client, items)`` yields the rows of a batch on the cluster; ``plan`` records what ran."""
    threads = min(workers, len(items))
    if threads <= 1:
        plan.reason = "one file" if len(items) <= 1 else "one worker"
        for f, w in items:
            yield here(f, w)
            plan.in_process += 1
        return
    pending = deque(items)
    yield here(*pending.popleft())  # the numerics' imports: not timed
    plan.in_process += 1
    if len(pending) < 2:
        plan.reason = f"{len(items)} files"
        while pending:
            yield here(*pending.popleft())
            plan.in_process += 1
        return
    timed = pending.popleft()
    before = _usage()
    row = here(*timed)
    plan.in_process += 1
    saving, figures = _threads_saving(before, _usage(), threads, _size_ratio(timed[0], [f for f, _ in pending]))
    yield row
    if saving <= DASK_START_S:
        plan.reason = (f"two files at a time would save ~{saving:.1f} s, less than starting Dask "
                       f"(~{DASK_START_S:g} s; {figures})")
        while pending:
            yield here(*pending.popleft())
            plan.in_process += 1
        return
    log.info("study plan: Dask worker threads, two files at a time saving ~%.1f s (%s)", saving, figures)
    start = ClusterStart(threads)
    start.start()
    try:
        while pending and not start.ready.is_set():
            f, w = pending.popleft()
            yield here(f, w)
            plan.in_process += 1
        if not pending:
            plan.reason = "done before a Dask cluster was up"
            return
        start.ready.wait()
        if start.client is None:
            plan.reason = ("no Dask: dask.distributed is not installed (pip install 'gravcal[study]')"
                           if isinstance(start.error, ImportError) else
                           f"no Dask cluster ({type(start.error).__name__}: {' '.join(str(start.error).split())})")
            log.warning("the study goes on in this process: %s", plan.reason)
            while pending:
                f, w = pending.popleft()
                yield here(f, w)
                plan.in_process += 1
            return
        plan.threads = threads
        with _blas_one_thread():
            for row in on_cluster(start.client, list(pending)):
                plan.on_cluster += 1
                yield row
    finally:
        start.cancel()


def _usage() -> tuple[float, float, float, float]:
    """(wall clock [s], this process's CPU [s], the machine's idle and total CPU time [jiffies]; both 0
    where /proc/stat cannot be read)."""
    idle = total = 0.0
    try:
        with open("/proc/stat", encoding="ascii") as f:
            fields = [float(x) for x in f.readline().split()[1:9]]  # user nice system idle iowait irq softirq steal
        idle, total = fields[3] + fields[4], sum(fields)
    except (OSError, ValueError, IndexError):
        pass
    return time.perf_counter(), time.process_time(), idle, total


def _threads_saving(before: tuple[float, ...], after: tuple[float, ...], threads: int, left_files: float
                    ) -> tuple[float, str]:
    """The wall time [s] calibrating ``threads`` files at a time would save on the files left (``left_files``
    of the timed one), from the timed file's usage; and the figures, as words."""
    wall = max(after[0] - before[0], 1e-9)
    used = max((after[1] - before[1]) / wall, 1e-3)  # cores this process kept busy
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    d_total = after[3] - before[3]
    idle = ((after[2] - before[2]) / d_total * (os.cpu_count() or 1)) if d_total > 0 else cores - used
    idle = min(max(idle, 0.0), max(cores - used, 0.0))
    extra = min(idle, (threads - 1) * used)
    left = wall * left_files
    saving = left * extra / (used + extra)
    return saving, (f"~{left:.1f} s left here, one file keeping {used:.1f} of {cores} cores busy, "
                    f"{idle:.1f} idle")


def _size_ratio(first: str, rest: list[str]) -> float:
    """The files ``rest`` together over the file ``first``, in bytes (a file that cannot be sized counts as
    one like the first): the calibrating time scales with the samples."""
    def size(f: str) -> float:
        try:
            return float(os.path.getsize(f))
        except OSError:
            return -1.0

    one = size(first)
    if one <= 0:
        return float(len(rest))
    return sum(s / one if s >= 0 else 1.0 for s in map(size, rest))


def _blas_one_thread() -> Any:
    """One BLAS thread for the whole threaded section: each calibration limits BLAS itself
    (core.pipeline), and limits set and restored by overlapping threads would leave the process's
    setting at whichever thread restored last."""
    from contextlib import nullcontext

    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - a dependency
        return nullcontext()
    return threadpool_limits(limits=1, user_api="blas")
