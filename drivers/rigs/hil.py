"""Run the emulator (``python -m gravcal.drivers.rigs.emulate``) in a child process and talk to it.

    with EmulatorProcess(["--bus", "serial", "--scenario", "pattern", "--duration", "5"]) as emu:
        with open_driver(emu.spec) as drv:
            ...
        emu.wait_done(timeout=30)

The child's stdout protocol: first line the driver spec, then ``event: ...`` lines, then
``done: ...``. The child lingers (``--linger``) after the stream until this object stops it.
``own_process_group=True`` starts it in a process group of its own, so a Ctrl-C at the terminal reaches only the
parent (a daemon that must save its state before it stops the emulator itself). Not a session of its own: the
scheduler puts each session in its own group (autogroup), and on a loaded host a device in another group answers
late (the emulated I2C bus's ioctls, each several round trips to this process, took ~4x longer: p50 9.6 against
2.4 ms at load 10).
"""
from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Sequence

EMULATOR_MODULE = f"{__package__}.emulate"  # the entry point beside this module


def _child_env() -> dict[str, str]:
    """The emulator's environment: this one's, without umockdev's preload (a host of the emulated I2C bus runs
    under it; the emulator serves the bus and opens no emulated device)."""
    env = {k: v for k, v in os.environ.items() if k != "UMOCKDEV_DIR"}
    preloads = [p for p in env.pop("LD_PRELOAD", "").split(":") if p and "libumockdev-preload" not in p]
    if preloads:
        env["LD_PRELOAD"] = ":".join(preloads)
    return {**env, "PYTHONUNBUFFERED": "1"}


class EmulatorProcess:
    def __init__(self, args: Sequence[str], *, linger: float = 120.0, start_timeout: float = 30.0,
                 own_process_group: bool = False):
        self.args = [sys.executable, "-m", EMULATOR_MODULE, *args, "--linger", str(linger), "--stop-at-stdin-eof"]
        self.start_timeout = start_timeout
        self.own_process_group = own_process_group
        self.proc: subprocess.Popen | None = None
        self.spec = ""
        self.events: list[str] = []
        self.done_line: str | None = None
        self._lines: queue.Queue[str | None] = queue.Queue()
        self._done = threading.Event()
        self.stderr_path: Path | None = None

    def __enter__(self) -> "EmulatorProcess":
        self.proc = subprocess.Popen(self.args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True,
                                     env=_child_env(),
                                     process_group=0 if self.own_process_group else None)
        threading.Thread(target=self._pump, daemon=True).start()
        try:
            line = self._lines.get(timeout=self.start_timeout)
        except queue.Empty:
            line = None
        if not line:
            err = self._stop()
            raise RuntimeError(f"emulator did not start: {err.strip()[-2000:]}")
        self.spec = line.strip()
        return self

    def _pump(self) -> None:
        first = True
        for line in self.proc.stdout:
            if first:
                self._lines.put(line)
                first = False
            elif line.startswith("event:"):
                self.events.append(line[6:].strip())
            elif line.startswith("done:"):
                self.done_line = line[5:].strip()
                self._done.set()
        self._lines.put(None)
        self._done.set()

    def wait_done(self, timeout: float) -> bool:
        """True once the stream has ended (``done:`` printed or the child exited)."""
        return self._done.wait(timeout)

    def _stop(self) -> str:
        if self.proc is None:
            return ""
        if self.proc.poll() is None:
            try:
                self.proc.send_signal(signal.SIGTERM)
            except PermissionError:  # a parent that dropped root's privileges: closing stdin stops the child
                pass
            self.proc.stdin.close()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if not self.proc.stdin.closed:
            self.proc.stdin.close()
        return self.proc.stderr.read() if self.proc.stderr else ""

    def __exit__(self, *exc) -> None:
        self.stderr = self._stop()
