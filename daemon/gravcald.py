"""gravcald: the in-use calibration service (command line; the service itself is daemon/service.py).

Modules: ``service`` (threads, signals, watchdog, reload, shutdown), ``processing`` (detector ->
OnlineCalibrator.feed -> correction), ``emulation`` (``--emulate``: the logger emulator as the device).
Calibration life cycle: core/estimators/online_policy.py. docs/daemon.md describes running it.

Entry point: ``gravcal.daemon.gravcald:main`` (console script ``gravcald``).
"""
from __future__ import annotations

import argparse
import importlib.machinery
import logging
import math
import os
import sys
from pathlib import Path
from typing import Any, Sequence

# the per-sample engine is compiled (a build without a C compiler installs without it): its files are looked
# for before anything imports them (importing a package's __init__ may), so that its absence is one line
NATIVE_ENGINE = ("drivers/_framekernel", "core/_correctkernel", "daemon/_linekernel", "daemon/_fastpath")
MISSING_ENGINE = [name for name in NATIVE_ENGINE
                  if not any((Path(__file__).resolve().parents[1] / (name + suffix)).is_file()
                             for suffix in importlib.machinery.EXTENSION_SUFFIXES)]
if MISSING_ENGINE:
    sys.stderr.write(f"gravcald: its native engine is missing ({', '.join(MISSING_ENGINE)} not built): reinstall "
                     f"gravcal where a C compiler and Python's headers are installed (e.g. apt install gcc python3-dev)\n")
    raise SystemExit(1)

from ..core.estimators.observability import ORDER_LADDER  # noqa: E402
from ..drivers.rigs.options import disconnect_arg, speed_arg
from . import config as config_mod
from . import memory_probe, privileges
from ..closed_pipe import write_or_stop
from .config import ConfigError
from ..errors import InputError
from .emulation import EmulatedBus, announce_emulation, discard_if_empty, emulation_defaults, exec_under_i2c_preload
from .socket_activation import SocketPathError
from .service import Gravcald

log = logging.getLogger("gravcal.gravcald")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="gravcald", description="gravcal in-use calibration daemon (serves calibrated IMU samples on a Unix socket).")
    p.add_argument("--config", metavar="FILE", help=f"TOML configuration (default: {config_mod.DEFAULT_CONFIG_PATH} if it exists)")
    p.add_argument("--device", metavar="SPEC", help="driver spec, e.g. serial:///dev/ttyUSB0?baudrate=460800")
    p.add_argument("--fs", metavar="HZ", type=float, help="nominal sample rate [Hz]")
    p.add_argument("--model", choices=tuple(ORDER_LADDER), help="calibration model order")
    p.add_argument("--socket", metavar="PATH", help="socket path when not socket-activated")
    p.add_argument("--state-dir", metavar="DIR", help="state directory")
    p.add_argument("--lab-calibration", metavar="FILE", help="start from this calibration JSON when there is no saved state")
    p.add_argument("--log-level", choices=("debug", "info", "warning", "error"))
    p.add_argument("--record-windows", metavar="FILE",
                   help="append each quasi-static window fed to the calibrator to FILE (JSON lines) for an offline "
                        "replay of the service's decisions")
    p.add_argument("--allow-root", action="store_true",
                   help="run as root without dropping privileges (default: refused unless [daemon] user is set)")
    p.add_argument("--print-config", action="store_true", help="print the effective configuration as TOML and exit")
    e = p.add_argument_group(
        "emulation", "--emulate runs the daemon against the built-in logger emulator instead of hardware: a sensor "
        "drawn off-nominal, a daemon starting from the datasheet values. The socket and state directory default to "
        "a fresh temporary directory (printed at start); /etc/gravcal/gravcald.toml is not read (use --config).")
    e.add_argument("--emulate", action="store_true", help="use the emulator as the device")
    e.add_argument("--bus", choices=("serial", "can", "i2c"), default="serial",
                   help="emulated bus: serial (pty), can (slcan on a pty) or i2c (/dev/i2c-N through umockdev) (default serial)")
    e.add_argument("--speed", type=speed_arg, default=1.0, metavar="X",
                   help="time-lapse factor of the emulated logger (1 = real time, default; 'max' = no pacing)")
    e.add_argument("--seed", type=int, default=0, help="seed of the emulated sensor and wearer (default 0)")
    e.add_argument("--scenario", default="daily_living",
                   help="emulated motion: daily_living (default), loetters, sagittal_postures, six_position, static, "
                        "or pattern")
    e.add_argument("--duration", type=float, default=86400.0, metavar="S",
                   help="emulated stream length [s of sensor time] (default 86400, a day; the motion is planned "
                        "ahead, so longer takes longer to start); then the bus goes silent")
    e.add_argument("--driver-options", default="", metavar="K=V&...",
                   help="serial/can: extra options for the driver's spec, e.g. latency_budget_s=0.02 (frames "
                        "arriving within 20 ms go out together: fewer wake-ups, more latency; default 0)")
    e.add_argument("--disconnect-at", type=disconnect_arg, action="append", default=[], metavar="T:DUR",
                   help="unplug the emulated device at sensor time T for DUR seconds (repeatable)")
    return p


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    return {
        "device.spec": args.device,
        "device.fs_hz": args.fs,
        "estimator.model": args.model,
        "socket.path": args.socket,
        "state.directory": args.state_dir,
        "state.lab_calibration": args.lab_calibration,
        "daemon.log_level": args.log_level,
    }


