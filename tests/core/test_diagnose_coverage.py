"""The std diagnose states for a named term's magnitude covers the truth, on sessions gravcal's simulator did not
make (tests/support/independent_sessions.py; scored by tests/support/diagnose_coverage.py).

Kinds whose planted term is named in most sessions (a temperature offset, a supply offset, an offset drift, leaned
axes: 55-95 % named at seeds 1000-1099), 40 seeds each, in the regime where the std is purely statistical (a
6-parameter baseline and every axis of the term determined). The z of the four kinds are pooled (n ~ 200):
their RMS must lie within the chi² bounds of n independent standard normal z and the count beyond 2σ within
the binomial (n, 4.55 %) bounds, each at a two-sided level of 1e-3. A std scaled by 0.7 puts the RMS near
1.5, by 1.4 near 0.75: outside both. The conditioning on being named is weak at these sizes; the kinds near the
detection floor and the held regime are measured, not asserted (docs/coverage.md, "diagnose's magnitudes").
"""
from __future__ import annotations

import numpy as np
import pytest

from seed_pool import pmap
from tests.support.coverage_runs import beyond_2sigma_bounds, rms, rms_bounds
from tests.support.diagnose_coverage import session_z

KINDS = ("temperature_offset", "supply_offset", "offset_drift", "misaligned")
SEEDS = range(40)
ALPHA = 1e-3


@pytest.fixture(scope="module")
def z():
    args = [(k, s) for k in KINDS for s in SEEDS]
    out = []
    for res in pmap(session_z, args):
        out += [v for q, zs in res.items() if "|" not in q and q not in ("refused", "not_found") for v in zs]
    return np.asarray(out)


def test_named_magnitudes_rms_z(z):
    assert z.size >= 150, f"only {z.size} magnitudes scored"
    lo, hi = rms_bounds(z.size, ALPHA)
    assert lo <= rms(z) <= hi, f"RMS z {rms(z):.3f} over {z.size}, outside the chi² bounds [{lo:.3f}, {hi:.3f}]"


def test_named_magnitudes_share_beyond_2_sigma(z):
    lo, hi = beyond_2sigma_bounds(z.size, ALPHA)
    k = int(np.sum(np.abs(z) > 2))
    assert lo <= k <= hi, f"{k} of {z.size} beyond 2σ (binomial bounds [{lo}, {hi}])"
