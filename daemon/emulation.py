"""``gravcald --emulate``: the built-in logger emulator as the device (the HIL rig of drivers/rigs)."""
from __future__ import annotations

import argparse
import logging
import math
import os
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


class EmulatedBus:
    """``gravcald --emulate``: the logger emulator stands in for the hardware.

    serial/can: the emulator runs in a child process (drivers/rigs/hil.py) on a real pty (serial
    frames) or an slcan pty (python-can's slcan interface opens it); the daemon opens the device
    path like a USB adapter. i2c: the fake I2C device runs in this process behind the real
    I2CDriver (there is no kernel I2C to share). The sensor is drawn off-nominal from ``seed``;
    the daemon starts from the datasheet values as usual, i.e. deliberately wrong.

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
        if bus == "i2c" and driver_options.strip("&?"):
            raise ValueError("--driver-options applies to the serial and can buses (i2c: [device] latency_budget_s "
                             "in a --config file sets its FIFO watermark)")
        self.bus, self.scenario, self.seed, self.speed, self.fs = bus, scenario, int(seed), float(speed), float(fs)
        self.duration, self.disconnects = float(duration), tuple(disconnects)
        self.driver_options = driver_options.strip("&?")
        self.process: Any = None  # EmulatorProcess (serial/can)
        self.device: Any = None  # FakeI2CDevice (i2c)
        self.piped: Any = None  # the i2c device's scenario blocks, made in a child process (PipedBlocks)
        self.spec = ""
        self.truth: Calibration | None = None  # set by open() (imports the simulator: not before the socket is bound)

    def _tick_hz(self) -> float:
        from ..drivers.codec import TICK_HZ

        return TICK_HZ * self.speed if math.isfinite(self.speed) else 0.0  # 0: stamp blocks at reception

    def open(self, *, latency_budget_s: float = 0.0) -> Any:
        """Start the emulator and return the opened driver (``latency_budget_s``: the driver's)."""
        self.truth = emulated_truth(self.scenario, self.seed)
        if self.speed > 1:
            latency_budget_s = max(latency_budget_s, TIME_LAPSE_LATENCY_BUDGET_S)
        if self.bus == "i2c":
            return self._open_i2c(latency_budget_s)
        from ..drivers.base import open_driver

        args = ["--bus", self.bus, "--scenario", self.scenario, "--seed", str(self.seed),
                "--speed", "max" if math.isinf(self.speed) else repr(self.speed), "--fs", repr(self.fs),
                "--duration", repr(self.duration)]
        for start, dur in self.disconnects:
            args += ["--disconnect-at", f"{start!r}:{dur!r}"]
        # the device stays plugged in after the stream ends; its own session: a Ctrl-C at the terminal reaches only
        # the daemon, which then saves its state and stops the emulator itself
        proc = EmulatorProcess(args, linger=-1.0, new_session=True)
        try:
            proc.__enter__()
        except RuntimeError as exc:
            raise ValueError(f"--emulate: {exc}") from None
        self.process = proc
        self.spec = proc.spec + ("&" if "?" in proc.spec else "?") + f"tick_hz={self._tick_hz():.0f}"
        if self.driver_options:
            self.spec += "&" + self.driver_options
        driver = open_driver(self.spec, open=False)
        if "latency_budget_s=" not in self.driver_options:
            driver.latency_budget_s = latency_budget_s
        return driver.open()

    def _open_i2c(self, latency_budget_s: float) -> Any:
        from ..drivers.rigs.emulator import Faults
        from ..drivers.rigs.fake_i2c import FakeI2CDevice, FakeI2CDriver, fake_i2c_spec, realtime_options
        from ..drivers.rigs.sources import PATTERN, scenario_source

        speed = self.speed if math.isfinite(self.speed) else 100.0  # a FIFO fills at a finite pace
        if self.scenario == PATTERN:
            blocks = scenario_source(self.scenario, seed=self.seed, fs=self.fs, duration=self.duration).blocks
        else:  # the sensor model (scipy.signal) runs in a child process, not in the daemon
            from ..drivers.rigs.block_pipe import PipedBlocks

            blocks = self.piped = PipedBlocks(self.scenario, seed=self.seed, fs=self.fs, duration=self.duration)
        depth = 255  # the deepest FIFO the register map allows: room for the host's scheduling jitter
        self.device = device = FakeI2CDevice(blocks, self.fs, speed=speed, fifo_depth=depth,
                                             faults=Faults(disconnects=self.disconnects, seed=self.seed))
        # the device samples in real time and raises DRDY; the driver sleeps on that line
        driver = FakeI2CDriver(device, tick_hz=self._tick_hz(), latency_budget_s=latency_budget_s,
                               **realtime_options(device))
        self.spec = fake_i2c_spec(device, scenario=self.scenario, seed=self.seed, fs=self.fs)
        return driver.open()

    def describe(self) -> str:
        where = {"serial": "a pty", "can": "an slcan pty",
                 "i2c": "a fake I2C device (in process; its samples from a child process)"}[self.bus]
        pid = f", emulator pid {self.process.proc.pid}" if self.process is not None else ""
        return (f"emulated {self.bus} logger on {where}{pid}: scenario {self.scenario}, seed {self.seed}, "
                f"{self.fs:g} Hz, speed {self.speed:g}x; device {self.spec}")

    def status(self) -> dict[str, Any]:
        out: dict[str, Any] = {"bus": self.bus, "scenario": self.scenario, "seed": self.seed, "speed": self.speed,
                               "fs_hz": self.fs, "spec": self.spec}
        if self.process is not None:
            out["events"] = list(self.process.events)
            out["stream_done"] = self.process.done_line
        if self.device is not None:  # the fake device's CPU in the driver's thread (a real I2C device costs none)
            out["bus_access_cpu_s"] = self.device.bus_cpu_s
        if self.truth is not None:  # what the estimate should converge to (raw = K a + o)
            out["truth"] = {"offset": self.truth.offset.tolist(), "sensitivity": self.truth.sensitivity.tolist()}
        return out

    def close(self) -> None:
        if self.piped is not None:
            self.piped.close()
            self.piped = None
        if self.process is not None:
            self.process.__exit__(None, None, None)
            err = (getattr(self.process, "stderr", "") or "").strip()
            if err:
                log.debug("emulator stderr: %s", err[-2000:])
            self.process = None



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

