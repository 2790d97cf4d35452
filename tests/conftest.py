"""Shared pytest fixtures.

``measured_data_dir``: the folder of measured recordings (``$GRAVCAL_DATA``, default
``../shared/data``). Tests using it skip with a visible reason when the folder is absent,
and FAIL instead when ``GRAVCAL_REQUIRE_DATA=1`` (CI sets it, so CI always runs them).

Before the session, gravcal's own sources are compiled into their ``__pycache__`` (git-ignored): the
suite starts a few hundred interpreters (the CLI, gravcald, emulators), and where PYTHONDONTWRITEBYTECODE
is set each of them would otherwise compile the package's ~90 modules again (~0.25 s a start).
"""
from __future__ import annotations

import compileall
import importlib.util

import pytest

from support.inputs import skip_or_fail


def pytest_sessionstart(session: pytest.Session) -> None:
    for package in ("gravcal", "gravcal.core", "gravcal.drivers", "gravcal.daemon"):
        spec = importlib.util.find_spec(package)
        for folder in (spec.submodule_search_locations or []) if spec else []:
            compileall.compile_dir(folder, quiet=2)  # only what is missing or older than its source


@pytest.fixture(scope="session")
def measured_data_dir():
    from gravcal.io.datasets import RECORDINGS, data_dir

    root = data_dir()
    missing = [name for name in RECORDINGS if not (root / name / "SOURCE.txt").is_file()]
    if missing:
        skip_or_fail(f"measured data not found: {', '.join(missing)} missing under {root} "
                     f"(set GRAVCAL_DATA to the folder holding them)", "GRAVCAL_REQUIRE_DATA")
    return root
