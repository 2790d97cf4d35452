"""Client churn against a live gravcald: rounds of request flooders and slow readers that fill their queues to
the byte bound and leave, beside one good watcher; the daemon's resident memory by kind of mapping after
warm-up, with each round's queues full, and after each round's clients left."""
from __future__ import annotations

import multiprocessing as mp
import time
from pathlib import Path

from .faults_starvation import abusers_main
from .gravcald_process import GravcaldProcess
from .smaps import resident_by_kind


def _queued(d: GravcaldProcess, n: int) -> list[int]:
    """Queued bytes of the ``n`` fullest client queues."""
    return sorted((c["queued_bytes"] for c in d.status()["server"]["per_client"]), reverse=True)[:n]


def _settle(d: GravcaldProcess, clients: int, timeout: float = 30.0) -> None:
    """Until at most ``clients`` besides the asking one are connected."""
    deadline = time.monotonic() + timeout
    while (server := d.status()["server"])["clients"] > clients + 1:
        if time.monotonic() > deadline:
            raise AssertionError(f"clients did not leave within {timeout} s: {server['per_client']}")
        time.sleep(0.1)


def _probe(directory: Path | None) -> str | None:
    if directory is None:
        return None
    n = len(list(directory.glob("report-*.txt"))) + 1
    (directory / "request").write_text("")
    deadline = time.monotonic() + 60
    while not (directory / f"report-{n}.txt").exists():
        if time.monotonic() > deadline:
            return "probe: no report within 60 s"
        time.sleep(0.1)
    return (directory / f"report-{n}.txt").read_text()


def run_churn(*, bus: str = "serial", rounds: int = 3, queue_bytes: int = 1 << 20, flooders: int = 8,
              slow_readers: int = 20, warmup_s: float = 5.0, settle_s: float = 2.0, fill_timeout_s: float = 60.0,
              fs: float = 200.0, probe_dir: Path | None = None, env: dict | None = None) -> dict:
    """Figures: ``baseline`` (after warm-up with the good client), per round ``full`` (the slow readers' queues
    at the byte bound; the flooders were disconnected for flooding after the server's flood_timeout_s) and
    ``after`` (all of them left, ``settle_s`` later): resident kB by kind (smaps.resident_by_kind), the queued
    bytes at ``full``, and with ``probe_dir`` (gravcald's memory_probe) its reports."""
    env = dict(env or {})
    if probe_dir is not None:
        env["GRAVCALD_MEMORY_PROBE"] = str(probe_dir)
    # slow readers (1 KiB/s) would be disconnected as stalled before their queues fill: a Unix socket polls
    # writable again only once its reader has taken 3/4 of what it holds
    config = f"[socket]\nqueue_bytes = {int(queue_bytes)}\nqueue_messages = 1000000\nstall_timeout_s = 600\n"
    d = GravcaldProcess(None, "--bus", bus, "--scenario", "static", "--speed", "1", "--duration", "100000",
                        fs=fs, config=config, env=env)
    ctx = mp.get_context("spawn")
    fig: dict = {"queue_bytes": queue_bytes, "rounds": []}
    try:
        d.wait_serving()
        with d.client() as good:
            good.set_watch(enable=True, rate=0)
            end = time.monotonic() + warmup_s
            while time.monotonic() < end:
                good.read_message(timeout=10)
            fig["baseline"] = resident_by_kind(d.proc.pid)
            fig["baseline_probe"] = _probe(probe_dir)
            for _ in range(rounds):
                result = ctx.Queue()
                child = ctx.Process(target=abusers_main,
                                    args=(d.sock, flooders, slow_readers, fill_timeout_s + 30, result))
                child.start()
                assert result.get(timeout=60) == "started"
                deadline = time.monotonic() + fill_timeout_s
                while True:
                    _drain(good)
                    fullest = _queued(d, slow_readers)
                    if len(fullest) == slow_readers and min(fullest) >= 0.9 * queue_bytes:
                        break
                    if time.monotonic() > deadline:
                        raise AssertionError(f"queues not at the byte bound within {fill_timeout_s} s: "
                                             f"{fullest}\n{d.log()[-3000:]}")
                    time.sleep(0.5)
                full = resident_by_kind(d.proc.pid)
                probe_full = _probe(probe_dir)
                child.terminate()  # the abusers' sockets close with their process
                child.join(30)
                _settle(d, 1)
                end = time.monotonic() + settle_s
                while time.monotonic() < end:
                    _drain(good)
                fig["rounds"].append({"full": full, "queued_bytes": sum(fullest), "after": resident_by_kind(d.proc.pid),
                                      "probe_full": probe_full, "probe_after": _probe(probe_dir)})
    finally:
        fig["exit_code"] = d.stop()
    return fig


def _drain(c) -> None:
    """Read what the good client has been sent (so its queue stays empty)."""
    c._sock.setblocking(False)
    try:
        while c._sock.recv(1 << 16):
            pass
    except (BlockingIOError, InterruptedError):
        pass
    finally:
        c._sock.setblocking(True)
        c._sock.settimeout(c.timeout)
    c._buf.clear()
    c._pending.clear()
