"""Faster forms in core/diagnosis against the plain forms they replace (kept here as the oracles): same
numbers, bit for bit.

quantization_test evaluates the two likelihoods per distinct sample value (quantised samples take few) and
gathers the per-sample terms, summed over the samples in their order as the plain form does; the plain form
evaluated every sample at every point of the noise-std search.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import ndtr

from gravcal.core.diagnosis.noise import (DELTA_BIC, _loglik_continuous, _loglik_quantised, _on_grid, lsb_of,
                                         quantization_test)


def loglik_oracle(vals: list[np.ndarray], s: float, lsb: float) -> tuple[float, float]:
    """Continuous and quantised log-likelihoods of the stretches, every sample evaluated."""
    la, lb = 0.0, 0.0
    for v in vals:
        mu = float(v.mean())
        z = (v - mu) / s
        la += float(np.sum(-0.5 * z * z - math.log(s * math.sqrt(2 * math.pi)) + math.log(lsb)))
        p = ndtr((v - mu + lsb / 2) / s) - ndtr((v - mu - lsb / 2) / s)
        lb += float(np.sum(np.log(np.maximum(p, 1e-300))))
    return la, lb


def quantization_oracle(stretches_raw: list[np.ndarray], scale: np.ndarray) -> dict:
    """The per-sample form of noise.quantization_test."""
    res: dict = {"axes": [], "found": False}
    if not stretches_raw:
        res["why"] = "no static stretch"
        return res
    dbic_tot, held_gain_tot = 0.0, 0.0
    for ax in range(3):
        parts = [s[:, ax] for s in stretches_raw]
        allv = np.concatenate(parts)
        lsb = lsb_of(allv[: 200_000])
        if lsb == 0.0:
            res["axes"].append({"lsb_mg": 0.0, "delta_bic": None})
            continue

        def loglik(vals, s):
            return loglik_oracle(vals, s, lsb)

        def best_s(vals):
            var = float(np.mean(np.concatenate([v - v.mean() for v in vals]) ** 2))
            s_a = math.sqrt(max(var, 1e-30))
            grid = s_a * np.linspace(0.05, 1.2, 47)
            lb = [loglik(vals, g)[1] for g in grid]
            return s_a, float(grid[int(np.argmax(lb))])

        s_a, s_b = best_s(parts)
        la, _ = loglik(parts, s_a)
        _, lb = loglik(parts, s_b)
        d_bic = 2 * (lb - la) - math.log(allv.size)
        half = len(parts) // 2
        early, late = parts[:half], parts[half:]
        if early:
            sa_e, sb_e = best_s(early)
            held = loglik(late, sb_e)[1] - loglik(late, sa_e)[0]
        else:
            held = 0.0
        dbic_tot += d_bic
        held_gain_tot += held
        res["axes"].append({"lsb_raw": lsb, "lsb_mg": lsb / scale[ax] * 1e3, "noise_std_lsb": s_b / lsb,
                            "delta_bic": round(d_bic, 2), "heldout_loglik_gain": round(held, 2)})
    res["delta_bic"] = round(dbic_tot, 2)
    res["heldout_loglik_gain"] = round(held_gain_tot, 2)
    res["found"] = bool(dbic_tot > DELTA_BIC and held_gain_tot > 0)
    return res


def stretches(seed: int, noise_lsb: float, lsb: float, n_parts: int) -> list[np.ndarray]:
    """Static stretches of different lengths and levels on a grid of ``lsb`` (an axis may be continuous)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_parts):
        n = int(rng.integers(300, 5000))
        level = rng.integers(-500, 500, 3) + 0.3  # 0.3 step from a grid line: a latent std well inside the search
        x = np.round((level + rng.normal(0, noise_lsb * lsb, (n, 3))) / lsb) * lsb
        x[:, 2] = level[2] + rng.normal(0, 1.3, n)  # continuous
        out.append(x)
    return out


@pytest.mark.parametrize("seed,noise_lsb,lsb,n_parts", [(0, 0.35, 1.0, 4), (1, 4.0, 1.0, 4), (2, 0.6, 0.25, 1),
                                                        (3, 1.0, 2.0, 7), (4, 0.2, 1.0, 2)])
def test_quantization_test_equals_the_per_sample_form(seed, noise_lsb, lsb, n_parts):
    parts = stretches(seed, noise_lsb, lsb, n_parts)
    scale = np.array([100.0, 110.0, 95.0])
    fast, plain = quantization_test(parts, scale), quantization_oracle(parts, scale)
    assert fast == plain  # floats compared exactly
    assert fast["axes"][0]["lsb_raw"] == lsb and fast["axes"][0]["noise_std_lsb"] > 0


@pytest.mark.parametrize("seed", range(4))
def test_likelihoods_equal_the_per_sample_sums_bit_for_bit(seed):
    """The two log-likelihoods themselves (unrounded) at latent stds across the search range."""
    lsb = (1.0, 0.25, 2.0, 1.0)[seed]
    parts = [p[:, 0] for p in stretches(10 + seed, (0.3, 0.8, 2.0, 6.0)[seed], lsb, 3 + seed)]
    grids = [_on_grid(v) for v in parts]
    for s in np.std(np.concatenate(parts)) * np.array([0.05, 0.3, 0.77, 1.0, 1.2]):
        la, lb = loglik_oracle(parts, float(s), lsb)
        assert (_loglik_continuous(grids, float(s), lsb), _loglik_quantised(grids, float(s), lsb)) == (la, lb)


def test_quantization_found_and_not_found_as_the_per_sample_form_says():
    coarse, fine = stretches(5, 0.3, 1.0, 4), stretches(6, 5.0, 1.0, 4)
    for parts, found in ((coarse, True), (fine, False)):
        r = quantization_test(parts, np.ones(3) * 100)
        assert r["found"] is found and r == quantization_oracle(parts, np.ones(3) * 100)
