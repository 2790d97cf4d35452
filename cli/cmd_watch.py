"""``gravcal watch``: print calibrated samples and calibration changes from gravcald."""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from typing import Any, TextIO

from ..clients.client import Client, ClientError, ProtocolMismatchError, default_socket_path
from ..closed_pipe import write_or_stop
from ..errors import InputError
from ..daemon.protocol import STANDARD_GRAVITY
from .summaries import SUMMARIES

RECONNECT_S = 1.0  # between attempts to reach gravcald again (--reconnect)
STATIC_WORDS = {True: "static", False: "moving"}  # null: the detector had no decision recent enough


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "watch",
        help=SUMMARIES["watch"],
        description="Connect to gravcald's socket and print calibrated samples (m/s²) and calibration changes.",
    )
    p.add_argument("--socket", metavar="PATH", default=None,
                   help=f"gravcald socket (default: $GRAVCAL_SOCKET or {default_socket_path()})")
    p.add_argument("--rate", metavar="HZ", type=float, default=10.0,
                   help="at most this many samples per second (0: every sample; default 10)")
    p.add_argument("--raw", action="store_true", help="also show the raw duty cycles")
    p.add_argument("--count", metavar="N", type=int, default=0, help="stop after N samples (default: run until Ctrl-C)")
    p.add_argument("--json", action="store_true", help="print the server's JSON messages as they are")
    p.add_argument("--timeout", metavar="S", type=float, default=10.0,
                   help="give up when nothing arrives for S seconds (default 10)")
    p.add_argument("--reconnect", action="store_true",
                   help="when gravcald is not there, stops or goes silent for --timeout, say so on stderr and "
                        "connect again (until Ctrl-C), instead of ending with an error")
    p.set_defaults(func=run)
    return p


def format_imu(msg: dict[str, Any], raw: bool = False) -> str:
    acc = msg.get("acc") or [None] * 3
    if all(isinstance(v, (int, float)) for v in acc):
        norm = math.sqrt(sum(v * v for v in acc))
        acc_s = " ".join(f"{v:+8.3f}" for v in acc) + f"  |a| {norm:7.3f} m/s² ({norm / STANDARD_GRAVITY:6.4f} g)"
    else:
        acc_s = "acc unavailable (missing channel)"
    gyro = msg.get("gyro")
    gyro_s = f"  gyro {gyro:+7.3f} rad/s" if isinstance(gyro, (int, float)) else ""
    line = f"IMU {msg.get('seq'):>9} t {msg.get('t', float('nan')):12.3f} s  acc {acc_s}{gyro_s}  {STATIC_WORDS.get(msg.get('static'), 'unknown')}"
    if raw and msg.get("duty") is not None:
        line += "  duty " + " ".join("  null  " if d is None else f"{d:.5f}" for d in msg["duty"])
    return line


def format_calib(msg: dict[str, Any]) -> str:
    off = msg.get("offset") or []
    sens = msg.get("sensitivity") or []
    diag = [row[i] for i, row in enumerate(sens)] if sens else []
    state = "accepted" if msg.get("accepted") else "not accepted"
    return (
        f"CALIB revision {msg.get('revision')} model {msg.get('model')} ({state}, {msg.get('n_windows', 0)} windows)"
        f"  offset {' '.join(f'{v:.5f}' for v in off)}  sensitivity {' '.join(f'{v:.5f}' for v in diag)} /g"
        + (f"  {msg['message']}" if msg.get("message") else "")
    )


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    out = out or sys.stdout
    if args.rate is not None and (args.rate < 0 or not math.isfinite(args.rate)):
        raise InputError(f"--rate must be a number of Hz >= 0, got {args.rate}")
    if args.count < 0:
        raise InputError(f"--count must be >= 0, got {args.count}")
    seen = [0]
    if not args.reconnect:
        with Client(args.socket, timeout=args.timeout) as client:
            return _print_stream(client, args, out, seen)
    lost = None
    while True:
        try:
            with Client(args.socket, timeout=args.timeout) as client:
                if lost is not None:
                    _note(f"gravcal watch: connected again to {client.path}")
                    lost = None
                return _print_stream(client, args, out, seen)
        except ProtocolMismatchError:
            raise
        except ClientError as exc:
            if lost != str(exc):  # once per cause, not once per attempt
                _note(f"gravcal watch: {exc}; connecting again every {RECONNECT_S:g} s (Ctrl-C stops)")
                lost = str(exc)
        time.sleep(RECONNECT_S)


def _note(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _print_stream(client: Client, args: argparse.Namespace, out: TextIO, seen: list[int]) -> int:
    """Print the watch until --count samples (``seen`` counts them across reconnections) or a closed pipe."""
    for msg in client.watch(rate=args.rate, raw=args.raw):
        cls = msg.get("class")
        text = None
        if args.json:
            text = json.dumps(msg, separators=(",", ":"))
        elif cls == "IMU":
            text = format_imu(msg, args.raw)
        elif cls == "CALIB":
            text = format_calib(msg)
        elif cls == "DROPPED":
            text = f"DROPPED {msg.get('count')} messages (too slow; {msg.get('total')} in total)"
        elif cls == "DEVICE":
            text = f"DEVICE {msg.get('path')} " + ("connected" if msg.get("connected") else "gone (no samples until back)")
        if text is not None and not write_or_stop(text, out):
            return 0  # the reader closed the pipe (| head): done
        if cls == "ERROR" and not args.json:
            print(f"ERROR {msg.get('message')}", file=sys.stderr, flush=True)
        if cls == "IMU":
            seen[0] += 1
            if args.count and seen[0] >= args.count:
                return 0
    return 0
