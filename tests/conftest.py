"""Shared pytest fixtures.

``measured_data_dir``: the folder of measured recordings (``$GRAVCAL_DATA``, default
``../shared/data``). Tests using it skip with a visible reason when the folder is absent,
and FAIL instead when ``GRAVCAL_REQUIRE_DATA=1`` (CI sets it, so CI always runs them).

Under pytest-xdist (the README's command runs two workers with ``--dist loadgroup``, one per core of the
reference machine) the tests of a module with a module-scoped fixture (many hold the sessions several tests
assert on) stay together on one worker, so that fixture is computed once; other tests go one by one to
whichever worker is free; tests marked ``xdist_group("realtime")`` (rates, wake-ups,
deadlines in real time) run on one worker one after the other instead of beside each other. Each worker
limits BLAS to one thread: two workers already fill the cores and OpenBLAS's threads would only spin against
the other worker's (tests/core/seed_pool.py measured it for the seed pools; it runs its seeds in a plain loop
under xdist).

Before the session, gravcal's own sources are compiled into their ``__pycache__`` (git-ignored): the
suite starts a few hundred interpreters (the CLI, gravcald, emulators), and where PYTHONDONTWRITEBYTECODE
is set each of them would otherwise compile the package's ~90 modules again (~0.25 s a start).
"""
from __future__ import annotations

import compileall
import importlib.util
import os
import shutil
import tempfile
from pathlib import Path

import pytest

from support.inputs import skip_or_fail


_BLAS_LIMIT = None  # the xdist worker's threadpoolctl limit, kept for the worker's life


def pytest_sessionstart(session: pytest.Session) -> None:
    global _BLAS_LIMIT
    if os.environ.get("PYTEST_XDIST_WORKER"):
        import scipy.linalg  # noqa: F401  (numpy's and scipy's BLAS loaded, so that the limit reaches both)
        from threadpoolctl import threadpool_limits

        _BLAS_LIMIT = threadpool_limits(limits=1, user_api="blas")
    for package in ("gravcal", "gravcal.core", "gravcal.drivers", "gravcal.daemon"):
        spec = importlib.util.find_spec(package)
        for folder in (spec.submodule_search_locations or []) if spec else []:
            compileall.compile_dir(folder, quiet=2)  # only what is missing or older than its source


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist reads the groups off the items
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    # a worker's config.option.dist reads "no"; xdist's own loadgroup flag is set on the controller and workers
    if not config.getoption("loadgroup", False):
        return
    shared = {item.nodeid.split("::")[0] for item in items if _uses_a_module_fixture(item)}
    for item in items:
        module = item.nodeid.split("::")[0]
        if module in shared and not any(item.iter_markers("xdist_group")):
            item.add_marker(pytest.mark.xdist_group(module))


def _uses_a_module_fixture(item: pytest.Item) -> bool:
    info = getattr(item, "_fixtureinfo", None)
    return info is not None and any(d.scope in ("class", "module", "package")
                                    for defs in info.name2fixturedefs.values() for d in defs)


@pytest.fixture(scope="session")
def measured_data_dir():
    from gravcal.io.datasets import RECORDINGS, data_dir

    root = data_dir()
    missing = [name for name in RECORDINGS if not (root / name / "SOURCE.txt").is_file()]
    if missing:
        skip_or_fail(f"measured data not found: {', '.join(missing)} missing under {root} "
                     f"(set GRAVCAL_DATA to the folder holding them)", "GRAVCAL_REQUIRE_DATA")
    return root


@pytest.fixture
def short_tmp_path():
    """A fresh directory with a short path, removed after the test, for tests whose Unix sockets gravcald names
    under it: an AF_UNIX address holds 107 bytes, and pytest's tmp_path grows by pytest-xdist's popen-gwN/."""
    path = Path(tempfile.mkdtemp(prefix="gravcal-"))
    yield path
    shutil.rmtree(path, ignore_errors=True)
