"""``gravcal daemon-demo``: the service end to end, in one command.

Starts ``gravcald --emulate`` as a child process (the emulated logger, in a process of its own, on a real
pty, an slcan pty or /dev/i2c-1 through umockdev; time-lapsed), connects to its socket as any client would, and
prints the calibration converging from the datasheet start: revision, windows, the norm error
of the calibrated static samples [mg] (|a| - 1 g, what a wrong calibration shows first), and
the offsets [mg] and sensitivities [%] against the emulated sensor's truth. Then it stops the
daemon with SIGTERM (which saves the state) and the emulator with it.
"""
from __future__ import annotations

import argparse
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from typing import Any, TextIO

import numpy as np

from ..errors import InputError
from .summaries import SUMMARIES

G = 9.80665  # m/s² per g (protocol.STANDARD_GRAVITY)
DEFAULT_SPEED = {"serial": 50.0, "can": 10.0, "i2c": 50.0}  # slcan's ASCII framing is the slowest link
HEADER = (" sensor time  rev  win  calibration    static |a|-1g [mg]   offset error x y z [mg]     "
          "sensitivity error x y z [%]")


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "daemon-demo",
        help=SUMMARIES["daemon-demo"],
        description="Start `gravcald --emulate` (the logger emulator on a pty, time-lapsed), connect to its socket "
                    "and print the calibration converging from the deliberately wrong datasheet start, against the "
                    "emulated sensor's truth; then stop the daemon (state saved) and the emulator.",
    )
    p.add_argument("--bus", choices=("serial", "can", "i2c"), default="serial", help="emulated bus (default serial)")
    p.add_argument("--scenario", default="six_position",
                   help="emulated motion (default six_position: the board turned through its six faces; "
                        "loetters and daily_living take longer to show every parameter)")
    p.add_argument("--seed", type=int, default=0, help="seed of the emulated sensor and motion (default 0)")
    p.add_argument("--duration", type=float, default=300.0, metavar="S",
                   help="sensor seconds to show (default 300)")
    p.add_argument("--speed", type=float, default=None, metavar="X",
                   help="time-lapse factor (default 50; 10 for can)")
    p.add_argument("--fs", type=float, default=100.0, help="sample rate [Hz] of the emulated logger (default 100)")
    p.add_argument("--every", type=float, default=15.0, metavar="S",
                   help="print a line at most every S sensor seconds, and on acceptance (default 15)")
    p.add_argument("--state-dir", metavar="DIR", help="keep the daemon's state here (default: a temporary directory)")
    p.add_argument("--timeout", type=float, default=60.0, metavar="S",
                   help="give up when the daemon does not start or goes quiet for S wall seconds (default 60)")
    return p


def _hms(t: float) -> str:
    t = int(round(t))
    return f"{t // 3600:02d}:{t // 60 % 60:02d}:{t % 60:02d}"


