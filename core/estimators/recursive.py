"""Lötters et al. (1998), recursive: the linearised model of eq. 9-14 applied one window at a time.

The recursion is the batch fit's (lotters.py, eq. 11a) online form: the same measurement model
h(m, p) = |K(p)^-1 (m - o(p))|, the same Jacobian (eq. 13a), the same per-window C_mu; see the
class docstring for the update equations.
"""
from __future__ import annotations

import math

import numpy as np

from ..calibration import Calibration
from ..windows import Window, WindowSet, validate_windows
from .consider import (
    CONSIDER_KEY,
    HELD_KEY,
    consider_metadata,
    held_jacobian,
    held_std_note,
    held_uncertainty,
)
from .extended import extended_metadata
from .lotters import START_TOLERANCE, resolve_parameterization
from .observability import SIGMA_FLOOR_G
from .parameterization import Parameterization
from .start import ellipsoid_fit

# Sliding-window relinearisation (LottersRecursive docstring): pending windows are folded into the anchor when
# their second-order term is at most this fraction of their noise std (its effect on the estimate is then ~1 %
# of the noise's in variance), or when this many are pending (memory bound: beyond it, folded where it stands).
LIN_FRACTION = 0.1
MAX_PENDING = 500
MAX_GN_ITERATIONS = 20
IEKF_ITERATIONS = 3  # relinearisations of a window's own update once nothing is pending
GN_STEP_TOL_STD = 1e-3  # Gauss-Newton stops when no parameter moves by more than this fraction of its std
POOR_FIT_SIGMA = 5.0  # pending windows' chi² this many stds above its mean: a wrong minimum, not folded
ELLIPSOID_MIN_WINDOWS = 12  # pending windows before an ellipsoid-fit restart is tried (twice its 6 unknowns)
_TINY_VAR_G2 = 1e-14  # as the batch fit's guard against zero-variance windows [g²]


def stated_variances(start: Calibration) -> dict[str, float]:
    """Variances [raw units²] a start states for its held parameters (metadata[HELD_KEY], e.g. the datasheet
    spread of a nominal start), by name; {} when it states none."""
    held = start.metadata.get(HELD_KEY) if isinstance(start.metadata, dict) else None
    if not isinstance(held, dict) or not held.get("names"):
        return {}
    names = list(held["names"])
    cov = np.asarray(held["cov"], dtype=float).reshape(len(names), len(names))
    return {nm: float(cov[k, k]) for k, nm in enumerate(names) if np.isfinite(cov[k, k]) and cov[k, k] > 0}


def _gauss_newton(evaluate, p: np.ndarray, info_a: np.ndarray, p_a: np.ndarray):
    """Gauss-Newton (eq. 11a with a prior of information info_a at p_a), step-halved, from p; ``evaluate(p)``
    gives (xi, B, R, cost). Returns (p, xi, B, R, cost) at the end."""
    xi, B, R, cost = evaluate(p)
    for _ in range(MAX_GN_ITERATIONS):
        H = info_a + B.T @ (B / R[:, None])
        grad = B.T @ (xi / R) - info_a @ (p - p_a)
        try:
            step = np.linalg.solve(H, grad)
        except np.linalg.LinAlgError:
            break
        if not np.all(np.isfinite(step)):
            break
        lam, trial = 1.0, None
        for _ in range(20):  # never accept a worse fit: the linearisation only holds near p
            try:
                cand = evaluate(p + lam * step)
            except (ValueError, np.linalg.LinAlgError):
                cand = None
            if cand is not None and np.isfinite(cand[3]) and cand[3] <= cost * (1 + 1e-12) + 1e-300:
                trial = cand
                break
            lam *= 0.5
        if trial is None:
            break
        p = p + lam * step
        xi, B, R, cost = trial
        std = np.sqrt(np.maximum(np.diag(np.linalg.inv(H)), 1e-300))
        if np.max(np.abs(lam * step) / std) < GN_STEP_TOL_STD:
            break
    return p, xi, B, R, cost


