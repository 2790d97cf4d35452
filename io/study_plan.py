"""How a study runs on this machine: Dask worker threads, started while this process calibrates.

A calibration's heavy parts (the reading pass, detection, the fit's sums) run in C and numpy with the GIL
released, so threads of one process calibrate files side by side as well as worker processes would,
without their fixed cost: spawning two worker processes (each starting an interpreter and importing dask
and numpy again) took 1.6 s here and closing them 0.8 s, against 0.01-0.1 s each for a cluster of
threads. What stays fixed is importing dask.distributed (0.7-1.8 s on this machine). So a background
thread imports it and starts a LocalCluster of threads while this process calibrates the first files one
by one; once the cluster is up, the files left go to its threads. A study done before that never waits
for a cluster, and one file or one worker runs here outright: ``Plan.summary`` says which plan ran.
A worker thread that runs out of memory takes this process with it; the rows written so far stay, and a
re-run resumes from them (a cluster of worker processes: ``--scheduler``).
"""
from __future__ import annotations

import logging
import threading
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Iterator

log = logging.getLogger(__name__)

Item = tuple[str, "str | None"]  # a recording and where its calibrated samples go (None: not written)


@dataclass
class Plan:
    """What ran where: files calibrated in this process, files on the cluster's threads, and why."""

    in_process: int = 0
    on_cluster: int = 0
    threads: int = 0
    reason: str = ""

    def summary(self) -> str:
        if not self.on_cluster:
            return f"all in this process: {self.reason}" if self.reason else "all in this process"
        return (f"{self.in_process} in this process while Dask started, {self.on_cluster} on "
                f"{self.threads} Dask worker threads")


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
    start = ClusterStart(threads)
    start.start()
    pending = deque(items)
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
