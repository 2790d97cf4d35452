"""Argument parsers shared by the emulator's entry point and ``gravcald --emulate``.

They raise ``argparse.ArgumentTypeError`` so argparse reports the option by name; keeping them
here (not in a command-line module) lets the service use them without importing a CLI.
"""
from __future__ import annotations

import argparse
import math


def speed_arg(text: str) -> float:
    """Time-lapse factor: a positive number, or 'max'/'inf' for no pacing."""
    if text.strip().lower() in ("max", "inf"):
        return math.inf
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"speed must be a number or 'max', got {text!r}") from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f"speed must be > 0, got {text!r}")
    return v


def disconnect_arg(text: str) -> tuple[float, float]:
    """``T:DUR`` [s of stream time]: unplug the device at T for DUR seconds."""
    try:
        start, dur = (float(x) for x in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected T:DUR in seconds (e.g. 30:5), got {text!r}") from None
    if start < 0 or dur <= 0:
        raise argparse.ArgumentTypeError(f"disconnect {text!r}: need T >= 0 and DUR > 0")
    return start, dur


def probability_arg(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a probability, got {text!r}") from None
    if not 0.0 <= v < 1.0:
        raise argparse.ArgumentTypeError(f"probability must be in [0, 1), got {text!r}")
    return v


def positive_arg(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return v
