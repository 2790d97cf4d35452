"""Lötters et al. (1998) estimator on quasi-static window means: the batch fit (eq. 11a iterated).

Measurement model (eq. 5, 8): every quasi-static window mean m satisfies

    y = 1 [g] = h(m, p) + mu,       h(m, p) = |K(p)^-1 (m - o(p))|

linearised about the previous estimate (eq. 9-10): xi = 1 - h(m, p_hat) = B q + mu with
B = dh/dp (eq. 13a, generalised by the Parameterization) and q = p - p_hat (eq. 12).
The minimum-variance unbiased solution is (eq. 11a, 11b)

    q_hat = (B^T C_mu^-1 B)^-1 B^T C_mu^-1 xi,      C_e = (B^T C_mu^-1 B)^-1.

LottersBatch iterates eq. 11a (Gauss-Newton with step halving) to convergence; recursive.py's
LottersRecursive applies the same linearised model one window at a time. Both work with any
Parameterization (offsets, 6, 9, 12 and the extended models), in the recording's raw units.

Parameters a parameterization holds (offsets-only: the sensitivities) at uncertain values get a consider
(Schmidt) term in the reported covariance (consider.py).

C_mu (the paper: "the variance of the collection of quasi-static moments") is per window:
the delta-method variance of h from the window's covariance of the mean (cov / n), plus a
quasi-static floor sigma_floor_g^2 for residual body motion that the window mean still
contains (see LottersBatch).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..calibration import Calibration
from ..windows import WindowSet, require_windows, validate_windows
from .consider import (CONSIDER_KEY, HELD_KEY, consider_gain, consider_metadata, held_jacobian, held_std_note,
                       held_uncertainty)
from .extended import axis_angles, extended_class, extended_metadata
from .floor import quasi_static_floor
from .observability import N_PARAMS, SIGMA_FLOOR_G, TOL_G, held_note, is_observable
from .parameterization import PARAMETERIZATIONS, Parameterization
from .start import ellipsoid_fit

START_TOLERANCE = 0.05  # the paper's convergence assumption: start within 5 % of the truth
_RCOND = 1e-12  # relative eigenvalue below which a direction of the (normalised) Fisher information is void
ANCHOR_STD_G = 0.3  # weak prior on the start [fraction of 1 g] (see LottersBatch._solve)
STEP_TOL_STD = 1e-6  # Gauss-Newton stops when no parameter moves by more than this fraction of its std
MAX_PLAUSIBLE_RMS_G = 0.5  # a converged fit leaving more than this RMS |a| - 1 g is not a calibration
_TINY_VAR_G2 = 1e-14  # guard against zero-variance windows when no floor is given [g²]
OUTLIER_MAX_FRACTION = 0.1  # the gate leaves out at most this fraction of the windows (more is a model error, not outliers)


# --------------------------------------------------------------------------------------
# shared helpers
# --------------------------------------------------------------------------------------
def resolve_parameterization(model: str | type[Parameterization] | Parameterization, start: Calibration) -> Parameterization:
    """A Parameterization whose held values (K0, o0) come from ``start`` (unless an instance is given)."""
    if isinstance(model, Parameterization):
        return model
    if isinstance(model, type) and issubclass(model, Parameterization):
        return model(start.sensitivity, start.offset)
    if isinstance(model, str):
        if "+" in model and model not in PARAMETERIZATIONS:  # "<base>+<term>...": registered on first use
            extended_class(model)
        try:
            cls = PARAMETERIZATIONS[model]
        except KeyError:
            raise ValueError(f"unknown model {model!r}; known: {', '.join(sorted(PARAMETERIZATIONS))}") from None
        return cls(start.sensitivity, start.offset)
    raise ValueError(f"model must be a name, a Parameterization class or instance, not {type(model).__name__}")


def window_directions_spread_deg(mean: np.ndarray, cal: Calibration) -> float:
    """Largest angle [deg] between a window's acceleration direction and their mean direction."""
    a = cal.apply_reference(mean)
    u = a / np.linalg.norm(a, axis=1, keepdims=True)
    c = u.sum(axis=0)
    nc = np.linalg.norm(c)
    if nc < 1e-12:
        return 180.0
    cosang = np.clip(u @ (c / nc), -1.0, 1.0)
    return float(np.degrees(np.arccos(cosang.min())))


