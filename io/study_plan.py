"""How a study runs on this machine: Dask's local scheduler, its workers started while this process
calibrates: worker processes forked from this one (Linux), else worker threads.

Forked processes, because a calibration holds the GIL for about half its wall time (py-spy --gil over
ten one-day files: 4.6 s of 8.9 s; the fit's estimators, detection's and the reading pass's Python
between the C kernels), so two files on threads of one process queue for it: on the quiet machine 20
one-day files, 16-17 of them on two threads (a LocalCluster's), ran at 0.82-0.84x the in-process API
loop, as 8 files calibrated in one process did (0.84x): the threads gained nothing. Forking costs
~0.01-0.05 s (the worker starts with everything this process imported), where spawning a worker (a
dask.distributed LocalCluster of processes: an interpreter importing dask and numpy again) took 1.6 s
here and closing them 0.8 s. The scheduler is Dask's own local one (dask.multiprocessing, or
dask.threaded where the platform cannot fork), not a dask.distributed LocalCluster: that one costs 0.25
s of a core to import and start (against 0.09 s) and runs its scheduler, event loop and system monitor
as Python in this process, beside the calibrations (process CPU for 19 one-day files on two threads,
load 8-12: 5.2-5.3 s with a LocalCluster of threads, 4.6-4.7 s with dask.threaded, 4.4-4.6 s in one
thread). A cluster, for studies larger than one machine: ``--scheduler``.

The plan is measured, not guessed. The first file is calibrated here, timed: its wall time, the CPU this
process used (one calibration already keeps part of a second core busy) and the cores the machine left
idle meanwhile (/proc/stat). It also pays the numerics' first imports (~0.1 s of one core against ~0.2 s
of CPU for a one-day file at 100 Hz), which makes the saving below look larger than it is by up to that
share; timing the second file instead kept one more file off the workers. Calibrating two files at a
time can only use idle cores: the files left would take ``left`` here and about
``left * u / (u + extra)`` on the workers (u: cores one calibration used, extra: the idle cores a second
one could take, at most u). Only when that saving exceeds DASK_START_S does a background thread import
Dask while this process goes on calibrating files one by one; once imported, the files left go to the
workers, and a study done before that never waits for it. One file, two files or one worker run here
outright. ``Plan.summary`` says which plan ran and why (-v logs the figures).
A worker process killed (out of memory) ends the study with that error, a worker thread the whole
process; the rows written so far stay, and a re-run resumes from them.
"""
from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Iterator

log = logging.getLogger(__name__)

Item = tuple[str, "str | None"]  # a recording and where its calibrated samples go (None: not written)
DASK_START_S = 0.2
"""What starting the workers costs the study [s]: importing dask and its local scheduler (0.09 s of a core
on this 2-core machine, quiet; its bytecode holds the GIL the calibration beside it needs) and forking,
doubled for a loaded machine."""


@dataclass
class Plan:
    """What ran where: files calibrated in this process, on Dask's local workers (``threads`` of them) or on a
    cluster (``--scheduler``: ``on_cluster`` with the reason naming it), and why."""

    in_process: int = 0
    on_cluster: int = 0
    threads: int = 0  # Dask's local workers: threads, or forked processes
    processes: bool = False
    reason: str = ""

    def summary(self) -> str:
        if self.threads:
            return (f"{self.in_process} in this process (one to time the plan, then while Dask was imported), "
                    f"{self.on_cluster} on {self.threads} Dask worker "
                    f"{'processes (forked)' if self.processes else 'threads'}")
        if self.on_cluster:
            return f"{self.on_cluster} {self.reason}"  # an existing cluster: "on the scheduler at ADDRESS"
        return f"all in this process: {self.reason}" if self.reason else "all in this process"


class DaskStart(threading.Thread):
    """Imports Dask's local scheduler (dask.multiprocessing with ``processes``, else dask.threaded) in the
    background; ``ready`` is set when it is imported or the import failed (``error``; ``ok`` False). The
    import cannot be interrupted: ``cancel`` only makes a late success count for nothing."""

    def __init__(self, processes: bool = False) -> None:
        super().__init__(name="gravcal-dask-import", daemon=True)
        self.processes = processes
        self.ready = threading.Event()
        self.ok = False
        self.error: BaseException | None = None
        self._cancelled = False

    def run(self) -> None:
        try:
            import importlib

            importlib.import_module("dask.multiprocessing" if self.processes else "dask.threaded")
            self.ok = not self._cancelled
        except BaseException as exc:  # noqa: BLE001 - reported to the study, which goes on without Dask
            self.error = exc
        finally:
            self.ready.set()

    def cancel(self) -> None:
        self._cancelled = True


def forking() -> bool:
    """Whether worker processes can be forked from this one (Linux): a fork starts with everything this
    process has imported, in ~0.01-0.05 s, where a spawned interpreter imports numpy and gravcal again."""
    import multiprocessing

    return sys.platform.startswith("linux") and "fork" in multiprocessing.get_all_start_methods()


def only_study_threads() -> bool:
    """Whether every other live thread of this process is the study's own (gravcal-*, its progress bar's
    monitor): a fork copies only the forking thread, and a lock another thread holds at that moment stays
    held in the worker. A process with threads of its own (a notebook's, a server's) gets worker
    threads instead."""
    main = threading.main_thread()
    return all(t is main or not t.is_alive() or t.name.startswith(("gravcal-", "tqdm_monitor"))
               for t in threading.enumerate())


