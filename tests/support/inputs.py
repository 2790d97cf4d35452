"""Inputs a test needs from outside the repository (measured data, a reader's own fixtures)."""
from __future__ import annotations

import os

import pytest


def skip_or_fail(reason: str, require_env: str) -> None:
    """Skip with ``reason``; fail instead when ``$require_env`` is 1 (CI sets it, so CI always runs the test)."""
    if os.environ.get(require_env) == "1":
        pytest.fail(f"{reason}; {require_env}=1 makes this a failure")
    pytest.skip(reason)