def relative_difference(a: Calibration, b: Calibration) -> float:
    """Largest difference of a vs b in fractions of 1 g (eq. 15-16 style, per axis)."""
    s = np.abs(np.diag(b.sensitivity))
    ds = np.max(np.abs(a.sensitivity - b.sensitivity) / s[:, None])
    do = np.max(np.abs(a.offset - b.offset) / s)
    return float(max(ds, do))


def start_far_note(off: float) -> str:
    """Message for an estimate that ended ``off`` (fraction of 1 g) away from the given start."""
    return (f"the given start was too far off ({off * 100:.1f} % of 1 g from the estimate; the paper's "
            f"linearisation assumes < 5 %): converged by iteration")


# --------------------------------------------------------------------------------------
# batch
# --------------------------------------------------------------------------------------
@dataclass
class _Solve:
    p: np.ndarray
    cov: np.ndarray  # C_e (eq. 11b), eigenvalue-guarded
    chi2: float
    resid_g: np.ndarray  # 1 - h at p [g]
    var_g2: np.ndarray  # C_mu diagonal [g²]
    iterations: int
    converged: bool
    fisher_eig: np.ndarray  # eigenvalues of B^T C_mu^-1 B for parameters in fractions of 1 g
    B: np.ndarray
    var_h: np.ndarray | None = None  # C_mu before the floor at p: a refit from p with another floor starts from it


