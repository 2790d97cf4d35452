"""The paper's Sections 3-4 simulation (core.reproduce)."""
from __future__ import annotations

import numpy as np
import pytest

from gravcal.core.reproduce import (KEYS, ReproduceConfig, cap_directions, first_theta_staying_below, make_figure,
                                    reproduce_loetters, simulate_run)


def test_cap_directions_lie_in_the_cap_symmetric_about_standing():
    rng = np.random.default_rng(0)
    d = np.ones(3) / np.sqrt(3)
    v = cap_directions(rng, 20000, 60.0, d)
    ang = np.degrees(np.arccos(np.clip(v @ d, -1, 1)))
    assert ang.max() <= 60.0 + 1e-9 and ang.max() > 59.0
    assert np.allclose(np.linalg.norm(v, axis=1), 1.0)
    m = v.mean(axis=0)
    assert np.degrees(np.arccos(m @ d / np.linalg.norm(m))) < 1.0  # symmetric: mean direction = standing
    # uniform over the cap area: cos(angle) uniform on [cos 60°, 1] -> mean 0.75
    assert abs(np.cos(np.radians(ang)).mean() - 0.75) < 0.01


def test_first_theta_staying_below():
    th = np.array([0, 15, 30, 45, 60.0])
    assert first_theta_staying_below(th, np.array([9, 2, 4, 2, 1.0]), 3.0) == 45.0
    assert first_theta_staying_below(th, np.array([1, 2, 2, 2, 1.0]), 3.0) == 0.0
    assert first_theta_staying_below(th, np.array([1, 2, 2, 2, 5.0]), 3.0) is None


def test_errors_shrink_with_theta_and_reading_validated():
    cfg = ReproduceConfig(seeds=1)
    small = np.mean([simulate_run(30.0, 1, "6", s, cfg)[0].mean() for s in range(6)])
    large = np.mean([simulate_run(180.0, 1, "6", s, cfg)[0].mean() for s in range(6)])
    assert large < 3.0 < small
    with pytest.raises(ValueError, match="c_mu_reading"):
        reproduce_loetters(c_mu_reading="percent")
    with pytest.raises(ValueError, match="unknown reproduce option"):
        reproduce_loetters(n_point=5)


@pytest.mark.slow
def test_thresholds_order_as_in_the_paper():
    """Computed, not hard-coded: offsets-only needs a smaller theta than all parameters, and
    orientation 2 (gravity spread over the axes) a smaller theta than orientation 1. With 8 seeds
    the curves are noisy near 3 %, but the gaps are >= 45° at the default settings."""
    res = reproduce_loetters(seeds=8)
    thr = res.thresholds_deg
    assert set(thr) == set(KEYS)
    assert thr["o1_all"] is not None and thr["o2_all"] is not None
    assert thr["o1_offsets"] < thr["o1_all"]
    assert thr["o2_all"] < thr["o1_all"]
    assert thr["o2_offsets"] < thr["o2_all"]
    # the error at full coverage is well under the criterion for every key
    for k in KEYS:
        assert res.error_pct(k)[-1] < 3.0
    d = res.to_dict()
    assert d["config"]["sigma_mu_g"] == pytest.approx(0.05)
    fig = make_figure(res)
    assert len(fig.axes) == 4


@pytest.mark.parametrize("setting, value", [("criterion", "median"), ("spread", "ring"), ("held_sensitivity_error", -0.1),
                                            ("theta_deg", np.array([30.0, 15.0]))])
def test_bad_settings_are_named(setting, value):
    with pytest.raises(ValueError, match=setting):
        reproduce_loetters(**{setting: value})
