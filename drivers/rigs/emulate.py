"""The emulator's entry point: the logger board, emulated, as a process of its own.

    python -m gravcal.drivers.rigs.emulate --bus serial --scenario daily_living --speed 10 --disconnect-at 30:5
    python -m gravcal.drivers.rigs.emulate --bus can --replay walk.csv --drop 0.01
    python -m gravcal.drivers.rigs.emulate --bus i2c --scenario static --fifo-depth 8

(``gravcal emulate`` is the same command.) Prints the driver spec to use (first line of stdout: serial/can a
stable symlink to a pty, e.g. ``serial:///tmp/gravcal-emu-x/ttyGRAVCAL0``; i2c ``i2c://1/0x42``, the
logger behind ``/dev/i2c-1`` of a umockdev testbed, for a host started with the environment printed on
stderr: ``LD_PRELOAD=libumockdev-preload.so.0 UMOCKDEV_DIR=...``), then streams until the source ends (or
Ctrl-C), printing ``event:`` lines for disconnects and a final ``done:`` line.
``--record FILE.npz`` writes every sample sent and its fate (sent, dropped, corrupted,
offline, ...) to compare with what the host got.
"""
from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
from typing import Sequence

import numpy as np

from ..codec import FRAME_LEN
from .can_links import SlcanPtyLink
from .emulator import Emulator, Faults, PtyLink, SentLog
from .fake_i2c import I2C_RDWR_MAX_LEN, FakeI2CDevice, realtime_options
from .i2c_dev import I2CDevServer
from .options import disconnect_arg, positive_arg, probability_arg, speed_arg
from .sources import replay_source, scenario_source

DESCRIPTION = "emulate the logger on a serial pty, slcan pty, or /dev/i2c-N (umockdev)"
STREAM_LINKS = {"serial": PtyLink, "can": SlcanPtyLink}
"""--bus -> the link the emulator pushes frames onto (i2c is pulled: see _run_i2c)."""


