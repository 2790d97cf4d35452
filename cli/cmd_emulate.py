"""``gravcal emulate``: the hardware-in-the-loop rig (the logger board, emulated).

The command line of ``gravcal.drivers.rigs.emulate`` (its docstring has the examples and the
stdout protocol); ``python -m gravcal.drivers.rigs.emulate`` is the same command.
"""
from __future__ import annotations

import argparse

from ..drivers.rigs import emulate
from .summaries import SUMMARIES


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("emulate", help=SUMMARIES["emulate"], description=emulate.DESCRIPTION)
    return emulate.configure_parser(p)


def run(args: argparse.Namespace) -> int:
    return emulate.run(args)
