"""The online recursion's random walk per parameter, adapted until its stated std covers what the data show.

A drifting sensor's parameters do not walk at one configured rate: one axis's sensitivity drifts 2.5x the
typical rate while another offset barely moves, and a daily temperature cycle adds a periodic part. With one
walk for all, some published std are too small and others too wide (bench/bench_soak.py; docs/daemon.md,
"Soak"). ``AdaptiveWalk`` scales each parameter's walk q_j [raw²/s] by a variance-ratio test of the
filter's covariance against the innovations of hour-long blocks (covariance matching, Mehra 1972, on
blocks of windows instead of single innovations):

  a block starts at (p_s, P_s) at time t_s. Its windows k, linearised at the fixed p_s, give the score and
  information of the block
      g = sum_k B_k^T xi_k(p_s) / R_k,      I = sum_k B_k^T B_k / R_k                  (1)
  With e = truth - p_s, xi_k(p_s) = B_k e + noise, and the block's own estimate of e (the filter's C as a
  prior, REG = 1: the block's update of e, which leaves the directions its windows do not determine at 0 --
  an upright hour does not separate an offset from its sensitivity -- instead of amplifying noise there)
      delta = (I + REG C^-1)^-1 g = A e + noise,   A = (I + REG C^-1)^-1 I                 (2)
  Under the filter's model (e ~ N(0, C), C = P_s + Q L/3 for the walk within the block of length L) each
  parameter's
      E[delta_j²] = (A C A^T)_jj + rho (Ir^-1 I Ir^-1)_jj,   Ir = I + REG C^-1               (3)
  rho the windows' noise relative to R (R carries a 2 mg floor for model errors the windows may not have):
  the block's own least-squares residual chi²_min / (m - n), as the batch fit's data-derived floor. The
  variance ratio per parameter, over blocks b with a fading memory (weights f_b), each block's
  z² = (delta_bj² - n_bj) / s_bj (s = (A C A^T)_jj, n the noise term) weighted by (s / (s + n))², the
  inverse of its variance 2 (s + n)² / s² up to a constant (a block that cannot see parameter j, s ~ 0,
  hardly counts; weighting by 1 / (s + n)² instead lets such blocks dominate),
      lambda_j = sum_b f_b s_b (delta_bj² - n_bj) / (s_b + n_b)² / sum_b f_b s_b² / (s_b + n_b)²   (4)
  is 1 when P_jj covers the truth's deviation, > 1 when the stated std is too small. Each block then moves
  q_j by lambda_j^GAIN (an integral controller: P ~ sqrt(q) in a random-walk filter, so a ratio lambda
  needs q x lambda², reached over ~2 / GAIN blocks), within Q_RANGE of the configured walk.

Status: opt-in (OnlineCalibrator.adapt_walk). On the independent drifting triad (tests/core/test_adaptive_walk.py,
test_adaptive_floor.py with the floor found by adaptive_floor.py) the stated std cover each parameter; on the
soak's 10 s windows every walk of an offset grows and every sensitivity's shrinks until a day upright leaves
them "not observable", with the configured or the found floor; why is unexplained (the windows' errors there
are white, not shared within a still run: docs/daemon.md, "Soak").

Why the score and not the estimate's own increments or single innovations: a single window's innovation is
dominated by its noise (the filter averages thousands of windows), so a per-window ratio stays ~1 whatever
the drift (Sage-Husa's estimate does not move); the estimate's increments (Mohamed & Schwarz 1999's
state-correction form) follow the filter's own allocation between parameters the windows do not separate
(an offset and its sensitivity while upright) and confirm whatever Q it has (measured: sensitivities
collapsed to the lower bound, the offsets took their drift). The score g comes from the windows alone:
an upright hour tests only the combination it measures, a night lying tests the others. The score g
itself mixes the parameters through I's off-diagonal terms (an offset error shows in the other axes'
scores), so the test is on the block's estimate delta, whose mixing A is near the identity wherever the
block determines the parameters.
"""
from __future__ import annotations

import math

import numpy as np

from ..model.datasheet import OFFSET_WALK_G_PER_SQRT_H, SENS_WALK_PER_SQRT_H

# The random walk of a sensitivity against an offset's, both in raw units (datasheet.py's assumed walks: 0.05 %/sqrt(h)
# of the sensitivity against 2 mg/sqrt(h)): the configured process noise is the offsets' walk.
SENS_WALK_RATIO2 = (SENS_WALK_PER_SQRT_H / OFFSET_WALK_G_PER_SQRT_H) ** 2

BLOCK_S = 3600.0  # block length L of (1)
MEMORY_S = 8 * 3600.0  # fading memory of (3)
REG = 1.0  # weight of the filter prior C in (2)
GAIN = 0.2  # log q_j moves by GAIN log lambda_j per block
LAMBDA_CLIP = (0.25, 4.0)  # one block's lambda is taken within these bounds (a block of outliers moves q by < 1.32x)
Q_RANGE = (1e-2, 1e2)  # q_j stays within this factor of the configured walk (a guard, not a prior)


