"""``gravcald --emulate``: the built-in logger emulator as the device (the HIL rig of drivers/rigs)."""
from __future__ import annotations

import argparse
import logging
import math
import os
import shutil
import sys
import tempfile
from typing import Any, Sequence

import numpy as np

from ..core.calibration import Calibration
from ..drivers.rigs.hil import EmulatorProcess

log = logging.getLogger("gravcal.gravcald")

# A time-lapse feeds the daemon `speed` times its real rate; latency is not what it exercises, and a wake-up per
# sample at thousands of samples per second would outrun a loaded host. Frames are then read in groups of this.
TIME_LAPSE_LATENCY_BUDGET_S = 0.02


def emulated_truth(scenario: str, seed: int) -> Calibration | None:
    """The calibration an ideal estimator should find for the emulator's sensor (raw = K a + o,
    duty cycle units): the emulator draws the sensor with ``default_model`` from the seed's
    model stream, exactly as ``core.simulate.simulate_blocks`` does. None for the test pattern."""
    if scenario == "pattern":
        return None
    from ..core.model.defaults import default_model, triad_truth
    from ..core.seeding import seed_streams  # the simulator's seed split, without its motion scenarios

    return triad_truth(default_model(seed_streams(seed)[1]))


PRELOAD_NOTE = "umockdev's preload library (Debian: apt-get install umockdev)"


def exec_under_i2c_preload() -> str | None:
    """``--emulate --bus i2c``: the emulated device answers this process's /dev/i2c-N ioctls from its own process
    through umockdev's preload library, which the dynamic linker loads only at a program's start: start again
    (the same process id and arguments) with it. Returns only when already under it (None) or when the library
    is missing (the reason)."""
    from ..drivers.rigs.i2c_dev import preload_library, preloaded

    if preloaded():
        return None
    if preload_library() is None:
        return f"--emulate --bus i2c needs {PRELOAD_NOTE}"
    from ..drivers.rigs.i2c_dev import PRELOAD_LIBRARY

    env = dict(os.environ)
    env["LD_PRELOAD"] = ":".join(p for p in (PRELOAD_LIBRARY, env.get("LD_PRELOAD", "")) if p)
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, list(sys.orig_argv), env)
    return None  # not reached


class EmulatedBus:
    """``gravcald --emulate``: the logger emulator stands in for the hardware.

    The emulator runs in a child process (drivers/rigs/hil.py) on a real pty (serial frames), an slcan pty
    (python-can's slcan interface opens it), or (i2c) behind ``/dev/i2c-N`` in a umockdev testbed (this
    process runs under umockdev's preload library and its ioctls are answered by the emulator's process:
    drivers/rigs/i2c_dev.py); the daemon opens the device like hardware. The sensor is drawn off-nominal from
    ``seed``; the daemon starts from the datasheet values as usual, i.e. deliberately wrong.

    With a time-lapse ``speed`` the device ticks run ``speed`` times faster than the host clock,
    so the drivers' host time stamps (``tick_hz`` scaled by ``speed``) stay monotonic; the
    estimator works on device time (seq / fs) and is unaffected.
    """

    def __init__(self, bus: str = "serial", *, scenario: str = "daily_living", seed: int = 0, speed: float = 1.0,
                 fs: float = 200.0, duration: float = 86400.0, disconnects: Sequence[tuple[float, float]] = (),
                 driver_options: str = ""):
        if bus not in ("serial", "can", "i2c"):
            raise ValueError(f"--bus must be serial, can or i2c, got {bus!r}")
        if not speed > 0:
            raise ValueError(f"--speed must be > 0, got {speed}")
        self.bus, self.scenario, self.seed, self.speed, self.fs = bus, scenario, int(seed), float(speed), float(fs)
        self.duration, self.disconnects = float(duration), tuple(disconnects)
        self.driver_options = driver_options.strip("&?")
        self.process: Any = None  # EmulatorProcess
        self.testbed: str | None = None  # i2c: the umockdev testbed directory holding /dev/i2c-N
        self.spec = ""
        self.truth: Calibration | None = None  # set by open() (imports the simulator: not before the socket is bound)

    def _tick_hz(self) -> float:
        from ..drivers.codec import TICK_HZ

        return TICK_HZ * self.speed if math.isfinite(self.speed) else 0.0  # 0: stamp blocks at reception

    def _start_emulator(self, extra: list[str]) -> None:
        args = ["--bus", self.bus, "--scenario", self.scenario, "--seed", str(self.seed),
                "--speed", "max" if math.isinf(self.speed) else repr(self.speed), "--fs", repr(self.fs),
                "--duration", repr(self.duration), *extra]
        for start, dur in self.disconnects:
            args += ["--disconnect-at", f"{start!r}:{dur!r}"]
        # the device stays plugged in after the stream ends; its own process group: a Ctrl-C at the terminal reaches
        # only the daemon, which then saves its state and stops the emulator itself
        proc = EmulatorProcess(args, linger=-1.0, own_process_group=True)
        try:
            proc.__enter__()
        except RuntimeError as exc:
            raise ValueError(f"--emulate: {exc}") from None
        self.process = proc

    def open(self, *, latency_budget_s: float = 0.0) -> Any:
        """Start the emulator and return the opened driver (``latency_budget_s``: the driver's)."""
        from ..drivers.base import open_driver

        self.truth = emulated_truth(self.scenario, self.seed)
        if self.speed > 1:
            latency_budget_s = max(latency_budget_s, TIME_LAPSE_LATENCY_BUDGET_S)
        if self.bus == "i2c":
            self._start_i2c()
        else:
            self._start_emulator([])
        proc = self.process
        self.spec = proc.spec + ("&" if "?" in proc.spec else "?") + f"tick_hz={self._tick_hz():.0f}"
        if self.driver_options:
            self.spec += "&" + self.driver_options
        driver = open_driver(self.spec, open=False)
        if "latency_budget_s=" not in self.driver_options:
            driver.latency_budget_s = latency_budget_s
        return driver.open()

    def _start_i2c(self) -> None:
        """The emulator serves /dev/i2c-N in a umockdev testbed; this process, under the preload library
        (:func:`exec_under_i2c_preload`), opens it there once UMOCKDEV_DIR names the testbed."""
        from ..drivers.rigs.i2c_dev import preloaded

        if not preloaded():
            raise ValueError(f"--bus i2c: gravcald did not start under {PRELOAD_NOTE}")
        self.testbed = tempfile.mkdtemp(prefix="gravcal-i2c-")
        # the deepest FIFO the register map allows: room for the host's scheduling jitter
        self._start_emulator(["--fifo-depth", "255", "--testbed", self.testbed])
        os.environ["UMOCKDEV_DIR"] = self.testbed  # the preload reads it at each open (and putenv sets it)

    def describe(self) -> str:
        where = {"serial": "a pty", "can": "an slcan pty",
                 "i2c": f"/dev/i2c-N of the umockdev testbed {self.testbed}"}[self.bus]
        pid = f", emulator pid {self.process.proc.pid}" if self.process is not None else ""
        return (f"emulated {self.bus} logger on {where}{pid}: scenario {self.scenario}, seed {self.seed}, "
                f"{self.fs:g} Hz, speed {self.speed:g}x; device {self.spec}")

    def status(self) -> dict[str, Any]:
        out: dict[str, Any] = {"bus": self.bus, "scenario": self.scenario, "seed": self.seed, "speed": self.speed,
                               "fs_hz": self.fs, "spec": self.spec}
        if self.process is not None:
            out["events"] = list(self.process.events)
            out["stream_done"] = self.process.done_line
        if self.truth is not None:  # what the estimate should converge to (raw = K a + o)
            out["truth"] = {"offset": self.truth.offset.tolist(), "sensitivity": self.truth.sensitivity.tolist()}
        return out

    def close(self) -> None:
        if self.process is not None:
            self.process.__exit__(None, None, None)
            err = (getattr(self.process, "stderr", "") or "").strip()
            if err:
                log.debug("emulator stderr: %s", err[-2000:])
            self.process = None
        if self.testbed is not None:
            shutil.rmtree(self.testbed, ignore_errors=True)
            self.testbed = None



