"""The sample-level tests of diagnose: colored noise on the Allan deviation of static stretches and
quantisation on the sample likelihood (the terms whose ``sample_test`` names them), after the extended
calibration's deterministic terms are removed."""
from __future__ import annotations

import numpy as np

from .noise import colored_noise_test, pooled_allan, quantization_test
from .terms import TermTest

MIN_ALLAN_STRETCH_S = 20.0  # colored noise needs a static stretch at least this long [s]


def _allan_test(name: str, parts_raw: list, parts_g: list, scale: np.ndarray, fs: float, longest: float) -> TermTest:
    """Colored noise on static stretches: the Allan deviation beyond white noise (fitted on the earlier half of
    the stretches in time, judged on the later half)."""
    if longest < MIN_ALLAN_STRETCH_S:
        return TermTest(name, "untestable", f"the longest static stretch is {longest:.1f} s "
                                            f"(need >= {MIN_ALLAN_STRETCH_S:g} s for the Allan deviation)")
    train, test = time_halves(parts_g)
    tr, te = pooled_allan(train, fs), pooled_allan(test, fs)
    res = colored_noise_test(tr, te) if tr is not None else {"found": False}
    tt = TermTest(name, "found" if res["found"] else "not_found",
                  "" if res["found"] else "Allan deviation explained by white noise (ΔBIC <= 10 or no "
                  "held-out gain on the later half of the stretches)", res.get("delta_bic"))
    bi, rw = res.get("bias_instability_mg", [0.0] * 3), res.get("random_walk_mg_per_sqrt_s", [0.0] * 3)
    white_only = "white noise alone on this axis (no flicker floor or random walk fitted)"
    tt.magnitude = {"unit": "mg", "value": {a: (bi[i] or None) if (bi[i] or rw[i]) else None for i, a in enumerate("xyz")},
                    "random_walk_mg_per_sqrt_s": {a: rw[i] if (bi[i] or rw[i]) else None for i, a in enumerate("xyz")},
                    "undetermined": {a: white_only for i, a in enumerate("xyz") if not (bi[i] or rw[i])}}
    if tt.status == "found" and not any(bi[i] or rw[i] for i in range(3)):
        tt.status, tt.why = "not_found", "the colored model's extra components fitted to zero on every axis"
    tt._extra = res  # type: ignore[attr-defined]
    tt._allan = pooled_allan(parts_g, fs)  # type: ignore[attr-defined]
    return tt


def _lsb_test(name: str, parts_raw: list, parts_g: list, scale: np.ndarray, fs: float, longest: float) -> TermTest:
    """Quantisation on static stretches: samples on a grid of steps well above the noise."""
    if not parts_raw:
        return TermTest(name, "untestable", "no static stretch")
    res = quantization_test(parts_raw, scale)
    tt = TermTest(name, "found" if res["found"] else "not_found",
                  "" if res["found"] else "samples look continuous at the noise level (ΔBIC <= 10 or no "
                  "held-out gain)", res.get("delta_bic"))
    tt.magnitude = {"unit": "mg_per_lsb", "value": {a: r.get("lsb_mg") or None for a, r in zip("xyz", res["axes"])},
                    "noise_std_lsb": {a: r.get("noise_std_lsb") for a, r in zip("xyz", res["axes"])},
                    "undetermined": {a: "samples on no grid (continuous)" for a, r in zip("xyz", res["axes"])
                                     if not r.get("lsb_mg")}}
    tt._extra = res  # type: ignore[attr-defined]
    return tt


def time_halves(parts: list[np.ndarray]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Static stretches (in time order) split into an earlier and a later half by sample count: contiguous
    in time, so a held-out score on the later half is not flattered by neighbours of the training half."""
    if len(parts) == 1:
        h = parts[0].shape[0] // 2
        return [parts[0][:h]], [parts[0][h:]]
    n = np.cumsum([p.shape[0] for p in parts])
    cut = int(np.clip(np.searchsorted(n, n[-1] / 2), 1, len(parts) - 1))
    return parts[:cut], parts[cut:]


SAMPLE_TESTS = {"allan": _allan_test, "lsb": _lsb_test}  # TermSpec.sample_test -> the static-sample test