def drift_walk(names: list[str], process_noise: float | np.ndarray | None) -> np.ndarray | float | None:
    """Per-parameter random walk [raw²/s] from the configured ``process_noise``: a scalar q is the offsets' walk;
    sensitivities (and cross-axis entries) walk SENS_WALK_RATIO2 q (the same q on them made their std grow
    ~4x faster than any sensor drifts, so a day upright left them "not determined"); an extended term's
    coefficient is a property of the part, not a drift: 0. A vector is taken as given."""
    if process_noise is None or np.ndim(process_noise) > 0:
        return process_noise
    q = float(process_noise)
    return np.array([q if n.startswith("o_") else q * SENS_WALK_RATIO2 if n.startswith("s_") else 0.0 for n in names])


class AdaptiveWalk:
    """Per-parameter walk q_j adapted by (4) (module docstring), kept by name across re-seeds and order changes.

    ``attach(rec)`` gives a (new) LottersRecursive the current walk and starts a block; ``observe(rec, mean,
    cov_of_mean)`` after each window it accepted adds the window to the block's (1) and, once the block has
    lasted BLOCK_S, updates lambda_j, q_j and rec.Q. Parameters whose configured walk is 0 (extended
    coefficients) never walk."""

    def __init__(self, process_noise: float):
        self.q0 = float(process_noise)
        self._q: dict[str, float] = {}
        self._num: dict[str, float] = {}
        self._den: dict[str, float] = {}
        self._block: dict | None = None
        self.n_blocks = 0

    def prior(self, name: str) -> float:
        return float(drift_walk([name], self.q0)[0])

    def q(self, name: str) -> float:
        return self._q.setdefault(name, self.prior(name))

    def walks(self) -> dict[str, float]:
        """q_j per parameter seen so far [raw²/s]."""
        return dict(self._q)

    def ratios(self) -> dict[str, float]:
        """lambda_j of (3) per parameter (nan before a block tested it)."""
        return {n: self._num[n] / self._den[n] if self._den.get(n, 0) > 0 else float("nan") for n in self._q}

    def attach(self, rec) -> None:
        """Give ``rec`` the current walk (diagonal Q); its first accepted window starts a block."""
        q = np.array([self.q(n) for n in rec.names])
        rec.Q = np.diag(q)
        rec._has_Q = bool(np.any(q > 0))
        self._block = None

    def observe(self, rec, mean: np.ndarray, cov_of_mean: np.ndarray) -> None:
        """After a window ``rec`` accepted (it is bound to that window): add it to the block's (1)."""
        t = rec.t_last
        if t is None or rec._pending:  # pending windows: the estimate is not settled (recursive.py)
            self._block = None
            return
        b = self._block
        if b is None or b["rec"] is not rec:
            n = len(rec.names)
            self._block = {"rec": rec, "t": float(t), "p": rec.p.copy(), "P": rec.P.copy(),
                           "g": np.zeros(n), "I": np.zeros((n, n)), "chi2": 0.0, "m": 0}
            return
        h, B, R = rec._h_B_R(b["p"], tuple(np.ravel(mean).tolist()), np.ravel(cov_of_mean).tolist())
        gk, Ik = B * ((1.0 - h) / R), np.outer(B, B / R)
        b["g"] += gk
        b["I"] += Ik
        b["chi2"] += (1.0 - h) ** 2 / R
        b["m"] += 1
        length = float(t) - b["t"]
        if length < BLOCK_S:
            return
        self._close(rec, b, length)
        self._block = None

    def _close(self, rec, b: dict, length: float) -> None:
        I, g = b["I"], b["g"]
        n_par = len(g)
        if b["m"] <= 2 * n_par:
            return
        # the windows' noise relative to R (R carries a 2 mg floor for model errors the windows may not have): the
        # block's own least-squares residual, chi²_min / (m - n), as the batch fit's data-derived floor
        rho = max(float(b["chi2"] - g @ np.linalg.lstsq(I, g, rcond=1e-12)[0]) / (b["m"] - n_par), 0.0)
        C = b["P"] + rec.Q * (length / 3.0)
        try:  # (4): the block's own estimate of e, a vanishing prior keeping undetermined directions finite
            Ir_inv = np.linalg.inv(I + REG * np.linalg.inv(C))
        except np.linalg.LinAlgError:
            return
        A = Ir_inv @ I
        delta = Ir_inv @ g
        signal = np.einsum("ij,jk,ik->i", A, C, A)  # (A C A^T)_jj
        noise = rho * np.einsum("ij,jk,ik->i", Ir_inv, I, Ir_inv)  # rho (Ir^-1 I Ir^-1)_jj
        fade = math.exp(-length / MEMORY_S)
        for k, n in enumerate(rec.names):
            if rec.Q[k, k] <= 0 or not signal[k] > 0:
                continue
            w = signal[k] / (signal[k] + noise[k]) ** 2  # (4): weight (s / (s + n))² on (delta² - n) / s
            self._num[n] = fade * self._num.get(n, 0.0) + w * (delta[k] * delta[k] - noise[k])
            self._den[n] = fade * self._den.get(n, 0.0) + w * signal[k]
            lam = min(max(self._num[n] / self._den[n], LAMBDA_CLIP[0]), LAMBDA_CLIP[1])
            prior = self.prior(n)
            self._q[n] = min(max(self.q(n) * lam ** GAIN, prior * Q_RANGE[0]), prior * Q_RANGE[1])
            rec.Q[k, k] = self._q[n]
        self.n_blocks += 1