def calib_errors(calib: dict[str, Any], truth: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Offset errors [mg] and sensitivity errors [% of the true one] of a CALIB message
    against the emulator's truth (both raw = K a + o in duty cycle units)."""
    s_true = np.diag(np.asarray(truth["sensitivity"], dtype=float))
    do = (np.asarray(calib["offset"], dtype=float) - np.asarray(truth["offset"], dtype=float)) / s_true * 1e3
    ds = (np.diag(np.asarray(calib["sensitivity"], dtype=float)) - s_true) / s_true * 1e2
    return do, ds


class Progress:
    """Collects the watch stream and prints one line per ``every`` sensor seconds."""

    def __init__(self, truth: dict[str, Any] | None, fs: float, every: float, out: TextIO):
        self.truth, self.fs, self.every, self.out = truth, fs, every, out
        self.calib: dict[str, Any] | None = None
        self.norm_err_mg: list[float] = []  # static samples since the last line
        self.sensor_t = 0.0
        self.next_line = 0.0
        self.was_accepted = False
        self.first_accepted_t: float | None = None
        self.last_static_mg: float | None = None

    def imu(self, msg: dict[str, Any]) -> None:
        self.sensor_t = msg["seq"] / self.fs
        acc = msg.get("acc")
        if msg.get("static") and acc and all(isinstance(v, (int, float)) for v in acc):
            self.norm_err_mg.append((math.sqrt(sum(v * v for v in acc)) / G - 1.0) * 1e3)
        if self.sensor_t >= self.next_line:
            self.line()

    def calib_changed(self, msg: dict[str, Any]) -> None:
        self.calib = msg
        if msg.get("accepted") and not self.was_accepted:
            self.was_accepted = True
            self.first_accepted_t = self.sensor_t
            self.line(note="accepted: the published samples use it from now on")

    def line(self, note: str = "") -> None:
        if not self.norm_err_mg and not note:
            return  # nothing new to show
        c = self.calib or {}
        state = "accepted" if c.get("accepted") else ("datasheet" if not c.get("revision") else "candidate")
        if self.norm_err_mg:
            e = np.asarray(self.norm_err_mg)
            self.last_static_mg = float(np.median(np.abs(e)))
            static = f"{np.median(e):+8.1f} (n={e.size:4d})"
        else:
            static = f"{'--':>8} (n=   0)"
        errs = ""
        if self.truth is not None and c.get("offset") is not None:
            do, ds = calib_errors(c, self.truth)
            errs = (" ".join(f"{v:+7.1f}" for v in do) + "   " + " ".join(f"{v:+6.2f}" for v in ds))
        print(f"  {_hms(self.sensor_t)}  {c.get('revision', 0):4d} {c.get('n_windows', 0):4d}  {state:<11}  "
              f"{static}   {errs}" + (f"   <- {note}" if note else ""), file=self.out, flush=True)
        self.norm_err_mg = []
        self.next_line = (math.floor(self.sensor_t / self.every) + 1) * self.every


def _wait_for_socket(proc: subprocess.Popen, path: str, timeout: float) -> None:
    from ..clients.client import Client, ClientError

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            with open(proc.log_path) as fh:  # type: ignore[attr-defined]
                err = " ".join(fh.read().split())[-600:]
            raise InputError(f"gravcald exited with status {proc.returncode} before serving: {err}")
        if os.path.exists(path):
            try:
                Client(path, timeout=2.0).close()
                return
            except ClientError:
                pass
        time.sleep(0.1)
    raise InputError(f"gravcald did not serve {path} within {timeout:g} s")


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    from ..clients.client import Client

    out = out or sys.stdout
    speed = DEFAULT_SPEED[args.bus] if args.speed is None else args.speed
    if not (args.duration > 0 and args.fs > 0 and speed > 0 and args.every > 0 and args.timeout > 0):
        raise InputError("--duration, --fs, --speed, --every and --timeout must be > 0")
    base = tempfile.mkdtemp(prefix="gravcal-daemon-demo-")
    sock = os.path.join(base, "gravcal.sock")
    state_dir = args.state_dir or os.path.join(base, "state")
    cmd = [sys.executable, "-m", "gravcal.daemon.gravcald", "--emulate", "--bus", args.bus,
           "--scenario", args.scenario, "--seed", str(args.seed), "--speed", repr(float(speed)),
           "--fs", repr(float(args.fs)), "--duration", repr(float(args.duration) + 30.0),
           "--socket", sock, "--state-dir", state_dir, "--log-level", "warning"]
    print(f"gravcal daemon-demo: gravcald on an emulated {args.bus} logger ({args.scenario}, seed {args.seed}, "
          f"{args.fs:g} Hz, {speed:g}x real time), {args.duration:g} s of sensor time", file=out)
    print(f"  $ gravcald --emulate --bus {args.bus} --scenario {args.scenario} --seed {args.seed} --speed {speed:g} "
          f"--fs {args.fs:g} --socket {sock} --state-dir {state_dir}", file=out, flush=True)
    log_path = os.path.join(base, "gravcald.log")  # a file, not a pipe: a full pipe would block the daemon
    with open(log_path, "w") as log_file:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=log_file, text=True,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
    proc.log_path = log_path  # type: ignore[attr-defined]
    code = 1
    try:
        _wait_for_socket(proc, sock, args.timeout)
        with Client(sock, timeout=args.timeout) as client:
            deadline = time.monotonic() + args.timeout
            status = client.status()  # the socket is served before the emulated device is open: wait for it
            while not status["device"].get("connected") and time.monotonic() < deadline:
                time.sleep(0.1)
                status = client.status()
            truth = (status.get("emulator") or {}).get("truth")
            if truth is not None:
                print(f"  truth of the emulated sensor: offset {np.round(truth['offset'], 4).tolist()}, sensitivity "
                      f"{np.round(np.diag(truth['sensitivity']), 5).tolist()} [duty, duty/g]", file=out)
            progress = Progress(truth, args.fs, args.every, out)
            progress.calib = client.calib()
            if truth is not None:
                do, ds = calib_errors(progress.calib, truth)
                print(f"  the daemon starts from the datasheet values: offsets off by up to {np.max(np.abs(do)):.0f} mg, "
                      f"sensitivities by up to {np.max(np.abs(ds)):.1f} %", file=out)
            print(HEADER, file=out, flush=True)
            # Every IMU sample is needed for the static statistics; the daemon drops (and
            # counts) what this client cannot keep up with, without slowing anything else.
            for msg in client.watch(rate=0):
                cls = msg.get("class")
                if cls == "IMU":
                    progress.imu(msg)
                    if progress.sensor_t >= args.duration:
                        break
                elif cls == "CALIB":
                    progress.calib_changed(msg)
            progress.line()
        code = _summary(progress, out)
    finally:
        stopped = _stop(proc)
        if stopped is not None:
            print(f"  daemon stopped (SIGTERM, exit status {stopped}); "
                  + (f"state kept in {state_dir}" if args.state_dir else "its temporary state removed"), file=out)
        shutil.rmtree(base, ignore_errors=True)  # socket dir, log, and the state unless --state-dir
    return code


def _summary(progress: Progress, out: TextIO) -> int:
    c = progress.calib or {}
    print("", file=out)
    if not c.get("accepted"):
        print(f"  no accepted calibration after {progress.sensor_t:.0f} s of sensor time ({c.get('n_windows', 0)} "
              f"windows: {c.get('message') or 'not enough orientations yet'}); try a longer --duration", file=out)
        return 3
    line = (f"  accepted at {progress.first_accepted_t:.0f} s of sensor time; now revision {c['revision']}, "
            f"{c['n_windows']} windows")
    if progress.last_static_mg is not None:
        line += f", static norm error (median |.|) {progress.last_static_mg:.1f} mg"
    print(line, file=out)
    if progress.truth is not None:
        do, ds = calib_errors(c, progress.truth)
        print(f"  vs the emulated sensor's truth: offsets within {np.max(np.abs(do)):.1f} mg, sensitivities within "
              f"{np.max(np.abs(ds)):.2f} %", file=out)
    return 0


def _stop(proc: subprocess.Popen) -> int | None:
    if proc.poll() is not None:
        return proc.returncode
    proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        return None
