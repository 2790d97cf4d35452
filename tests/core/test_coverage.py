"""Every std the batch fit states covers the truth, on sessions gravcal's simulator did not make.

The sessions come from tests/support/independent_sessions.py (the physics written anew, its own random
streams): 100 seeds of each of eleven kinds (a plain worn sensor; leaned axes, worn and in a lab, fitted with
6+misalignment and with the in-use 9; offsets and gains driven by temperature or drifting in time; an offset
following the supply; a quadratic bow; offsets with the sensitivities held from a previous calibration). Each is fitted with the model it was made with, and every
stated quantity is scored as z = (estimate - truth) / stated std: offsets, sensitivities, the cross-axis terms,
the misalignment angles and each term's magnitude in its report units.

Tolerances, from the counts: with n independent standard normal z the RMS lies within sqrt(chi²_n quantiles / n)
and the number beyond 2σ within the binomial (n, 4.55 %) quantiles (``coverage_runs.rms_bounds`` /
``beyond_2sigma_bounds``), each at a two-sided level of 1e-3 shared (Bonferroni) by the checks of its test:
10 quantities pooled over the kinds, 40 (kind, quantity) cells. Pooled offsets and sensitivities (n ~ 3000)
then lie within ~[0.95, 1.05], inside the issue's band [0.9, 1.1]; one term or the angles (n ~ 300-900) within
~[0.85, 1.15]: there the band would be only ±2.5 sampling std wide, and bench/bench_coverage.py shows it at 400
seeds a kind (every cell in [0.9, 1.1]; the std are ~2-5 % small in worn sessions, docs/coverage.md). A std
scaled by 0.7 puts the RMS near 1.4, by 1.4 near 0.7: far outside either.
"""
from __future__ import annotations

import numpy as np
import pytest

from seed_pool import pmap
from tests.support.coverage_runs import KINDS, QUANTITIES, beyond_2sigma_bounds, pooled, rms, rms_bounds

SEEDS = range(100)
ALPHA = 1e-3  # two-sided level of each test, shared by its checks
POOLED_CHECKS, CELL_CHECKS = len(QUANTITIES), 40
MAX_UNSCORED = 0.15  # at most this share of a kind's sessions refused or stated as not determined (measured: 0-13 %,
# the most for the bow, which upright postures cannot tell from the gains): a fit that flags everything fails


@pytest.fixture(scope="module")
def z_by_kind():
    return pooled(KINDS, SEEDS, mapper=lambda fn, args: pmap(fn, args))


def _pooled(z_by_kind, q):
    parts = [d[q] for d in z_by_kind.values() if q in d]
    return np.concatenate(parts) if parts else np.zeros(0)


def test_almost_every_session_is_scored(z_by_kind):
    for kind, d in z_by_kind.items():
        unscored = len(d.get("refused", ())) + len(d.get("flagged", ()))
        assert unscored <= MAX_UNSCORED * len(SEEDS), f"{kind}: {unscored} of {len(SEEDS)} sessions refused or not determined"


@pytest.mark.parametrize("quantity", QUANTITIES)
def test_pooled_rms_z(z_by_kind, quantity):
    z = _pooled(z_by_kind, quantity)
    assert z.size >= 3 * int((1 - MAX_UNSCORED) * len(SEEDS)), f"{quantity}: only {z.size} estimates scored"
    lo, hi = rms_bounds(z.size, ALPHA / POOLED_CHECKS)
    r = rms(z)
    assert lo <= r <= hi, f"{quantity}: RMS z {r:.3f} over {z.size}, outside the chi² bounds [{lo:.3f}, {hi:.3f}]"


@pytest.mark.parametrize("quantity", QUANTITIES)
def test_pooled_share_beyond_2_sigma(z_by_kind, quantity):
    z = _pooled(z_by_kind, quantity)
    lo, hi = beyond_2sigma_bounds(z.size, ALPHA / POOLED_CHECKS)
    k = int(np.sum(np.abs(z) > 2))
    assert lo <= k <= hi, f"{quantity}: {k} of {z.size} beyond 2σ (binomial bounds [{lo}, {hi}])"


@pytest.mark.parametrize("kind", KINDS)
def test_each_kind_rms_z_within_chi2_bounds(z_by_kind, kind):
    for q, z in z_by_kind[kind].items():
        if q in ("refused", "flagged"):
            continue
        lo, hi = rms_bounds(z.size, ALPHA / CELL_CHECKS)
        assert lo <= rms(z) <= hi, f"{kind} {q}: RMS z {rms(z):.3f} over {z.size}, outside [{lo:.3f}, {hi:.3f}]"