def emulation_defaults(args: argparse.Namespace, overrides: dict[str, Any]) -> list[str]:
    """--emulate without --socket/--state-dir: both in a fresh private temporary directory
    (under $XDG_RUNTIME_DIR when set). Fills ``overrides``; returns what to print."""
    if args.socket and args.state_dir:
        return []
    base = tempfile.mkdtemp(prefix="gravcald-emulate-", dir=os.environ.get("XDG_RUNTIME_DIR") or None)
    if not args.socket:
        overrides["socket.path"] = os.path.join(base, "gravcal.sock")
    if not args.state_dir:
        overrides["state.directory"] = os.path.join(base, "state")
    return [base]


def discard_if_empty(dirs: list[str]) -> None:
    """Remove the temporary directories of :func:`emulation_defaults` that hold nothing (a failed start, or a
    run that saved no state): a start that fails creates nothing. Anything with a file in it stays."""
    for base in dirs:
        for root, _subdirs, _files in os.walk(base, topdown=False):  # the state directory before its parent
            try:
                os.rmdir(root)
            except OSError:  # not empty (a saved state, a socket of a running daemon), or gone
                pass


def announce_emulation(daemon: Any, emulator: EmulatedBus, dirs: list[str]) -> None:
    """What ``gravcald --emulate`` prints at start: the emulated device, socket, state, start and truth."""
    sock = daemon.server.address if isinstance(daemon.server.address, str) else daemon.cfg.socket.path
    temporary_state = bool(dirs) and daemon.store.directory == os.path.join(dirs[0], "state")
    lines = [f"gravcald --emulate: {emulator.describe()}",
             f"  socket: {sock}   (try: gravcal watch --socket {sock})",
             f"  state:  {daemon.store.directory}" + (f"   (new; --state-dir {daemon.store.directory} resumes it)"
                                                     if temporary_state else ""),
             "  start:  " + "; ".join(daemon.notes[-1:]) + "   (Ctrl-C stops and saves the state)"]
    if emulator.truth is not None:
        t = emulator.truth
        lines.append(f"  truth:  offset {np.round(t.offset, 5).tolist()} sensitivity "
                     f"{np.round(np.diag(t.sensitivity), 5).tolist()} [duty, duty/g] (what the estimate should reach)")
    print("\n".join(lines), flush=True)