class LottersBatch:
    """Iterated eq. 11a on a WindowSet.

    Parameters
    ----------
    model: name in PARAMETERIZATIONS ("offsets", "6", ...), a Parameterization class, or an instance.
    sigma_floor_g: quasi-static floor [g] added (in quadrature) to each window's delta-method std of h.
        None (default): derived from the data. A window mean of a body-worn sensor still contains residual
        motion that cov/n does not describe (slow sway, posture drift inside the window, unmodelled
        cross-axis terms), so cov/n alone makes C_mu far too small and C_e over-confident. When the reduced
        chi² of the residuals exceeds 1 we solve for the floor that brings it to 1 and refit with it
        (re-weighting, not just scaling C_e). With an explicit floor, a reduced chi² > 1 inflates C_e by
        that factor (Birge ratio) and is reported in metadata and the message.
    max_iter, tol: Gauss-Newton limits; tol is the largest step in fractions of 1 g (eq. 15-16 units).
    max_std_g: a parameter whose std exceeds this fraction of 1 g is "not determined" -> observable=False.
        Default 0.03: the paper's 3 % criterion.
    retry_from_ellipsoid: when a given start ends > 5 % away or does not converge, also try the
        ellipsoid-fit start and keep the better converged fit (False: the paper's setting, start trusted).
    tol_g: the observability rule's tolerance [g] (``order.is_observable``: predicted RMS acceleration error
        of the order over all orientations, including the geometry's amplification of per-window model
        error). Default ``order.TOL_G`` (10 mg, what ``--model auto`` uses), or inf (no rule) when
        max_std_g is inf (reproducing the paper's tables, which report every estimate).
    outlier_gate_sigma: None (default: every window counts, the paper's estimator) or k: after the fit,
        windows whose norm residual exceeds k robust sigmas are left out and the rest refitted (at most
        OUTLIER_MAX_FRACTION of them; metadata ``outlier_windows``, ``outlier_t``). The robust
        sigma is 1.4826 x the median |residual| in units of each window's own std (noise of its mean plus
        ``sigma_floor_g``, else SIGMA_FLOOR_G), never below 1, of a robust (Cauchy-loss) fit. It is the batch counterpart of
        LottersRecursive's gate: a detector on |a| passes a window that straddles a bump or a smooth
        acceleration plateau (its mean is off the sphere by tens of mg), and with a data-derived floor
        such a window keeps the weight of a good one, so a single one moves a 20-window fit by ~10 mg.
    """

    def __init__(
        self,
        model: str | type[Parameterization] | Parameterization = "6",
        *,
        sigma_floor_g: float | None = None,
        max_iter: int = 50,
        tol: float = 1e-10,
        max_std_g: float = 0.03,
        retry_from_ellipsoid: bool = True,
        tol_g: float | None = None,
        outlier_gate_sigma: float | None = None,
    ):
        if outlier_gate_sigma is not None and not (outlier_gate_sigma > 0 and math.isfinite(outlier_gate_sigma)):
            raise ValueError(f"outlier_gate_sigma must be a finite number > 0 or None, got {outlier_gate_sigma!r}")
        self.outlier_gate_sigma = outlier_gate_sigma
        if sigma_floor_g is not None and not (sigma_floor_g >= 0 and math.isfinite(sigma_floor_g)):
            raise ValueError(f"sigma_floor_g must be a finite number >= 0, got {sigma_floor_g!r}")
        self.model = model
        self.sigma_floor_g = sigma_floor_g
        self.max_iter = int(max_iter)
        self.tol = float(tol)
        self.max_std_g = float(max_std_g)
        self.retry_from_ellipsoid = bool(retry_from_ellipsoid)
        if tol_g is None:
            tol_g = TOL_G if math.isfinite(self.max_std_g) else math.inf
        self.tol_g = float(tol_g)

    # -- core iteration --------------------------------------------------------------
    def _solve(self, par: Parameterization, p0: np.ndarray, anchor: np.ndarray, mean: np.ndarray,
               cov_mean: np.ndarray, floor2: float, at_p0: _Solve | None = None) -> _Solve:
        """Iterate eq. 11a from p0. ``anchor`` (the start) enters as a weak prior of ANCHOR_STD_G
        (0.3 g as a std, in fractions of 1 g): negligible for any determined parameter (a std of 1e-3 g
        is changed by ~1e-5 relative, the 3 % observability limit by 1 %), but it keeps combinations the windows cannot determine at the start instead
        of letting them wander to wherever the noise leads."""
        scale = float(np.mean(np.abs(np.diag(par.unpack(anchor)[0])))) or 1.0
        w_prior = 1.0 / (ANCHOR_STD_G * scale) ** 2

        def evaluate(p, known=None):
            if known is None:
                h, B, _, var_h = par.norm_jacobian_variance(p, mean, cov_mean)
                xi = 1.0 - h  # eq. 14
            else:  # the same p's residuals, Jacobian and C_mu before the floor (``at_p0``)
                xi, B, var_h = known
            var = np.maximum(var_h + floor2, _TINY_VAR_G2)  # C_mu diagonal
            cost = float(np.sum(xi**2 / var) + w_prior * np.sum((p - anchor) ** 2))
            return xi, B, var, cost, var_h

        p = np.array(p0, dtype=float)
        xi, B, var, cost, var_h = evaluate(p, None if at_p0 is None or at_p0.var_h is None
                                           else (at_p0.resid_g, at_p0.B, at_p0.var_h))
        converged = False
        it = 0
        for it in range(1, self.max_iter + 1):
            try:
                step, std = _mvu_solve(B, var, xi, w_prior, p - anchor)  # eq. 11a (+ weak prior)
            except np.linalg.LinAlgError:  # an information that underflowed to singular: ends unconverged
                break
            if not np.all(np.isfinite(step)):
                break
            # converged when the step is negligible in absolute terms or against the parameter's own std
            # (along a direction the windows barely determine, Gauss-Newton crawls; that crawl is noise)
            if np.max(np.abs(step)) / scale < self.tol or np.max(np.abs(step) / std) < STEP_TOL_STD:
                p = p + step  # at the optimum: the cost no longer resolves such steps
                xi, B, var, cost, var_h = evaluate(p)
                converged = True
                break
            # step halving: the linearisation (eq. 9) only holds near p; never accept a worse fit
            lam = 1.0
            for _ in range(30):
                try:
                    trial = evaluate(p + lam * step)
                except np.linalg.LinAlgError:
                    lam *= 0.5
                    continue
                # compare at the current weights C_mu(p): eq. 11a is a descent direction for that cost
                # (an IRLS step); its fixed point is the MVU estimate, the paper's solution
                cost_fixed = float(np.sum(trial[0] ** 2 / var) + w_prior * np.sum((p + lam * step - anchor) ** 2))
                if np.isfinite(cost_fixed) and cost_fixed <= cost * (1 + 1e-12):
                    break
                lam *= 0.5
            else:
                break
            p = p + lam * step
            xi, B, var, cost, var_h = trial
            cost = float(np.sum(xi**2 / var) + w_prior * np.sum((p - anchor) ** 2))
            if np.max(np.abs(lam * step)) / scale < self.tol:
                converged = True
                break
        cov, eig = _mvu_covariance(B, var, scale)  # eq. 11b (data only: no prior in the reported C_e)
        converged = converged and bool(np.all(np.isfinite(eig)))
        return _Solve(p, cov, float(np.sum(xi**2 / var)), xi, var, it, converged, eig, B, var_h)

    # -- public ------------------------------------------------------------------------
    def fit(self, ws: WindowSet, start: Calibration | None = None) -> Calibration:
        """Calibration (raw = K a + o) from quasi-static windows; raises ValueError on unusable input."""
        return self._fit(ws, start, gate=self.outlier_gate_sigma is not None)

    def fit_fold(self, ws: WindowSet, start: Calibration | None = None) -> Calibration:
        """``fit`` for a held-out fold's training windows, whose fit only scores the windows left out:
        the same parameters (K, o, metadata ``params``/``extended``), ``converged`` and fit statistics,
        without what only a reported calibration needs (the consider term of the covariance, the
        observability verdict: ``observable`` is False and the message says it was not judged)."""
        return self._fit(ws, start, gate=self.outlier_gate_sigma is not None, verdict=False)

    def _outliers(self, par: Parameterization, sol: _Solve, mean: np.ndarray, floor2: float) -> np.ndarray:
        """Windows more than outlier_gate_sigma robust sigmas off a robust fit (bool (m,)), the largest first,
        at most OUTLIER_MAX_FRACTION of them. The robust fit (Cauchy loss on the residuals in units of each
        window's std, scipy.optimize.least_squares from the least-squares solution) keeps two outliers from
        masking each other: least squares spreads them over the other windows, so its residuals would not
        single them out."""
        from scipy.optimize import least_squares  # noqa: PLC0415 (start-up cost: only this robust fit needs it)

        floor_g2 = floor2 if self.sigma_floor_g is not None else SIGMA_FLOOR_G**2
        sd = np.sqrt(np.maximum(sol.var_g2 - floor2 + floor_g2, _TINY_VAR_G2))

        def resid(p: np.ndarray) -> np.ndarray:
            return (1.0 - par.norm_and_jacobian(p, mean)[0]) / sd

        def jac(p: np.ndarray) -> np.ndarray:
            return -par.norm_and_jacobian(p, mean)[1] / sd[:, None]

        try:
            rob = least_squares(resid, sol.p, jac=jac, loss="cauchy", f_scale=1.0, x_scale="jac", max_nfev=200)
            r = np.abs(resid(rob.x))
        except (ValueError, np.linalg.LinAlgError):
            r = np.abs(sol.resid_g) / sd
        sigma = max(1.4826 * float(np.median(r)), 1.0)
        over = np.flatnonzero(r > self.outlier_gate_sigma * sigma)
        over = over[np.argsort(-r[over])][: int(OUTLIER_MAX_FRACTION * len(r))]
        mask = np.zeros(len(r), dtype=bool)
        mask[over] = True
        return mask

    def _fit(self, ws: WindowSet, start: Calibration | None, *, gate: bool = False, verdict: bool = True) -> Calibration:
        if not isinstance(ws, WindowSet):
            raise ValueError(f"expected a WindowSet, got {type(ws).__name__}")
        validate_windows(ws)
        notes: list[str] = []
        start_source = "given"
        if start is None:
            start = ellipsoid_fit(ws)
            start_source = "ellipsoid_fit"
        if not (np.all(np.isfinite(start.offset)) and np.all(np.isfinite(start.sensitivity))):
            raise ValueError("start calibration has non-finite offset or sensitivity")
        if abs(np.linalg.det(start.sensitivity)) < 1e-300:
            raise ValueError("start calibration has a singular sensitivity matrix")
        par = resolve_parameterization(self.model, start).at_windows(ws)  # per-window covariates, if any
        unusable = par.unusable_windows()
        if unusable:
            raise ValueError(unusable)
        require_windows(len(ws), par.n_params)  # the rest validate_windows checked above

        mean = ws.mean
        cov_mean = ws.cov_of_mean
        p0 = par.pack(start.sensitivity, start.offset)
        floor2 = 0.0 if self.sigma_floor_g is None else float(self.sigma_floor_g) ** 2
        anchor = p0
        sol = self._solve(par, p0, p0, mean, cov_mean, floor2)

        # A start far from the truth may converge elsewhere (the paper assumes < 5 %): when the estimate
        # ends > 5 % from the given start or did not converge, also fit from the ellipsoid start and keep
        # the converged fit with the lower chi²; flag non-convergence if neither converged.
        K1, o1 = par.unpack(sol.p)
        far = relative_difference(Calibration(par.model, o1, K1), start) > START_TOLERANCE
        if start_source == "given" and self.retry_from_ellipsoid and (not sol.converged or far):
            try:
                alt_start = ellipsoid_fit(ws)
                pa = par.pack(alt_start.sensitivity, alt_start.offset)
                alt = self._solve(par, pa, pa, mean, cov_mean, floor2)
                if alt.converged and (alt.chi2 < sol.chi2 * (1 - 1e-9) or not sol.converged):
                    sol, anchor = alt, pa
                    start_source = "ellipsoid_fit (retry: the given start led to a worse or no solution)"
                    notes.append("the given start was too far off (did not converge or a worse fit); "
                                 "used the ellipsoid-fit start")
            except ValueError as exc:
                notes.append(f"ellipsoid-fit retry impossible: {exc}")

        m, P = len(ws), par.n_params
        if gate and sol.converged:
            out = self._outliers(par, sol, mean, floor2)
            if out.any() and m - int(out.sum()) >= P + 3:
                cal = self._fit(ws.subset(np.flatnonzero(~out)), start, verdict=verdict)
                cal.metadata["outlier_windows"] = int(out.sum())
                cal.metadata["outlier_t"] = [float(t) for t in ws.t[out]]
                note = (f"left out {int(out.sum())} of {m} windows whose |a| is more than {self.outlier_gate_sigma:g} "
                        f"robust sigmas off the fit (not quasi-static: a bump or an acceleration plateau)")
                cal.message = "; ".join(x for x in (cal.message, note) if x)
                return cal
        dof = m - P
        chi2_red_stat = sol.chi2 / dof if dof > 0 else float("nan")
        floor_used = math.sqrt(floor2)
        inflation = 1.0
        if self.sigma_floor_g is None and dof > 0 and chi2_red_stat > 1.0:
            # data-derived floor: solve sum xi²/(v + f²) = dof for f², then re-weight and refit
            v0 = sol.var_g2 - floor2
            r2 = sol.resid_g**2
            floor2 = quasi_static_floor(r2, v0, dof, _TINY_VAR_G2)
            floor_used = math.sqrt(floor2)
            sol2 = self._solve(par, sol.p, anchor, mean, cov_mean, floor2, at_p0=sol)
            sol = _Solve(sol2.p, sol2.cov, sol2.chi2, sol2.resid_g, sol2.var_g2, sol.iterations + sol2.iterations,
                         sol.converged and sol2.converged, sol2.fisher_eig, sol2.B)
            notes.append(f"reduced chi² {chi2_red_stat:.3g} from window noise alone: added a quasi-static floor "
                         f"of {floor_used * 1e3:.3g} mg to C_mu")
        if not np.all(np.isfinite(sol.fisher_eig)):
            raise ValueError(f"the {par.model} fit overflowed to non-finite values from the start "
                             f"({start_source}): the start is far off these windows' scale (units?)")
        rms_g = float(np.sqrt(np.mean(sol.resid_g**2)))
        if rms_g > MAX_PLAUSIBLE_RMS_G:
            sol.converged = False
            notes.append(f"the fit leaves an RMS |a| - 1 g of {rms_g * 1e3:.0f} mg: the windows do not lie on the "
                         f"fitted ellipsoid (wrong start, wrong units, or not quasi-static)")
        chi2_red = sol.chi2 / dof if dof > 0 else float("nan")
        if self.sigma_floor_g is not None and dof > 0 and chi2_red > 1.0:
            inflation = chi2_red  # Birge ratio: the given C_mu is too small by this factor
            notes.append(f"reduced chi² {chi2_red:.3g} > 1 with sigma_floor_g={self.sigma_floor_g}: C_e inflated by it")
        cov_noise = sol.cov * inflation

        K, o = par.unpack(sol.p)
        if not verdict:
            return Calibration(model=par.model, offset=o, sensitivity=K, covariance=cov_noise, param_names=list(par.names),
                               n_windows=m, converged=bool(sol.converged and np.all(np.isfinite(sol.p))), observable=False,
                               message="; ".join(["held-out fold: observability not judged", *notes]),
                               metadata={"estimator": "lotters_batch", "iterations": int(sol.iterations),
                                         "chi2": float(sol.chi2), "dof": int(dof), "sigma_floor_g": float(floor_used),
                                         **extended_metadata(par, sol.p, cov=cov_noise)})
        scale = np.abs(np.diag(K))
        scale_ref = float(np.mean(scale))
        # consider term: the held parameters' uncertainty (consider.py)
        held = held_uncertainty(start, par)
        cov, consider_meta, held_meta = cov_noise, None, {}
        if held is not None:
            G = consider_gain(sol.cov, sol.B, sol.var_g2, held_jacobian(par, sol.p, mean, held))
            cons = G @ held.cov @ G.T
            cov = cov_noise + cons
            consider_meta = consider_metadata(held, -G, cov_noise, list(par.names), scale_ref)
            held_meta = {HELD_KEY: {"names": list(held.names), "cov": held.cov.tolist(), "source": held.source}}
            note = held_std_note(list(par.names), held, cov_noise, cons, scale_ref)
            if note:
                notes.append(note)
        std = np.sqrt(np.clip(np.diag(cov), 0, None))
        std_g = std / scale_ref  # fractions of 1 g (eq. 15-16)
        # window spread judged with the estimate when it converged (a far-off start distorts angles)
        view = Calibration(par.model, o, K) if sol.converged else start
        here = Calibration(par.model, o, K, metadata=dict(held_meta))  # the estimate, with its held uncertainty
        # the offsets-only alternative ("use --model offsets") holds the start's K with the start's uncertainty
        offsets_alt = Calibration(start.model, o, start.sensitivity, covariance=start.covariance,
                                  param_names=list(start.param_names), metadata=dict(start.metadata))
        observable, obs_msg = self._observability(par, sol, cov, std_g, ws, here, view, offsets_alt)
        converged = bool(sol.converged and np.all(np.isfinite(sol.p)))
        if not converged:
            notes.insert(0, f"did not converge in {sol.iterations} iterations (start {start_source}); "
                            f"the estimate is not trustworthy")
        if obs_msg:
            notes.insert(0, obs_msg)
        off = relative_difference(Calibration(par.model, o, K), start)
        if off > START_TOLERANCE and start_source == "given":
            notes.append(start_far_note(off))
        metadata = {
            "estimator": "lotters_batch",
            "iterations": int(sol.iterations),
            "chi2": float(sol.chi2),
            "dof": int(dof),
            "reduced_chi2": float(chi2_red),
            "reduced_chi2_window_noise_only": float(chi2_red_stat),
            "sigma_floor_g": float(floor_used),
            "cov_inflation": float(inflation),
            "start": start_source,
            "start_offset_from_estimate": off,
            "std_g": {n: float(s) for n, s in zip(par.names, std_g)},
            "direction_std_g": (1.0 / np.sqrt(np.maximum(sol.fisher_eig, 1e-300))).tolist(),
            "spread_deg": window_directions_spread_deg(mean, view),
            "insample_rms_mg": float(np.sqrt(np.mean(sol.resid_g**2)) * 1e3),
            **held_meta,
            # params (+ extended terms): K, o above hold at T_ref / t0 only; apply_extended needs these
            **extended_metadata(par, sol.p, cov=cov),
        }
        if consider_meta is not None:
            metadata[CONSIDER_KEY] = consider_meta
        if (par.model if par.model in N_PARAMS else getattr(par, "base_model", None)) in ("9", "12"):
            # the symmetric cross-axis entries as the angles between the calibrated axes (K's rows), with std
            metadata["misalignment_deg"] = axis_angles(par, sol.p, cov)
        return Calibration(
            model=par.model, offset=o, sensitivity=K, covariance=cov, param_names=list(par.names),
            n_windows=m, converged=converged, observable=observable, message="; ".join(notes), metadata=metadata,
        )

    def _observability(self, par, sol: _Solve, cov, std_g, ws: WindowSet, cal, start,
                       offsets_alt: Calibration | None = None) -> tuple[bool, str]:
        """Is every requested parameter determined? gravcal's one rule (``order.is_observable``: predicted
        RMS acceleration error of this order <= ``tol_g``, the rule ``select_order`` uses, so an order auto
        would not choose is never flagged observable here), plus a numerically singular Fisher information
        B^T C_mu^-1 B and, as before, every parameter's std <= ``max_std_g`` (fractions of 1 g)."""
        mean = ws.mean
        eig = sol.fisher_eig  # information in (fraction of 1 g)^-2
        singular = eig.size == 0 or eig.min() <= max(_RCOND * eig.max(), 1.0 / self.max_std_g**2)
        bad = [n for n, s in zip(par.names, std_g) if not (s <= self.max_std_g)]
        # the order rule: on this parameterization, or on the base order of an extended one (extra terms: std rule)
        base = par.model if par.model in N_PARAMS else getattr(par, "base_model", None)
        rule_ok, obs = True, None
        if base in N_PARAMS and math.isfinite(self.tol_g):
            try:
                rule_ok, obs = is_observable(ws, cal, par if base == par.model else base, tol_g=self.tol_g)
            except (ValueError, np.linalg.LinAlgError):
                rule_ok = False
        if not singular and not bad and rule_ok:
            return True, ""
        offsets_ok = False  # worth saying "use --model offsets"? (only computed for a negative verdict)
        if par.model != "offsets" and math.isfinite(self.tol_g):
            try:
                offsets_ok = is_observable(ws, offsets_alt if offsets_alt is not None else cal, "offsets",
                                           tol_g=self.tol_g)[0]
            except (ValueError, np.linalg.LinAlgError):
                pass
        if (singular or not rule_ok) and not bad:
            if base == "offsets":
                bad = [n for n in par.names if n.startswith("o_")]
            elif offsets_ok:
                bad = [n for n in par.names if n.startswith("s_")]
            else:
                bad = list(par.names)
        spread = window_directions_spread_deg(mean, start)
        kinds = {n.split("_")[0] for n in bad}
        what = {"s": "sensitivities", "o": "offsets"}.get(next(iter(kinds)), "") if len(kinds) == 1 else ""
        if what == "sensitivities" and base in ("9", "12"):
            what = "sensitivities and cross-axis terms"
        what = what or ", ".join(bad)
        worst = max((s for s in std_g if np.isfinite(s)), default=float("inf"))
        msg = (f"{what} not observable: all {len(mean)} windows within {spread:.0f}° of one direction "
               f"(std up to {worst * 100:.3g} % of 1 g")
        if obs is not None and not rule_ok:
            pred = "unbounded" if obs["predicted_mg"] is None else f"{obs['predicted_mg']:.3g} mg"
            msg += f"; predicted error {pred} > {self.tol_g * 1e3:.3g} mg)"
            note = held_note(obs)
            if note:
                msg += f"; {note}"
        else:
            msg += f" > {self.max_std_g * 100:.3g} %)"
        if offsets_ok:
            msg += "; use --model offsets"
        return False, msg


