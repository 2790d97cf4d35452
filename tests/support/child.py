"""Code under test run in a child Python process, so a hang (e.g. LAPACK looping on a NaN) fails its test
after a timeout instead of hanging the suite."""
from __future__ import annotations

import subprocess
import sys

import pytest


def run_child(code: str, *args: str, timeout: float, what: str) -> str:
    """The standard output of ``python -c code args...``; the test fails when the child does not end within
    ``timeout`` s (naming ``what`` it was doing) or ends with an error (its stderr's tail)."""
    try:
        out = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        pytest.fail(f"no result within {timeout:g} s: {what}")
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout
