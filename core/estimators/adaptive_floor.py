"""The online recursion's quasi-static floor, estimated from successive windows of one still run.

The recursion gives each window the variance R_k = v_k + f² (recursive.py): v_k the window's own noise
(its samples' covariance over their count, through the norm), f² a floor for what the samples' noise does not
carry (residual body motion, model error). A configured floor (2 mg) far above what the windows show makes
every stated std too wide and, with a random walk, the filter's memory too long: the week-long soak's offsets
were over-covered whatever walk was used (docs/daemon.md, "Soak"). ``AdaptiveFloor`` sets f² from
successive windows of one still run (von Neumann 1941's mean square successive difference; the within-run
variance component of a one-way random-effects model): two consecutive windows of one posture (directions
within SAME_RUN_DEG, mid times within SAME_RUN_S) measure nearly the same direction with nearly the same
parameters, so the difference of their norms at a linearisation point p_ref taken before either updated the
filter (renewed every REF_S), d_k = h_k(p_ref) - h_k-1(p_ref), carries their errors and not the point's
(B_k e - B_k-1 e ~ 0 for B_k ~ B_k-1):

    E[d_k²] = v_k + v_k-1 + 2 f²                                                                (1)

(v the windows' own noise through the norm). Over a fading memory (sensor time, MEMORY_S)

    f² = sum_k w_k (d_k² - v_k - v_k-1) / (2 sum_k w_k),   w_k = exp(-(t - t_k) / MEMORY_S)       (2)

clipped to FLOOR_RANGE_G, applied once the memory holds MIN_PAIRS pairs (the configured floor until then).
Why not covariance matching on the filter's own innovations or residuals (Mehra 1972; Myers & Tapley 1976,
E[nu²] = B P- B^T + R, E[r²] = R - B P+ B^T): both need the filter's P to be right to separate it from R,
and here P is what is in question. Measured: the residual form holds a too-wide P's floor up (the soak at
10 s windows: f = 1.43 mg, 90 % within 1σ as with the configured 2 mg); the innovation form together with
the adapted walk ran away (tests/support/drifting_triad.py: RMS z 19). (1) does not involve P.

What (2) leaves out: an error shared by the windows of one still run (sway slower than a window, a
posture-dependent model error) cancels in d_k; the filter then counts such an error once per window. On the
soak's simulated wearer the windows' errors are white (|f| - 1 at 0.05 mg RMS against 0.07 mg of sample noise
per 10 s window, docs/daemon.md, "Soak").

Status: opt-in (OnlineCalibrator.adapt_floor), figures in docs/daemon.md, "Soak".
"""
from __future__ import annotations

import math

import numpy as np

MEMORY_S = 6 * 3600.0  # fading memory of (2) [s of sensor time]
MIN_PAIRS = 50  # pairs in the memory before (2) replaces the configured floor
FLOOR_RANGE_G = (1e-5, 2e-2)  # f stays within [g] (a guard against a degenerate (2), not a prior)
SAME_RUN_DEG = 5.0  # consecutive windows this close in direction ...
SAME_RUN_S = 300.0  # ... and in mid time belong to one still run (one posture, parameters unchanged)
REF_S = 3600.0  # the pairs' linearisation point p_ref is renewed this often (the drift since moves both alike)


class AdaptiveFloor:
    """f² of (2) (module docstring), kept across re-seeds: ``attach(rec)`` gives a (new) LottersRecursive the
    current floor; ``observe(rec, mean, cov_of_mean, t)`` with every window the recursion accepted pairs it
    with the previous one and sets rec.R_floor."""

    def __init__(self, sigma_floor_g: float):
        self.configured_g2 = float(sigma_floor_g) ** 2
        self._num = self._den = 0.0
        self._t: float | None = None
        self._last: tuple[tuple, list, float] | None = None  # (mean, covariance of the mean, t) of the last window
        self._ref: tuple | None = None  # (recursion, p_ref, t_ref): where the pairs are evaluated
        self.n = 0

    @property
    def floor_g(self) -> float:
        """The floor in use [g]: (2) once MIN_PAIRS pairs are in, else the configured one."""
        if self.n < MIN_PAIRS or not self._den > 0:
            return math.sqrt(self.configured_g2)
        lo, hi = FLOOR_RANGE_G
        return min(max(math.sqrt(max(self._num / self._den, 0.0)), lo), hi)

    def attach(self, rec) -> None:
        rec.R_floor = self.floor_g ** 2

    def observe(self, rec, mean: np.ndarray, cov_of_mean: np.ndarray, t: float) -> None:
        m, Cm, t = tuple(np.ravel(mean).tolist()), np.ravel(cov_of_mean).tolist(), float(t)
        if self._ref is None or self._ref[0] is not rec or t - self._ref[2] > REF_S:
            # the pairs' linearisation point: fixed, and taken before either window of a pair updated the filter
            # (a posterior that has fitted a window shrinks its norm error; with a small floor, to ~0)
            self._ref = (rec, rec.p.copy(), t)
            self._last = None
            return
        last, self._last = self._last, (m, Cm, t)
        if last is None or not (0.0 <= t - last[2] <= SAME_RUN_S):
            return
        p_ref = self._ref[1]
        try:
            h0, _, R0 = rec._h_B_R(p_ref, last[0], last[1])
            u0 = rec._a / h0
            h1, _, R1 = rec._h_B_R(p_ref, m, Cm)
            u1 = rec._a / h1
        except ValueError:
            return
        if float(u0 @ u1) < math.cos(math.radians(SAME_RUN_DEG)):
            return
        sample = 0.5 * ((h1 - h0) ** 2 - (R0 - rec.R_floor) - (R1 - rec.R_floor))  # (1)
        if not math.isfinite(sample):
            return
        fade = 1.0 if self._t is None else math.exp(-max(t - self._t, 0.0) / MEMORY_S)
        self._num = fade * self._num + sample
        self._den = fade * self._den + 1.0
        self._t = t
        self.n += 1
        rec.R_floor = self.floor_g ** 2