class LottersRecursive:
    """One linearised MVU (iterated-EKF) update per quasi-static window.

    State (filterpy style): ``p`` (P,) parameters in raw units, ``P`` (P, P) their covariance (C_e),
    ``Q`` (P, P) process noise per second of elapsed time [param units² / s] (random walk of the
    parameters, so drifting offsets are tracked), ``R_floor`` = sigma_floor_g² [g²].

    Per window (mean m, covariance of the mean C_m, mid time t):
        P  <- P + Q (t - t_prev)                                   (prediction: random-walk drift)
        h, B = |K^-1 (m - o)|, dh/dp at p                          (eq. 8, 13a)
        R   = (a/|a|)^T K^-1 C_m K^-T (a/|a|) + sigma_floor²       (C_mu of this window)
        S   = B P B^T + R;  xi = 1 - h                             (innovation, eq. 14)
        gate: xi² / S > gate_sigma²  -> reject, count
        K_g = P B^T / S;  p <- p + K_g xi;  P <- (I - K_g B) P (I - K_g B)^T + K_g R K_g^T   (Joseph form)
    With ``iterations`` > 1 the update is relinearised at the new estimate (IEKF):
        p_i+1 = p_prior + K_g,i (xi_i - B_i (p_prior - p_i)).
    Eq. 11a over all windows at once is the batch limit of this recursion (no prior, no Q).

    Relinearisation (``relinearise=True``, the default): a sliding-window filter (Sibley et al. 2010, the
    fixed-lag smoother of a static state). An EKF freezes every window's Jacobian at the estimate of its
    time; from a start 1 % off, daily living's first windows leave the cross-axis and sensitivity directions
    at errors whose second-order terms exceed the window noise, and those frozen linearisations bias the
    end result (efficiency 0.06-0.3, bench/bench_efficiency.py). Here the accepted windows stay *pending*
    and each step is Gauss-Newton (eq. 11a, step-halved) over the anchor prior (p_a, P_a) and every pending
    window, relinearised at the new estimate each iteration. The pending windows are folded into the anchor
    (p_a, P_a <- p, P: marginalised at the current estimate) once the linearisation error the posterior
    still allows is negligible: for every pending window the second-order term ~ 1/2 tr(J P J^T) (J = da/dp,
    |a| = 1) at most ``LIN_FRACTION`` of that window's noise std sqrt(R). From then on each window is folded
    as it arrives: the iterated EKF. ``MAX_PENDING`` bounds the memory (beyond it the pending windows are
    folded where the estimate stands). The random walk inflates P_a (the pending windows are taken to
    measure the current parameters: their span is short against the drift once the estimate has settled).

    Held parameters (consider covariance, Schmidt): when ``start`` states an uncertainty C_h for
    parameters this parameterization holds (``held_uncertainty``: offsets-only from a datasheet start
    holds uncertain sensitivities), the sensitivity ``S`` = dp/dtheta_held (P, H) is propagated with
    the filter, S <- (I - K_g B) S - K_g B_h (B_h = dh/dtheta_held), from the start's (a batch fit's
    metadata["consider"]["sensitivity"], else 0). The reported covariance is P + S C_h S^T; the state
    update (gain, P) is the plain filter's, unchanged.
    """

    def __init__(
        self,
        start: Calibration,
        model: str | type[Parameterization] | Parameterization = "6",
        *,
        process_noise: float | np.ndarray | None = None,
        sigma_floor_g: float = SIGMA_FLOOR_G,
        gate_sigma: float = 5.0,
        prior_std_rel: float = START_TOLERANCE,
        iterations: int = 1,
        max_consecutive_rejections: int = 20,
        max_std_g: float = 0.03,
        relinearise: bool = True,
    ):
        if not isinstance(start, Calibration):
            raise ValueError("LottersRecursive needs a start Calibration (e.g. LottersBatch().fit(first_windows))")
        self.par = resolve_parameterization(model, start)
        par = self.par
        n = par.n_params
        self.names = list(par.names)
        self.p = par.pack(start.sensitivity, start.offset)
        stated = start.metadata.get("params") if isinstance(start.metadata, dict) else None
        if start.model == par.model and "+" in par.model and isinstance(stated, dict) and all(n in stated for n in self.names):
            # an extended start (a batch fit): its extra terms are not in (K, o); resume from its parameters
            self.p = np.array([float(stated[n]) for n in self.names])
        self.scale_ref = float(np.mean(np.abs(np.diag(start.sensitivity))))
        # held parameters' uncertainty (consider term of the reported covariance only)
        self.held = held_uncertainty(start, par)
        cons = start.metadata.get(CONSIDER_KEY) if isinstance(start.metadata, dict) else None
        same = (self.held is not None and isinstance(cons, dict) and cons.get("held") == self.held.names
                and list(start.param_names) == self.names)
        h = 0 if self.held is None else len(self.held.names)
        self.S = np.asarray(cons["sensitivity"], dtype=float).reshape(n, h) if same else np.zeros((n, h))
        start_cov = np.asarray(cons["covariance_noise_only"], dtype=float) if same else start.covariance
        if start_cov.shape == (n, n) and list(start.param_names) == self.names and np.all(np.isfinite(start_cov)) \
                and np.all(np.diag(start_cov) > 0):
            self.P = start_cov.copy()  # the filter's own covariance (noise only: the consider part is reported)
        else:
            # the paper's assumption: start within 5 % (of 1 g) of the truth, unless the start states its
            # spread for a parameter (a datasheet start: datasheet_held_uncertainty), then that
            self.P = np.eye(n) * (prior_std_rel * self.scale_ref) ** 2
            stated = stated_variances(start)
            for k, name in enumerate(self.names):
                if name in stated:
                    self.P[k, k] = max(self.P[k, k], stated[name])
        if process_noise is None:
            self.Q = np.zeros((n, n))
        else:
            q = np.asarray(process_noise, dtype=float)
            self.Q = np.diag(np.broadcast_to(q, (n,))).astype(float) if q.ndim <= 1 else q.reshape(n, n).copy()
            if not np.all(np.isfinite(self.Q)) or np.any(np.diag(self.Q) < 0):
                raise ValueError("process_noise must be finite and non-negative")
        self.R_floor = float(sigma_floor_g) ** 2
        self.gate2 = float(gate_sigma) ** 2
        self.iterations = max(1, int(iterations))
        self.max_consecutive_rejections = int(max_consecutive_rejections)
        self.max_std_g = float(max_std_g)
        # constant derivatives, flattened for small explicit products
        self._dK9 = np.ascontiguousarray(par.dK.reshape(n, 9))  # (P, 9): K = K_const + p @ dK9
        # dh/dp_k = -sum_ij g_i dK_k[i, j] a_j: contract dK_k with the outer product g a^T (row-major i, j)
        self._dKg = self._dK9
        self._do = np.ascontiguousarray(par.do)  # (P, 3)
        if self.held is not None:
            self._dKh9 = np.ascontiguousarray(self.held.dK.reshape(h, 9))
            self._doh = np.ascontiguousarray(self.held.do)
        self._ag = self._g = None  # the last linearisation's a g^T (9,) and g (3,) (for B_h)
        self._dK9_ref, self._do_ref = self._dK9, self._do  # at the reference covariates (what .calibration reports)
        self._has_Q = bool(np.any(self.Q != 0))
        self._n = n
        self.t_last: float | None = None
        self.n_updates = 0
        self.n_rejected = 0
        self.consecutive_rejected = 0
        self.nis_sum = 0.0  # sum of normalised innovations squared of accepted windows (should average ~1)
        self._eye = np.eye(n)
        self.relinearise = bool(relinearise)
        # pending windows (mean, cov of the mean, t, aux) since the anchor (p_a, P_a, S_a): see the class docstring
        self._pending: list[tuple[np.ndarray, np.ndarray, float, np.ndarray]] = []
        self.p_a, self.P_a, self.S_a = self.p, self.P, self.S
        self.n_folds = 0

    # -- the update ----------------------------------------------------------------------
    def _h_B_R(self, p: np.ndarray, m: tuple, Cm: list) -> tuple[float, np.ndarray, float]:
        """h (eq. 8), dh/dp (eq. 13a generalised) and the window's C_mu at p; 3-vectors in plain floats
        (numpy call overhead dominates 3x3 work)."""
        par = self.par
        K = (par.K_const.ravel() + p @ self._dK9).tolist()
        o = (par.o_const + p @ self._do).tolist()
        k00, k01, k02, k10, k11, k12, k20, k21, k22 = K
        c00 = k11 * k22 - k12 * k21
        c01 = k02 * k21 - k01 * k22
        c02 = k01 * k12 - k02 * k11
        det = k00 * c00 + k10 * c01 + k20 * c02
        if det == 0.0:
            raise ValueError("sensitivity matrix became singular")
        inv = 1.0 / det
        i00, i01, i02 = c00 * inv, c01 * inv, c02 * inv
        i10, i11, i12 = (k12 * k20 - k10 * k22) * inv, (k00 * k22 - k02 * k20) * inv, (k02 * k10 - k00 * k12) * inv
        i20, i21, i22 = (k10 * k21 - k11 * k20) * inv, (k01 * k20 - k00 * k21) * inv, (k00 * k11 - k01 * k10) * inv
        d0, d1, d2 = m[0] - o[0], m[1] - o[1], m[2] - o[2]
        a0 = i00 * d0 + i01 * d1 + i02 * d2  # a = K^-1 (m - o)
        a1 = i10 * d0 + i11 * d1 + i12 * d2
        a2 = i20 * d0 + i21 * d1 + i22 * d2
        h = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        u0, u1, u2 = a0 / h, a1 / h, a2 / h
        g0 = u0 * i00 + u1 * i10 + u2 * i20  # g = dh/dm = u^T K^-1
        g1 = u0 * i01 + u1 * i11 + u2 * i21
        g2 = u0 * i02 + u1 * i12 + u2 * i22
        # dh/dp_k = -g (dK_k a + do_k)
        self._ag = np.array((a0 * g0, a1 * g0, a2 * g0, a0 * g1, a1 * g1, a2 * g1, a0 * g2, a1 * g2, a2 * g2))
        self._g = np.array((g0, g1, g2))
        self._a = np.array((a0, a1, a2))
        self._Kinv = np.array(((i00, i01, i02), (i10, i11, i12), (i20, i21, i22)))
        B = -(self._dKg @ self._ag + self._do @ self._g)
        R = (g0 * (Cm[0] * g0 + Cm[1] * g1 + Cm[2] * g2) + g1 * (Cm[3] * g0 + Cm[4] * g1 + Cm[5] * g2)
             + g2 * (Cm[6] * g0 + Cm[7] * g1 + Cm[8] * g2)) + self.R_floor
        return h, B, R

    def _bind(self, mean: np.ndarray, t: float | None, aux: np.ndarray | None) -> None:
        """Bind the derivatives to this window's covariates (extended terms, extended.py); a no-op without them."""
        if not self.par.covariates:
            return
        one = WindowSet(np.reshape(np.asarray(mean, dtype=float), (1, 3)), np.zeros((1, 3, 3)), np.ones(1),
                        np.array([0.0 if t is None else float(t)]),
                        np.reshape(np.zeros(0) if aux is None else np.asarray(aux, dtype=float), (1, -1)),
                        np.zeros(1, dtype=np.int64), np.ones(1, dtype=np.int64))
        pw = self.par.at_windows(one)
        self._dK9 = self._dKg = np.ascontiguousarray(pw.dK.reshape(self._n, 9))
        self._do = np.ascontiguousarray(pw.do)

    def step(self, mean: np.ndarray, cov_of_mean: np.ndarray, t: float | None = None, aux: np.ndarray | None = None) -> bool:
        """Process one window (mean and covariance of the mean in raw units, mid time t [s], aux means
        e.g. temperature [°C]). Returns True if accepted, False if gated out as an outlier."""
        m = tuple(float(x) for x in np.ravel(mean))
        if len(m) != 3 or not all(math.isfinite(x) for x in m):
            raise ValueError(f"window mean must be 3 finite values, got {mean!r}")
        self._bind(mean, t, aux)
        Cm = np.ravel(cov_of_mean).tolist()
        if not self._pending:  # nothing pending: the anchor is the posterior (which a caller may have set)
            self.p_a, self.P_a, self.S_a = self.p, self.P, self.S
        if t is not None:
            if self.t_last is not None and t > self.t_last and self._has_Q:
                self.P = self.P + self.Q * (t - self.t_last)  # random-walk prediction
                self.P_a = self.P_a + self.Q * (t - self.t_last) if self._pending else self.P
            self.t_last = float(t) if self.t_last is None else max(self.t_last, float(t))
        if self.relinearise and self._pending:
            return self._step_relinearised(m, Cm, t, aux)
        p_prior, P, S_prior = self.p, self.P, self.S
        p = p_prior
        settled = not self.relinearise
        n_iter = max(self.iterations, IEKF_ITERATIONS) if self.relinearise else self.iterations
        for i in range(n_iter):
            h, B, R = self._h_B_R(p, m, Cm)
            PB = P @ B
            S = float(B @ PB) + R
            if i == 0:
                xi0 = 1.0 - h  # eq. 14
                # (relinearising) the gate allows the linearisation error too: the estimate may still be far
                if xi0 * xi0 > self.gate2 * (S + (self._second_order(P) ** 2 if self.relinearise else 0.0)):
                    self.n_rejected += 1
                    self.consecutive_rejected += 1
                    return False
                xi = xi0
            else:
                xi = 1.0 - h - float(B @ (p_prior - p))  # IEKF: relinearised at p, referred to the prior
            p = p_prior + PB * (xi / S)  # K_g = P B^T / S
            if i == 0 and not settled:
                # settled once the posterior leaves this window's second-order term negligible: then relinearising
                # it cannot move the estimate (one EKF update is the Gauss-Newton solution), else iterate and keep it
                settled = self._settled_one(P - np.outer(PB, PB * (1.0 / S)), R)
                if settled:
                    break
        if self.held is not None:  # consider sensitivity: S <- (I - K_g B) S - K_g B_h (K_g = PB / S)
            B_h = -(self._dKh9 @ self._ag + self._doh @ self._g)
            self.S = self.S - np.outer(PB * (1.0 / S), B @ self.S + B_h)
        # P - K_g S K_g^T = P - PB PB^T / S: equal to the Joseph form for the optimal gain, and exactly symmetric
        self.P = P - np.outer(PB, PB * (1.0 / S))
        self.p = p
        if not settled:  # this window stays pending (the anchor is the prior): the next steps relinearise it
            self.p_a, self.P_a, self.S_a = p_prior, P, S_prior
            self._pending.append((np.array(m), np.reshape(np.asarray(Cm, dtype=float), (3, 3)),
                                  0.0 if t is None else float(t),
                                  np.zeros(0) if aux is None else np.ravel(np.asarray(aux, dtype=float))))
        self.nis_sum += xi0 * xi0 / S
        self.n_updates += 1
        self.consecutive_rejected = 0
        return True

    def _step_relinearised(self, m: tuple, Cm: list, t: float | None, aux: np.ndarray | None) -> bool:
        """The sliding-window step (class docstring): gate at the current estimate, then Gauss-Newton over
        the anchor and the pending windows, then fold them when their linearisation has settled."""
        h, B, R = self._h_B_R(self.p, m, Cm)
        xi0 = 1.0 - h
        S_inn = float(B @ self.P @ B) + R
        # no gate at arrival: while windows are pending the estimate is not settled (it may still be far, a
        # datasheet start, or in a wrong minimum) and no reference for one; pending windows are gated at the fold
        aux_row = np.zeros(0) if aux is None else np.ravel(np.asarray(aux, dtype=float))
        self._pending.append((np.array(m), np.reshape(np.asarray(Cm, dtype=float), (3, 3)),
                              0.0 if t is None else float(t), aux_row))
        self._solve_pending()
        self.nis_sum += xi0 * xi0 / S_inn
        self.n_updates += 1
        self.consecutive_rejected = 0
        return True

    def _pending_windows(self) -> tuple[Parameterization, np.ndarray, np.ndarray]:
        """(the parameterization bound to the pending windows, their means (M, 3), covariances of the mean)."""
        mean = np.array([w[0] for w in self._pending])
        cov = np.array([w[1] for w in self._pending])
        if not self.par.covariates:
            return self.par, mean, cov
        k = max(w[3].size for w in self._pending)
        aux = np.array([np.resize(w[3], k) if w[3].size else np.full(k, np.nan) for w in self._pending]).reshape(-1, k)
        m = len(mean)
        ws = WindowSet(mean, cov, np.ones(m), np.array([w[2] for w in self._pending]), aux,
                       np.zeros(m, dtype=np.int64), np.ones(m, dtype=np.int64))
        return self.par.at_windows(ws), mean, cov

    def _solve_pending(self) -> None:
        """Gauss-Newton (eq. 11a with the anchor as prior, step-halved) over the pending windows from the
        current estimate; sets p, P (and the consider sensitivity S) and folds when settled."""
        par, mean, cov = self._pending_windows()
        try:
            info_a = np.linalg.inv(self.P_a)
        except np.linalg.LinAlgError:
            info_a = np.linalg.pinv(self.P_a)
        p_a = self.p_a

        def evaluate(p):
            h, B, _, var = par.norm_jacobian_variance(p, mean, cov)
            R = np.maximum(var + self.R_floor, _TINY_VAR_G2)
            xi = 1.0 - h
            d = p - p_a
            return xi, B, R, float(np.sum(xi * xi / R) + d @ info_a @ d)

        p, xi, B, R, cost = _gauss_newton(evaluate, self.p, info_a, p_a)
        m = len(mean)
        poor = float(np.sum(xi * xi / R)) > m + POOR_FIT_SIGMA * math.sqrt(2 * m)
        if poor and m >= ELLIPSOID_MIN_WINDOWS:
            # a far start (the datasheet's offsets are up to ~1 g off) can stall Gauss-Newton in a wrong minimum:
            # also start from an ellipsoid fit of the pending windows, as the batch fit does, keep the better
            try:
                e = ellipsoid_fit(WindowSet(mean, cov, np.ones(m), np.arange(m, dtype=float), np.zeros((m, 0)),
                                            np.zeros(m, dtype=np.int64), np.ones(m, dtype=np.int64)))
                alt = _gauss_newton(evaluate, self.par.pack(e.sensitivity, e.offset), info_a, p_a)
            except (ValueError, np.linalg.LinAlgError):
                alt = None
            if alt is not None and alt[4] < cost:
                p, xi, B, R, cost = alt
                poor = float(np.sum(xi * xi / R)) > m + POOR_FIT_SIGMA * math.sqrt(2 * m)
        H = info_a + B.T @ (B / R[:, None])
        try:
            P = np.linalg.inv(H)
        except np.linalg.LinAlgError:
            P = np.linalg.pinv(H)
        self.p, self.P = p, 0.5 * (P + P.T)
        if self.held is not None:  # dp/dtheta_held of the minimiser: P (P_a^-1 S_a - sum B^T B_h / R)
            B_h = held_jacobian(par, p, mean, self.held)
            self.S = self.P @ (info_a @ self.S_a - B.T @ (B_h / R[:, None]))
        if len(self._pending) >= MAX_PENDING or (not poor and self._settled(par, mean, R)):
            out = xi * xi > self.gate2 * (R + np.einsum("mp,pq,mq->m", B, self.P, B))
            if out.any() and not out.all():  # outliers among them, judged at the settled estimate: drop, re-solve
                self._pending = [w for w, o in zip(self._pending, out) if not o]
                k = int(out.sum())
                self.n_rejected += k
                self.n_updates -= k
                self._solve_pending()
                return
            self._pending = []
            self.p_a, self.P_a, self.S_a = self.p, self.P, self.S
            self.n_folds += 1

    def _second_order(self, P: np.ndarray) -> float:
        """1/2 tr(J P J^T) [g] for the window _h_B_R linearised last (J = da/dp from its a and K^-1): the size
        of h's second-order term over the spread P leaves (|a| = 1)."""
        n = self._n
        J = -((self._dK9.reshape(n, 3, 3) @ self._a + self._do) @ self._Kinv.T)  # (da/dp)^T (P, 3)
        return 0.5 * float(np.sum((P @ J) * J))

    def _settled_one(self, P: np.ndarray, R: float) -> bool:
        """_settled for the window _h_B_R linearised last, under the covariance P."""
        return self._second_order(P) <= LIN_FRACTION * math.sqrt(R)

    def _settled(self, par: Parameterization, mean: np.ndarray, R: np.ndarray) -> bool:
        """Every pending window's second-order term 1/2 tr(J P J^T) (J = da/dp at p) <= LIN_FRACTION sqrt(R)."""
        _, J = par.accel_and_jacobian(self.p, mean)
        lin = 0.5 * np.einsum("mip,pq,miq->m", J, self.P, J)
        return bool(np.all(lin <= LIN_FRACTION * np.sqrt(R)))

    def update(self, window: Window | WindowSet) -> Calibration:
        """Update with one Window (or every row of a WindowSet, in order) and return the calibration."""
        if isinstance(window, Window):
            self.step(window.mean, window.cov / max(window.n, 1), window.t_mid, window.aux_mean)
        elif isinstance(window, WindowSet):
            if len(window):
                validate_windows(window)
            cm = window.cov_of_mean
            for i in range(len(window)):
                self.step(window.mean[i], cm[i], float(window.t[i]), window.aux[i])
        else:
            raise ValueError(f"expected a Window or WindowSet, got {type(window).__name__}")
        return self.calibration

    @property
    def calibration(self) -> Calibration:
        """The current estimate as a Calibration (covariance = P); cheap enough to build per window."""
        par = self.par
        K = (par.K_const.ravel() + self.p @ self._dK9_ref).reshape(3, 3)
        o = par.o_const + self.p @ self._do_ref
        scale_ref = (abs(K[0, 0]) + abs(K[1, 1]) + abs(K[2, 2])) / 3.0
        cov, extra = self.P, {}
        notes = []
        if self.held is not None:
            cons = self.S @ self.held.cov @ self.S.T
            cov = self.P + cons
            extra = {HELD_KEY: {"names": list(self.held.names), "cov": self.held.cov.tolist(), "source": self.held.source},
                     CONSIDER_KEY: consider_metadata(self.held, self.S, self.P, self.names, scale_ref)}
            note = held_std_note(self.names, self.held, self.P, cons, scale_ref)
            if note:
                notes.append(note)
        std_g = np.sqrt(np.maximum(np.diagonal(cov), 0.0)) / scale_ref
        observable = bool((std_g <= self.max_std_g).all())
        if not observable:
            bad = [n for n, s in zip(self.names, std_g) if s > self.max_std_g]
            notes.append(f"not yet determined: {', '.join(bad)} (std > {self.max_std_g * 100:.3g} % of 1 g)")
        converged = self.consecutive_rejected < self.max_consecutive_rejections
        if not converged:
            notes.append(f"last {self.consecutive_rejected} windows rejected by the {math.sqrt(self.gate2):.3g}σ gate: "
                         f"the estimate has probably diverged or the sensor changed; re-run a batch fit")
        return Calibration(
            model=self.par.model, offset=o, sensitivity=K, covariance=cov.copy(), param_names=list(self.names),
            n_windows=self.n_updates, converged=converged, observable=observable, message="; ".join(notes),
            metadata={"estimator": "lotters_recursive", "n_rejected": self.n_rejected,
                      "mean_nis": self.nis_sum / self.n_updates if self.n_updates else float("nan"),
                      "std_g": dict(zip(self.names, std_g.tolist())),
                      **extended_metadata(par, self.p, cov=cov), **extra},  # magnitudes' std: J cov J^T
        )
