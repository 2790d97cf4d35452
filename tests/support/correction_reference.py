"""The numpy reference of the per-sample correction (core/_correctkernel.c), the oracle its tests compare it to.

``plain_block``: a = scale K^-1 (raw - o) as the kernel's plain form computes it, term by term left to right
(x0 k[0] + x1 k[1]) + x2 k[2], x = raw - o: the same bits. An extended calibration's oracle is the model itself,
Calibration.apply (core/model/effect.py apply_terms, LAPACK's solve), compared within rounding bounds
(:func:`extended_bound`)."""
from __future__ import annotations

import numpy as np

from gravcal.core.calibration import Calibration
from gravcal.core.correction import CP_COEF, CP_REF, CP_USES, correction_params
from gravcal.core.model.terms import calibration_view
from gravcal.core.samples import raw_triad
from gravcal.core.simulate import simulate

EPS = np.finfo(float).eps


def plain_block(samples: np.ndarray, offset: np.ndarray, sensitivity: np.ndarray, scale: float = 1.0) -> np.ndarray:
    k = np.linalg.inv(np.asarray(sensitivity, dtype=float)).T * scale
    x = raw_triad(samples) - np.asarray(offset, dtype=float)
    return x[:, 0:1] * k[0] + x[:, 1:2] * k[1] + x[:, 2:3] * k[2]


def extended_model(cal: Calibration, samples: np.ndarray, fs: float, scale: float) -> np.ndarray:
    """Calibration.apply at each record's covariates, in the output unit."""
    return cal.apply(raw_triad(samples), temp=samples["temp"].astype(float),
                     vsupply=samples["vsupply"].astype(float), t=samples["seq"].astype(float) / fs) * scale


def extended_bound(cal: Calibration, samples: np.ndarray, want: np.ndarray, scale: float, fs: float) -> np.ndarray:
    """Per-record bound (N,) on |kernel - model| from the operation count, at each record's K + dK and o + do: the
    offset subtraction and the terms (about 8 roundings of values up to |raw| + |o| + |do|, carried through
    (K + dK)^-1) and the 3x3 solve (about 16 roundings relative, amplified by the condition number of K + dK, in
    either solve)."""
    raw = raw_triad(samples)
    k = np.asarray(cal.sensitivity, dtype=float)
    v = correction_params(cal, scale, fs)
    coef = v[CP_COEF:].reshape(2, 4, 3)
    uses = v[CP_USES:CP_USES + 4]
    ref = v[CP_REF:CP_REF + 3]
    a0 = np.linalg.solve(k, (raw - cal.offset).T).T
    z = [samples["temp"].astype(float) - ref[0], samples["vsupply"].astype(float) - ref[1],
         (samples["seq"] / fs - ref[2]) / 3600.0]
    zs = [np.repeat(c[:, None], 3, axis=1) for c in z] + [np.abs(np.diag(k)) * a0 * a0]
    do = sum(uses[c] * coef[0, c] * zs[c] for c in range(4) if uses[c])
    dk = sum(uses[c] * coef[1, c] * zs[c] for c in range(4) if uses[c])
    kc = k[None] + np.zeros((raw.shape[0], 3, 3))
    kc[:, range(3), range(3)] += dk if np.ndim(dk) else 0.0
    size = np.abs(raw).max(axis=1) + np.abs(cal.offset).max() + (np.abs(do).max(axis=1) if np.ndim(do) else 0.0)
    return scale * 8 * EPS * np.linalg.norm(np.linalg.inv(kc), 2, axis=(1, 2)) * size + \
        16 * EPS * np.linalg.cond(kc) * np.abs(want).max(axis=1)


# per term, a parameter size [raw units per covariate unit] giving effects of a few % of g over the samples' spread
SIZE = {("offset", "temp"): 2e-4, ("sensitivity", "temp"): 4e-5, ("offset", "vsupply"): 4e-3,
        ("offset", "time"): 4e-3, ("sensitivity", "time"): 1e-3, ("offset", "accel"): 0.02}


def samples_with_covariates(seed: int, fs: float = 100.0) -> np.ndarray:
    """A simulated session with temperature, supply and hours of seq spread, a few missing periods."""
    rng = np.random.default_rng(seed)
    s = simulate("daily_living", seed=seed, duration=6.0, fs=fs).samples.copy()
    n = s.shape[0]
    s["temp"] = 25.0 + rng.uniform(-15, 15, n)
    s["vsupply"] = 3.3 + rng.uniform(-0.2, 0.2, n)
    s["seq"] += int(rng.integers(0, 10_000_000))  # hours into the session: the time terms act
    s["t2"][rng.integers(0, n, 5), rng.integers(0, 2, 5)] = 0  # missing periods -> NaN
    return s


def calibration(rng: np.random.Generator, terms: tuple[str, ...], cross: bool = True) -> Calibration:
    """A calibration with ``terms`` at random values of a few % of g, K with cross-axis entries (``cross``)."""
    k = 0.04 * np.eye(3) + (rng.normal(0, 0.002, (3, 3)) if cross else 0.0)
    params = {}
    for t in terms:
        view = calibration_view(t)
        size = SIZE.get((view.acts_on, view.covariate), 1e-3)
        params.update({n: float(size * rng.normal()) for n in view.param_names()})
    meta = {"extended": {"terms": list(terms), "t_ref_c": 25.0 + rng.normal(), "v_ref": 3.3 + 0.05 * rng.normal(),
                         "t0_s": float(rng.uniform(0, 3600))}, "params": params}
    return Calibration("+".join(("6",) + terms), 0.5 + rng.normal(0, 0.02, 3), k, metadata=meta if terms else {})
