"""Observability: which parameters can the windows determine now? gravcal's one rule (``is_observable``).

For every candidate order — offsets (3), 6,
   the full identifiable set 9 (or 12 with a lab frame) — the Fisher information of the
   windows (``core/crlb.py``) gives two numbers, both as RMS calibrated-acceleration error
   over all orientations [g]:

   * statistical: sqrt(tr(G F^-1)) with the window noise plus a quasi-static floor;
   * systematic: a per-window model error of ``systematic_g`` RMS (nonlinearity, residual
     motion, temperature) amplified by the geometry, ``amp = sqrt(lambda_max(G Fbar^-1))``
     with Fbar the per-window information at unit noise. amp depends only on the coverage of
     the sphere, not on the number of windows: it is why orientation 1 with theta = 30° never
     gives sensitivities however long one records (amp ~ 1600 for 6 parameters, ~ 4 for offsets).

   * consider: the parameters the order holds (offsets-only holds the sensitivities) carry the
     uncertainty the current calibration states for them (consider.held_uncertainty: its covariance,
     its stated held covariance, or the datasheet spread for a nominal start); through these
     windows it biases the estimated ones by Gc dtheta (Schmidt consider gain), RMS over all
     orientations sqrt(tr(G Gc C_h Gc^T)). Upright windows cannot tell a sensitivity error from
     an offset: from a datasheet start the offsets are then not determined.

   An order is observable when sqrt(stat^2 + (amp * systematic)^2 + consider^2) <= ``tol_g``.

select_order, check_observable, the batch fit's ``observable`` flag, the online calibrator and
`gravcal diagnose` all ask ``is_observable``; evidence (what *should* be updated) is order.py's.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..calibration import Calibration
from ..crlb import (
    RANK_RTOL,
    bound_from_fisher,
    fisher_inuse,
    norm_noise_var,
    on_ellipsoid,
    sphere_directions,
    sphere_metric,
)
from ..windows import WindowSet, validate_windows
from .consider import consider_gain, held_jacobian, held_uncertainty

ORDERS = ("offsets", "6", "9", "12")
# the orders the online estimator may choose for a configured order (9 and 12 share the 6 below them)
ORDER_LADDER: dict[str, tuple[str, ...]] = {"offsets": ("offsets",), "6": ("offsets", "6"),
                                            "9": ("offsets", "6", "9"), "12": ("offsets", "6", "12")}
N_PARAMS = {"offsets": 3, "6": 6, "9": 9, "12": 9}
TOL_G = 0.010  # auto: predicted RMS acceleration error allowed [g]: 1 % of 1 g (a third of Lötters' 3 %)
TOL_EXPLICIT_G = 0.030  # an order the user asked for is refused only beyond Lötters' 3 % criterion
SYSTEMATIC_G = 0.0005  # per-window model error that no window count averages away [g] (nonlinearity, residual motion)
SIGMA_FLOOR_G = 0.002  # quasi-static floor on each window's norm noise [g] (residual body motion)
POSTURE_CELLS = 400  # sphere cells (~10° apart) for counting distinct postures


@dataclass
class OrderDecision:
    """The order chosen (``model``: "none", "offsets", "6", "9" or "12"), why, and the numbers."""

    model: str
    reason: str
    evidence: dict[str, Any] = field(default_factory=dict)
    calibration: Calibration | None = None  # the fit of the chosen order when select_order fitted it

    @property
    def updates_sensitivities(self) -> bool:
        return self.model in ("6", "9", "12")


# -- coverage and observability -----------------------------------------------------------
def coverage(ws: WindowSet, cal: Calibration) -> dict[str, Any]:
    """How much of the sphere the windows cover (directions through ``cal``).

    spread_deg: largest angle from the mean direction (Lötters' theta); scatter_eig: eigenvalues of
    mean(u u^T) (1/3 each for the full sphere, (1, 0, 0) for one posture); distinct_postures:
    occupied cells of a ~10° grid on the sphere."""
    if len(ws):
        validate_windows(ws)  # the scatter's eigvalsh (LAPACK) may loop forever on a NaN
    a = cal.apply_reference(ws.mean)
    u = a / np.linalg.norm(a, axis=1, keepdims=True)
    c = u.sum(axis=0)
    nc = np.linalg.norm(c)
    spread = 180.0 if nc < 1e-12 else float(np.degrees(np.arccos(np.clip(u @ (c / nc), -1, 1).min())))
    # the nearest cell of each direction, in blocks of windows: the (M, cells) products of a week are 40 MB
    cells_T = sphere_directions(POSTURE_CELLS).T
    cells = np.concatenate([np.argmax(b @ cells_T, axis=1) for b in np.array_split(u, max(1, len(u) // 2048))])
    return {
        "n_windows": len(ws),
        "spread_deg": round(spread, 2),
        "scatter_eig": np.round(np.linalg.eigvalsh(u.T @ u / len(u))[::-1], 4).tolist(),
        "distinct_postures": int(np.unique(cells).size),
    }


def observability(ws: WindowSet, cal: Calibration, model: str, *, sigma_floor_g: float = SIGMA_FLOOR_G,
                  systematic_g: float = SYSTEMATIC_G) -> dict[str, Any]:
    """Predicted errors of order ``model`` for these windows at ``cal`` (see module docstring)."""
    # one Jacobian for both informations: with the window noise (+ floor), and per window at unit noise
    F, param, Fu = fisher_inuse(ws, cal, model, sigma_floor_g=sigma_floor_g, unit_floor_g=1.0)
    G = sphere_metric(param, cal)
    bound = bound_from_fisher(param.model, param.names, F, G, len(ws))
    Fbar = Fu / max(len(ws), 1)  # geometry only
    w = np.linalg.eigvalsh(Fbar) if len(ws) else np.zeros(1)
    if len(ws) == 0 or w.min() <= 1e-12 * max(w.max(), 1e-300):
        amp = math.inf
    else:
        L = np.linalg.cholesky(G)
        amp = float(np.sqrt(np.linalg.eigvalsh(L.T @ np.linalg.solve(Fbar, L)).max()))
    stat = bound.accel_rms_g
    consider, held = _consider_g(ws, cal, param, F, G, sigma_floor_g) if math.isfinite(stat) else (0.0, None)
    total = (math.sqrt(stat**2 + (amp * systematic_g) ** 2 + consider**2)
             if math.isfinite(stat) and math.isfinite(amp) and math.isfinite(consider) else math.inf)
    return {
        "n_params": param.n_params,
        "stat_mg": mg_or_none(stat),
        "amplification": round(amp, 2) if math.isfinite(amp) else None,
        "consider_mg": mg_or_none(consider),
        "held": None if held is None else {"names": held.names, "source": held.source},
        "predicted_mg": mg_or_none(total),
        # the same without the held parameters' uncertainty: determined *given* the held values
        "predicted_given_held_mg": mg_or_none(math.hypot(stat, amp * systematic_g) if math.isfinite(stat) and math.isfinite(amp)
                                       else math.inf),
        "fisher_eig_per_window": np.round(w * float(np.mean(np.abs(np.diag(cal.sensitivity)))) ** 2, 8).tolist()
        if len(ws) else [],
        "undetermined": bound.undetermined,
        "_total_g": total,
    }


def _consider_g(ws: WindowSet, cal: Calibration, param, F: np.ndarray, G: np.ndarray,
                sigma_floor_g: float) -> tuple[float, Any]:
    """RMS calibrated-acceleration error [g] over all orientations that the uncertainty of the parameters
    ``param`` holds (``cal``'s stated uncertainty, consider.held_uncertainty) puts into the estimated ones
    through these windows: sqrt(tr(G_sphere Gc C_h Gc^T)), Gc the consider gain (Schmidt) at ``cal``."""
    held = held_uncertainty(cal, param)
    if held is None or len(ws) == 0:
        return 0.0, held
    _, r_star = on_ellipsoid(ws, cal)
    p = param.pack(cal.sensitivity, cal.offset)
    _, B, _ = param.norm_and_jacobian(p, r_star)
    var = norm_noise_var(ws, cal, sigma_floor_g=sigma_floor_g)
    w, V = np.linalg.eigh(0.5 * (F + F.T))
    if w.min() <= RANK_RTOL * max(w.max(), 1e-300):
        return math.inf, held
    Gc = consider_gain((V / w) @ V.T, B, var, held_jacobian(param, p, r_star, held))
    return float(np.sqrt(max(np.trace(G @ Gc @ held.cov @ Gc.T), 0.0))), held


def held_note(obs: dict[str, Any]) -> str:
    """What to say when the held parameters' uncertainty dominates an order's predicted error ('' if not)."""
    c, stat, held = obs.get("consider_mg"), obs.get("stat_mg"), obs.get("held")
    if held is None or c is None or stat is None or c <= stat:
        return ""
    what = "sensitivities" if all(n.startswith("s_") and len(n) == 3 for n in held["names"]) else ", ".join(held["names"])
    return (f"the uncertainty of the held {what} ({held['source']}) dominates: {c:.3g} mg of the predicted error "
            f"(window noise {stat:.3g} mg); windows in other postures (lying, bending: the sensor's axes "
            f"along and against gravity) determine the sensitivities (order 6), or start from a calibration "
            f"with a small covariance")


def is_observable(ws: WindowSet, cal: Calibration, model, *, tol_g: float = TOL_G,
                  sigma_floor_g: float = SIGMA_FLOOR_G, systematic_g: float = SYSTEMATIC_G) -> tuple[bool, dict[str, Any]]:
    """THE observability rule of gravcal (one place; select_order, check_observable and LottersBatch's
    ``observable`` flag all use it): order ``model`` (a name or a Parameterization, evaluated at ``cal``)
    is observable from ``ws`` when there are at least as many windows as parameters and the predicted
    RMS calibrated-acceleration error sqrt(stat² + (amp·systematic)² + consider²) [g] over all orientations
    is <= ``tol_g`` (consider: the held parameters' stated uncertainty, see the module docstring). Returns (verdict, the numbers of ``observability``)."""
    obs = observability(ws, cal, model, sigma_floor_g=sigma_floor_g, systematic_g=systematic_g)
    return bool(len(ws) >= obs["n_params"] and obs["_total_g"] <= tol_g), obs


def mg_or_none(x: float) -> float | None:
    """[g] -> [mg] rounded for reports; None (JSON null) when not finite."""
    return round(x * 1e3, 3) if math.isfinite(x) else None


def check_observable(ws: WindowSet, model: str, start: Calibration, *, tol_g: float = TOL_EXPLICIT_G,
                     sigma_floor_g: float = SIGMA_FLOOR_G, systematic_g: float = SYSTEMATIC_G) -> dict[str, Any]:
    """Raise ValueError saying what is missing if ``model`` cannot be determined from ``ws``;
    return the observability numbers otherwise."""
    if model not in N_PARAMS:
        raise ValueError(f"unknown model order {model!r}; expected one of {', '.join(ORDERS)}")
    m, P = len(ws), N_PARAMS[model]
    if m < P:
        raise ValueError(f"model {model} has {P} parameters but there are only {m} quasi-static window(s): "
                         f"need at least {P}, from different postures")
    cov = coverage(ws, start)
    ok, obs = is_observable(ws, start, model, tol_g=tol_g, sigma_floor_g=sigma_floor_g, systematic_g=systematic_g)
    if not ok:
        what = "offsets" if model == "offsets" else ("sensitivities" if model == "6" else "sensitivities and cross-axis terms")
        pred = "unbounded (singular Fisher information)" if obs["predicted_mg"] is None else f"{obs['predicted_mg']:.3g} mg"
        raise ValueError(
            f"model {model}: the {m} windows do not determine the {what}: they cover {cov['distinct_postures']} "
            f"distinct posture(s) within {cov['spread_deg']:.0f}° of one direction (scatter eigenvalues "
            f"{', '.join(f'{e:.3g}' for e in cov['scatter_eig'])}); predicted error {pred} > {tol_g * 1e3:.3g} mg"
            + (f" ({note})" if (note := held_note(obs)) else "") +
            ". Record more varied postures (lying, bending), or use --model auto")
    return obs
