"""The reproduction's thresholds against Lötters et al. (1998), Sect. 4, computed here, not written down.

Every comparison with the 3 % criterion carries a margin of t standard errors over the seeds, with t
chosen so that a correct simulation fails a test's whole family of comparisons with probability below
ALPHA (one-sided, Bonferroni over the comparisons, Student t with seeds - 1 degrees of freedom).
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import t as student_t

from gravcal.core.reproduce import ReproduceResult, reproduce_cases
from gravcal.core.reproduce_config import (DEFAULT_THETA_STEP_DEG, ReproduceConfig, paper_threshold_on_grid,
                                           theta_grid)
from seed_pool import pmap

ALPHA = 1e-3
LIMIT = ReproduceConfig().threshold_pct


def margin_t(comparisons: int, seeds: int) -> float:
    return float(student_t.ppf(1.0 - ALPHA / comparisons, seeds - 1))


def runs_at(key: str, theta: float, seeds: int, settings: dict) -> tuple[np.ndarray, np.ndarray]:
    """reproduce_cases at one theta: (sensitivity runs (1, seeds, 3), offset runs (1, seeds, 3))."""
    res = reproduce_cases((key,), ReproduceConfig(theta_deg=np.array([theta]), seeds=seeds, **settings))
    return res.runs_sensitivity_pct[key], res.runs_offset_pct[key]


def reproduce_by_theta(key: str, theta, seeds: int, **settings) -> ReproduceResult:
    """reproduce_cases((key,), ...) with each theta run in a worker process: every (theta, seed) run draws from
    its own generator, so the joined result is the one-call result run for run
    (test_the_monte_carlo_split_by_theta_is_the_one_call_monte_carlo)."""
    cfg = ReproduceConfig(theta_deg=np.asarray(theta, dtype=float), seeds=seeds, **settings)
    cfg.validate()
    parts = pmap(runs_at, [(key, float(th), seeds, settings) for th in cfg.theta_deg])
    return ReproduceResult(cfg.theta_deg, {key: np.concatenate([p[0] for p in parts])},
                           {key: np.concatenate([p[1] for p in parts])}, cfg)


def curve(key: str, theta, seeds: int, **settings) -> tuple[np.ndarray, np.ndarray, float | None]:
    res = reproduce_by_theta(key, theta, seeds, **settings)
    err, se = res.error_and_se_pct(key)
    return err, se, res.thresholds_deg[key]


@pytest.mark.parametrize("key, settings", [("o1_all", {}), ("o2_offsets", {"held_sensitivity_error": 0.05})])
def test_the_monte_carlo_split_by_theta_is_the_one_call_monte_carlo(key, settings):
    theta = [15.0, 90.0, 165.0]
    whole = reproduce_cases((key,), ReproduceConfig(theta_deg=np.array(theta), seeds=4, **settings))
    split = reproduce_by_theta(key, theta, 4, **settings)
    np.testing.assert_array_equal(split.runs_offset_pct[key], whole.runs_offset_pct[key])
    np.testing.assert_array_equal(split.runs_sensitivity_pct[key], whole.runs_sensitivity_pct[key])
    assert split.thresholds_deg == whole.thresholds_deg


def assert_above(err, se, t, theta):
    for th, e, s in zip(theta, err, se):
        assert e - t * s > LIMIT, f"θ={th:g}°: {e:.2f} ± {s:.2f} % is not significantly above {LIMIT:g} %"


def assert_below(err, se, t, theta):
    for th, e, s in zip(theta, err, se):
        assert e + t * s < LIMIT, f"θ={th:g}°: {e:.2f} ± {s:.2f} % is not significantly below {LIMIT:g} %"


@pytest.mark.parametrize("key, step, seeds", [
    ("o1_all", DEFAULT_THETA_STEP_DEG, 20), ("o2_all", DEFAULT_THETA_STEP_DEG, 20),
    pytest.param("o1_all", 5.0, 80, marks=pytest.mark.slow), pytest.param("o2_all", 5.0, 80, marks=pytest.mark.slow),
])
def test_all_parameter_thresholds_within_one_grid_step_of_the_papers(key, step, seeds):
    """Paper: orientation 1 needs θ > 105°, orientation 2 θ >= 75°. Our threshold is within one grid step
    of the first grid point the paper's statement allows: the error is significantly above 3 % two steps
    before that point (so our threshold is later) and significantly below from one step after it on."""
    grid = theta_grid(step)
    paper = paper_threshold_on_grid(key, grid)
    theta = grid[grid >= paper - 2 * step]
    err, se, thr = curve(key, theta, seeds)
    assert thr is not None and abs(thr - paper) <= step, (key, thr, paper)
    after = theta >= paper + step
    t = margin_t(1 + int(after.sum()), seeds)
    assert_above(err[:1], se[:1], t, theta[:1])
    assert_below(err[after], se[after], t, theta[after])


@pytest.fixture(scope="module")
def offsets_only_at_15():
    """Orientation 1, offsets only, at θ = 15° over 200 seeds: the point that decides the threshold."""
    return curve("o1_offsets", [15.0], 200)


def test_offsets_only_threshold_is_15_degrees_and_not_a_grid_artefact(offsets_only_at_15):
    """Default reading: the error is under 3 % from θ = 15° on, on a 5° grid as on the 15° one, so the
    paper's "larger than 30°" (first point allowed on our grid: 45°) is not reached by refining the grid:
    10° is significantly above 3 %, and 15° ... 45° significantly below (larger θ: the next test)."""
    err15, se15, _ = offsets_only_at_15
    theta = np.array([10.0, 20.0, 25.0, 30.0, 35.0, 40.0, 45.0])
    seeds = 40
    err, se, _ = curve("o1_offsets", theta, seeds)
    t = margin_t(len(theta) + 1, seeds)
    assert_above(err[:1], se[:1], t, theta[:1])
    assert_below(err[1:], se[1:], t, theta[1:])
    assert_below(err15, se15, margin_t(len(theta) + 1, 200), [15.0])


def test_offsets_only_full_grid_threshold_two_steps_before_the_papers():
    grid = theta_grid(DEFAULT_THETA_STEP_DEG)
    paper = paper_threshold_on_grid("o1_offsets", grid)
    seeds = 20
    err, se, thr = curve("o1_offsets", grid, seeds)
    assert thr == 15.0 and paper - thr == 2 * DEFAULT_THETA_STEP_DEG
    t = margin_t(len(grid) - 1, seeds)
    assert_above(err[:1], se[:1], t, grid[:1])
    assert_below(err[2:], se[2:], t, grid[2:])  # 15° itself: the 200-seed test above


@pytest.mark.parametrize("settings", [{"held_sensitivity_error": 0.05}, {"spread": "angle"}, {"criterion": "worst"},
                                      {"n_points": 30}], ids=lambda s: next(iter(s)))
def test_each_surviving_explanation_moves_offsets_only_to_30_but_not_past_it(settings):
    """docs/loetters.md: each of these settings alone lifts the 15° error significantly above 3 %, so the
    threshold becomes 30° on the 15° grid (one step before the paper's first allowed point, 45°), and
    none lifts the error at 30° to 3 %: none reproduces "larger than 30°" read like "larger than 105°"."""
    seeds = 200
    err, se, _ = curve("o1_offsets", [15.0, 30.0], seeds, **settings)
    t = margin_t(2, seeds)
    assert_above(err[:1], se[:1], t, [15.0])
    assert_below(err[1:], se[1:], t, [30.0])
