"""Output into a pipe the reader closed early (``gravcald --print-config | head``) ends quietly."""
from __future__ import annotations

import os
import sys


def write_or_stop(text: str, out=None) -> bool:
    """Print ``text`` and flush; False when the reader has gone (the rest is not wanted).

    stdout is then pointed at /dev/null so that the interpreter's own flush at exit does not raise
    the BrokenPipeError again (the recipe of the Python signal module's documentation)."""
    out = out or sys.stdout
    try:
        print(text, file=out, flush=True)
        return True
    except BrokenPipeError:
        if out is sys.stdout:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
        return False