def _mvu_solve(B: np.ndarray, var: np.ndarray, xi: np.ndarray, w_prior: float, dev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """q_hat of eq. 11a with C_mu = diag(var), plus the weak prior w_prior |p - anchor|² (dev = p - anchor);
    also the std of each parameter under that regularised information."""
    BW = B.T * (1.0 / var)
    F = BW @ B
    F[np.diag_indices_from(F)] += w_prior
    b = BW @ xi - w_prior * dev
    Finv = np.linalg.inv(F)
    return Finv @ b, np.sqrt(np.diag(Finv))


def _mvu_covariance(B: np.ndarray, var: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """C_e of eq. 11b and the eigenvalues of the information B^T C_mu^-1 B for parameters in units
    of ``scale`` (the mean sensitivity), i.e. in fractions of 1 g as eq. 15-16: 1/sqrt(eigenvalue) is
    the std [fraction of 1 g] of that parameter combination. A (numerically) singular direction gets
    a huge, finite variance, so an unobservable parameter never looks confident."""
    W = 1.0 / var
    F = (B.T * W) @ B * (scale * scale)
    if not np.all(np.isfinite(F)):  # an iterate that overflowed (a start far off the windows' scale): eigh (LAPACK)
        return np.full(F.shape, np.nan), np.full(F.shape[0], np.nan)  # may loop forever on a NaN; no C_e then
    lam, V = np.linalg.eigh(F)
    lam_c = np.maximum(lam, _RCOND * max(float(lam[-1]), 1e-300))
    cov = (V / lam_c) @ V.T * (scale * scale)
    return cov, lam
