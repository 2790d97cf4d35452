"""Where gravcald's memory is, asked from outside: an env-guarded probe for benches and tests (not a protocol).

``GRAVCALD_MEMORY_PROBE=DIR`` starts tracemalloc at start-up (slow: for measurements only) and a thread that,
whenever a file ``DIR/request`` appears, writes ``DIR/report-N.txt`` (N counts from 1: the traced Python
allocations by line, largest first, and what grew since the first report) and removes the request. With
``GRAVCALD_MEMORY_PROBE_TRACE=0`` nothing is traced and the reports give pymalloc's arena figures instead
(sys._debugmallocstats, which has none to give while tracemalloc hooks the allocator).
"""
from __future__ import annotations

import logging
import os
import sys
import threading
import time

ENV = "GRAVCALD_MEMORY_PROBE"
TOP_LINES = 25

log = logging.getLogger("gravcal.memory_probe")


def install_from_env(env) -> None:
    directory = env.get(ENV)
    if not directory:
        return
    if env.get(ENV + "_TRACE", "1") != "0":
        import tracemalloc

        tracemalloc.start(1)
    threading.Thread(target=_serve, args=(directory,), name="gravcal-memory-probe", daemon=True).start()


def _serve(directory: str) -> None:
    request = os.path.join(directory, "request")
    count = 0
    while True:
        if os.path.exists(request):
            count += 1
            path = os.path.join(directory, f"report-{count}.txt")
            try:
                with open(path + ".tmp", "w") as fh:
                    fh.write(report())
                os.replace(path + ".tmp", path)
                os.unlink(request)
            except OSError as exc:
                log.warning("memory probe stops: cannot write its report in %s: %s", directory, exc.strerror or exc)
                return
        time.sleep(0.05)


_FIRST: list = []  # the first report's snapshot: later reports also show what grew since


def report() -> str:
    """Traced allocations by line and what grew since the first report; else the pymalloc arena summary."""
    import tracemalloc

    if not tracemalloc.is_tracing():
        return _pymalloc_summary()
    snap = tracemalloc.take_snapshot().filter_traces([tracemalloc.Filter(False, tracemalloc.__file__)])
    stats = snap.statistics("lineno")
    out = [f"traced {sum(s.size for s in stats) / 1048576:.2f} MiB in {sum(s.count for s in stats)} blocks"]
    out += [f"{s.size / 1048576:8.2f} MiB {s.count:8d} {s.traceback[0].filename}:{s.traceback[0].lineno}"
            for s in stats[:TOP_LINES]]
    if _FIRST:
        out.append("grown since the first report:")
        out += [f"{d.size_diff / 1024:+9.1f} KiB {d.count_diff:+8d} {d.traceback[0].filename}:{d.traceback[0].lineno}"
                for d in snap.compare_to(_FIRST[0], "lineno")[:TOP_LINES] if d.size_diff]
    else:
        _FIRST.append(snap)
    return "\n".join(out) + "\n"


def _pymalloc_summary() -> str:
    """The arena lines of sys._debugmallocstats (it writes to the C stderr: captured through a file)."""
    import tempfile  # only when asked: not among the daemon's start-up imports

    with tempfile.TemporaryFile() as tmp:
        sys.stderr.flush()
        saved = os.dup(2)
        try:
            os.dup2(tmp.fileno(), 2)
            sys._debugmallocstats()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        tmp.seek(0)
        text = tmp.read().decode(errors="replace")
    keep = ("arenas", "bytes in", "Total")
    return "\n".join(line for line in text.splitlines() if any(k in line for k in keep)) + "\n"