def default_config_path(environ: dict[str, str] | os._Environ) -> str:
    conf_dir = environ.get("CONFIGURATION_DIRECTORY")  # set by ConfigurationDirectory=
    return os.path.join(conf_dir.split(":")[0], "gravcald.toml") if conf_dir else config_mod.DEFAULT_CONFIG_PATH


def _setup_logging(level: str, environ: Any) -> None:
    under_journal = bool(environ.get("JOURNAL_STREAM") or environ.get("INVOCATION_ID"))
    fmt = "%(levelname)s %(name)s: %(message)s" if under_journal else "%(asctime)s gravcald %(levelname)s %(name)s: %(message)s"
    logging.basicConfig(stream=sys.stderr, format=fmt, force=True)
    logging.getLogger("gravcal").setLevel(level.upper())


def main(argv: Sequence[str] | None = None, *, driver: Any = None, environ: dict[str, str] | None = None) -> int:
    """``gravcald`` entry point. Exit status: 0 clean stop, 1 runtime failure, 2 bad
    configuration or arguments (one line on stderr)."""
    env = os.environ if environ is None else environ
    memory_probe.install_from_env(env)
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.emulate:
        given = [opt for opt, dest in (("--bus", "bus"), ("--speed", "speed"), ("--seed", "seed"),
                                       ("--scenario", "scenario"), ("--duration", "duration"),
                                       ("--disconnect-at", "disconnect_at"), ("--driver-options", "driver_options"))
                 if getattr(args, dest) != parser.get_default(dest)]
        if given:
            print(f"gravcald: error: {', '.join(given)} {'needs' if len(given) == 1 else 'need'} --emulate", file=sys.stderr)
            return 2
    elif args.device:
        print("gravcald: error: --device and --emulate exclude each other (the emulator is the device)", file=sys.stderr)
        return 2
    elif not (args.duration > 0 and math.isfinite(args.duration)):
        print(f"gravcald: error: --duration must be a positive number of seconds, got {args.duration}", file=sys.stderr)
        return 2
    if args.emulate and args.bus == "i2c" and argv is None and driver is None and not args.print_config:
        problem = exec_under_i2c_preload()  # returns only when already under the preload, or without it
        if problem:
            print(f"gravcald: error: {problem}", file=sys.stderr)
            return 2
    overrides = overrides_from_args(args)
    emulate_dirs = emulation_defaults(args, overrides) if args.emulate and not args.print_config else []
    try:
        return _configure_and_run(args, env, overrides, emulate_dirs, driver)
    finally:
        discard_if_empty(emulate_dirs)


def _configure_and_run(args: argparse.Namespace, env: Any, overrides: dict[str, Any], emulate_dirs: list[str],
                       driver: Any) -> int:
    config_path = args.config
    try:
        if args.emulate:  # the emulator is self-contained: read a config file only when asked to
            cfg = config_mod.load_config(config_path, overrides)
        elif config_path is None:
            candidate = default_config_path(env)
            cfg = config_mod.load_config(candidate if os.path.exists(candidate) else None, overrides)
            config_path = candidate if os.path.exists(candidate) else None
        else:
            cfg = config_mod.load_config(config_path, overrides)
    except ConfigError as exc:
        print(f"gravcald: error: {exc}", file=sys.stderr)
        return 2
    if args.print_config:
        write_or_stop(config_mod.example_toml(cfg))
        return 0
    _setup_logging(cfg.daemon.log_level, env)
    d = cfg.daemon
    # the emulator and an injected driver (tests) open no hardware: root is only warned about there
    meant = d.allow_root or args.allow_root or args.emulate or driver is not None
    try:
        identity = privileges.check_start(os.geteuid(), d.user, d.group, meant)
    except InputError as exc:
        print(f"gravcald: error: {exc}", file=sys.stderr)
        return 2
    emulator = None
    if args.emulate and driver is None:
        try:
            emulator = EmulatedBus(args.bus, scenario=args.scenario, seed=args.seed, speed=args.speed,
                                   fs=cfg.device.fs_hz, duration=args.duration, disconnects=args.disconnect_at,
                                   driver_options=args.driver_options)
        except ValueError as exc:
            print(f"gravcald: error: {' '.join(str(exc).split())}", file=sys.stderr)
            return 2
    recorder = None
    if args.record_windows:
        from .window_log import WindowRecorder

        try:
            recorder = WindowRecorder(args.record_windows)
        except OSError as exc:
            print(f"gravcald: error: --record-windows {args.record_windows}: {exc.strerror or exc}", file=sys.stderr)
            return 2
    daemon = Gravcald(cfg, driver=driver, environ=env, config_path=config_path, overrides=overrides,
                      emulator=emulator, window_sink=recorder, identity=identity)
    daemon.install_signal_handlers()
    try:
        daemon.start()
    except (ConfigError, ValueError, SocketPathError) as exc:
        daemon.shutdown()
        print(f"gravcald: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except Exception as exc:  # e.g. DriverError: the device is missing; systemd restarts us
        daemon.shutdown()
        print(f"gravcald: error: {type(exc).__name__}: {' '.join(str(exc).split())}", file=sys.stderr)
        return 1
    if emulator is not None:
        announce_emulation(daemon, emulator, emulate_dirs)
    try:
        return daemon.run()
    finally:
        if recorder is not None:
            recorder.close()



if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
