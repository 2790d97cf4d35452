"""Shared pytest fixtures.

``measured_data_dir``: the folder of measured recordings (``$GRAVCAL_DATA``, default
``../shared/data``). Tests using it skip with a visible reason when the folder is absent,
and FAIL instead when ``GRAVCAL_REQUIRE_DATA=1`` (CI sets it, so CI always runs them).
"""
from __future__ import annotations

import pytest

from support.inputs import skip_or_fail


@pytest.fixture(scope="session")
def measured_data_dir():
    from gravcal.daemon.datasets import RECORDINGS, data_dir

    root = data_dir()
    missing = [name for name in RECORDINGS if not (root / name / "SOURCE.txt").is_file()]
    if missing:
        skip_or_fail(f"measured data not found: {', '.join(missing)} missing under {root} "
                     f"(set GRAVCAL_DATA to the folder holding them)", "GRAVCAL_REQUIRE_DATA")
    return root
