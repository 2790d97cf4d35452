"""The C programs in bench/ (the floors bench scripts compare gravcald with), built as those scripts build them."""
from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"


def build_bench_program(name: str, directory: Path) -> str:
    """bench/NAME.c compiled with ``cc`` (warnings as errors) into ``directory``. A compiler is there wherever
    gravcal was installed from this checkout (its own C extensions need one), so its absence fails the test."""
    if shutil.which("cc") is None:
        pytest.fail(f"no C compiler (cc) to build bench/{name}.c; gravcal's own extensions need one too")
    exe = str(directory / name)
    subprocess.run(["cc", "-O2", "-Wall", "-Werror", "-o", exe, str(BENCH / f"{name}.c")], check=True)
    return exe