def configure_parser(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    p.add_argument("--bus", choices=("serial", "can", "i2c"), default="serial", help="bus to emulate (default serial)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--scenario", default="daily_living",
                     help="sensor-model scenario (gravcal.core.scenarios), or 'pattern' for a test pattern")
    src.add_argument("--replay", metavar="FILE", help="replay a recording with timer counts (.csv/.npy)")
    p.add_argument("--speed", type=speed_arg, default=1.0, help="time-lapse factor (1 = real time; 'max' = no pacing)")
    p.add_argument("--seed", type=int, default=0, help="seed of the scenario and of the injected faults")
    p.add_argument("--duration", type=positive_arg, default=60.0, help="stream seconds to emulate (default 60)")
    p.add_argument("--fs", type=positive_arg, default=100.0, help="sample rate [Hz] (default 100)")
    p.add_argument("--link", metavar="PATH", help="serial/can: stable path of the pty (default in a temp dir)")
    p.add_argument("--ber", type=probability_arg, default=0.0, help="bit-error rate (serial bytes, I2C bursts; CAN: frame loss)")
    p.add_argument("--drop", type=probability_arg, default=0.0, help="probability that a frame is not sent")
    p.add_argument("--disconnect-at", type=disconnect_arg, action="append", default=[], metavar="T:DUR",
                   help="unplug the device at stream time T for DUR seconds (repeatable)")
    p.add_argument("--fifo-depth", type=int, default=32, help="i2c: FIFO depth in frames (small values provoke overflows)")
    p.add_argument("--testbed", metavar="DIR",
                   help="i2c: the umockdev testbed directory to serve /dev/i2c-1 in (default a temporary one)")
    p.add_argument("--record", metavar="FILE.npz", help="write every sample sent and its fate")
    p.add_argument("--linger", type=float, default=0.0, metavar="S",
                   help="keep the device open S seconds after the stream ends (-1: until interrupted)")
    p.add_argument("--stop-at-stdin-eof", action="store_true",
                   help="also stop when stdin is closed (a parent that may lose the right to signal this process)")
    return p


def _source(args):
    if args.replay:
        return replay_source(args.replay)
    return scenario_source(args.scenario, seed=args.seed, fs=args.fs, duration=args.duration)


def _say(text: str) -> None:
    print(text, flush=True)


def run(args: argparse.Namespace) -> int:
    """Emulate until the source ends (or a stop signal); 0 when done. Bad input raises ValueError."""
    faults = Faults(ber=args.ber, drop=args.drop, disconnects=args.disconnect_at, seed=args.seed)
    source = _source(args)
    sent_log = SentLog() if args.record else None
    stop = threading.Event()
    _install_stop(stop)
    if args.stop_at_stdin_eof:
        threading.Thread(target=_stop_at_eof, args=(stop,), daemon=True).start()
    if args.bus == "i2c":
        return _run_i2c(args, source, faults, sent_log, stop)
    link = STREAM_LINKS[args.bus](args.link)
    emu = Emulator(source.blocks, source.fs, link, speed=args.speed, faults=faults, log=sent_log, stop=stop,
                   on_event=lambda text: _say(f"event: {text}"))
    started = threading.Event()
    connect = link.connect

    def connect_and_announce() -> None:  # print the spec once the first pty exists
        connect()
        if not started.is_set():
            started.set()
            _say(link.spec)

    link.connect = connect_and_announce
    try:
        n = emu.run()
        if sent_log is not None:
            sent_log.save(args.record)
        counts = sent_log.counts() if sent_log is not None else {}
        _say("done: samples=%d %s" % (n, " ".join(f"{k}={v}" for k, v in counts.items())))
        if args.linger:
            emu.linger(None if args.linger < 0 else args.linger)
    finally:
        link.close()
    return 0


def _run_i2c(args, source, faults, sent_log, stop) -> int:
    """Serve the device at /dev/i2c-1 of a umockdev testbed until stopped; the host reads it (i2c_dev.py)."""
    speed = args.speed if math.isfinite(args.speed) else 100.0  # a FIFO needs a finite pace
    device = FakeI2CDevice(source.blocks, source.fs, speed=speed, fifo_depth=args.fifo_depth, faults=faults,
                           log=sent_log)
    with I2CDevServer(device, bus=1, testbed=args.testbed) as server:
        # a time-lapse fills the FIFO faster than the driver's default poll assumes: poll at a quarter of its fill
        # and drain it in one transfer
        poll = realtime_options(device).get("poll_s")
        burst = min(device.depth, I2C_RDWR_MAX_LEN // FRAME_LEN)
        _say(f"i2c://{server.bus}/0x{device.address:02X}" + (f"?poll_s={poll:.4g}&burst_frames={burst}" if poll else ""))
        print(f"gravcal emulate: the logger is /dev/i2c-{server.bus} for a process started with "
              f"{' '.join(f'{k}={v}' for k, v in server.env({}).items())}", file=sys.stderr, flush=True)
        while not stop.wait(0.2):
            with device._lock:
                device._advance()  # the FIFO fills with time whether or not the host reads
            if device.exhausted:
                break
        if sent_log is not None:
            np.savez(args.record, **device.fates())
        _say(f"done: samples={device._produced} accesses={device.accesses}")
        if args.linger and not stop.is_set():
            stop.wait(None if args.linger < 0 else args.linger)
    return 0


def _stop_at_eof(stop: threading.Event) -> None:
    while sys.stdin.buffer.read(4096):
        pass
    stop.set()


def _install_stop(stop: threading.Event) -> None:
    if threading.current_thread() is not threading.main_thread():
        return

    def handler(signum, frame):
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)


def main(argv: Sequence[str] | None = None) -> int:
    parser = configure_parser(argparse.ArgumentParser(prog="gravcal emulate", description=DESCRIPTION))
    args = parser.parse_args(argv)
    try:
        return run(args)
    except (ValueError, OSError) as exc:
        print(f"gravcal emulate: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
