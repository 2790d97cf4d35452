"""The C programs in bench/ (the floors bench scripts compare gravcald with), built as those scripts build them."""
from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"


def build_bench_program(name: str, directory: Path) -> str:
    """bench/NAME.c compiled with ``cc`` (warnings as errors) into ``directory``; the test is skipped without a
    compiler, as the bench script skips that floor."""
    if shutil.which("cc") is None:
        pytest.skip(f"no C compiler (cc): the bench scripts skip bench/{name}.c too")
    exe = str(directory / name)
    subprocess.run(["cc", "-O2", "-Wall", "-Werror", "-o", exe, str(BENCH / f"{name}.c")], check=True)
    return exe