def _ignore_sigint() -> None:
    """A worker process leaves Ctrl-C to the study, which ends it (no traceback from a worker)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def worker_rows(items: list[Item], here: Callable[[str, "str | None"], dict], workers: int,
                failed: Callable[[str, BaseException], dict], processes: bool) -> Iterator[dict]:
    """The rows of ``items`` calibrated ``workers`` at a time by Dask's local scheduler, yielded here as
    they finish; a task that raises is ``failed``'s row. ``processes``: Dask's multiprocessing scheduler
    on worker processes forked from this one (each file's Python runs under its own GIL; ``here`` goes
    by cloudpickle); else its threaded scheduler (worker threads of this process). The scheduler runs in
    a background thread: this generator only waits for rows. Closed early (Ctrl-C, an error writing
    rows), the files not started are dropped and the worker processes are ended."""
    import queue

    finished: queue.SimpleQueue = queue.SimpleQueue()
    done = object()

    def task(f: str, w: "str | None") -> dict:
        try:
            return here(f, w)
        except Exception as exc:  # noqa: BLE001 - one file's failure is its row, not the study's end
            return failed(f, exc)

    def posttask(key: Any, result: Any, dsk: Any, state: Any, worker_id: Any) -> None:
        finished.put(result)

    graph = {("gravcal-calibrate", i): (task, f, w) for i, (f, w) in enumerate(items)}
    # this computation's callbacks only (start, start_state, pretask, posttask, finish): none registered
    # for the process, where the caller's own Dask work would see them
    callbacks = [(None, None, None, posttask, None)]
    if processes:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        import dask.multiprocessing

        pool: Any = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork"),
                                        initializer=_ignore_sigint)

        def compute() -> None:  # one file per task (chunksize 1): rows as they finish, even shares
            dask.multiprocessing.get(graph, list(graph), pool=pool, callbacks=callbacks, chunksize=1,
                                     optimize_graph=False)
    else:
        from concurrent.futures import ThreadPoolExecutor

        import dask.threaded

        pool = ThreadPoolExecutor(workers, thread_name_prefix="gravcal-dask")

        def compute() -> None:
            dask.threaded.get(graph, list(graph), pool=pool, callbacks=callbacks)

    def run() -> None:
        try:
            compute()
        except BaseException as exc:  # noqa: BLE001 - the scheduler's own failure (a worker process killed)
            finished.put(exc)
        finally:
            finished.put(done)

    runner = threading.Thread(target=run, name="gravcal-dask-scheduler", daemon=True)
    runner.start()
    ended = False
    try:
        while (got := finished.get()) is not done:
            if isinstance(got, BaseException):
                raise got
            yield got
        ended = True
    finally:
        pool.shutdown(wait=ended, cancel_futures=True)
        if processes and not ended:
            import multiprocessing

            for child in multiprocessing.active_children():  # its files are dropped, as unstarted ones
                if child.name.startswith("ForkProcess"):
                    child.terminate()


def local_rows(items: list[Item], here: Callable[[str, "str | None"], dict],
               failed: Callable[[str, BaseException], dict], workers: int, plan: Plan,
               processes: bool | None = None) -> Iterator[dict]:
    """The results rows of ``items`` (in the order they finish): ``here`` calibrates one in this process
    (never raising), ``failed(file, exc)`` is the row of a worker's task that raised; ``plan`` records
    what ran. ``processes``: forked worker processes (default where the platform forks and no thread but
    the study's runs) or threads."""
    processes = forking() and only_study_threads() if processes is None else processes
    threads = min(workers, len(items))
    if threads <= 1:
        plan.reason = "one file" if len(items) <= 1 else "one worker"
        for f, w in items:
            yield here(f, w)
            plan.in_process += 1
        return
    pending = deque(items)
    if len(pending) < 3:
        plan.reason = f"{len(items)} files"
        while pending:
            yield here(*pending.popleft())
            plan.in_process += 1
        return
    timed = pending.popleft()
    before = _usage()
    row = here(*timed)  # with the numerics' first imports: ~0.1 s of one core, counted as the file's
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
    log.info("study plan: Dask workers, two files at a time saving ~%.1f s (%s)", saving, figures)
    start = DaskStart(processes)
    start.start()
    try:
        while pending and not start.ready.is_set():
            f, w = pending.popleft()
            yield here(f, w)
            plan.in_process += 1
        if not pending:
            plan.reason = "done before Dask was imported"
            return
        start.ready.wait()
        if not start.ok:
            plan.reason = ("no Dask: dask is not installed (pip install 'gravcal[study]')"
                           if isinstance(start.error, ImportError) else
                           f"no Dask ({type(start.error).__name__}: {' '.join(str(start.error).split())})")
            log.warning("the study goes on in this process: %s", plan.reason)
            while pending:
                f, w = pending.popleft()
                yield here(f, w)
                plan.in_process += 1
            return
        plan.threads, plan.processes = threads, processes
        with _blas_one_thread():
            for row in worker_rows(list(pending), here, threads, failed, processes):
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


def _threads_saving(before: tuple[float, ...], after: tuple[float, ...], threads: int, left_files: float,
                    cores: int | None = None, online: int | None = None) -> tuple[float, str]:
    """The wall time [s] calibrating ``threads`` files at a time would save on the files left (``left_files``
    of the timed one), from the timed file's usage; and the figures, as words. ``cores``: the cores this
    process may run on, ``online``: the machine's (the idle jiffies count over all of them); default this host's."""
    wall = max(after[0] - before[0], 1e-9)
    used = max((after[1] - before[1]) / wall, 1e-3)  # cores this process kept busy
    if cores is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    online = online or os.cpu_count() or 1
    d_total = after[3] - before[3]
    idle = ((after[2] - before[2]) / d_total * online) if d_total > 0 else cores - used
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
