"""Consider (Schmidt) covariance: the uncertainty of the parameters a parameterization holds.

A parameterization estimates p and holds the rest of (K, o) at the start's values (offsets-only
holds the sensitivities). When those held values are themselves uncertain (a datasheet nominal
start, a previous fit), their error propagates into p: linearised, Lötters' eq. 10 becomes
    xi = B_e q + B_h dtheta + mu       (B_h = dh/dtheta, theta the held parameters)
and the MVU estimate (eq. 11a) picks up  q_hat = ... + G dtheta,  G = (B_e^T W B_e)^-1 B_e^T W B_h,
W = C_mu^-1. The honest covariance is C_total = C_e + G C_h G^T (consider / uncertain-parameter
analysis), C_h the held parameters' covariance. The estimate itself is unchanged.

Used by the batch and recursive estimators (lotters.py, recursive.py), the observability rule
(observability.py) and the bootstrap (start.py).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..calibration import Calibration
from ..model.datasheet import D0_LIMITS, SENS_LIMITS, SENS_TYP
from .parameterization import Parameterization

# Where C_h comes from (one mechanism: the start Calibration says how uncertain it is):
#   1. the start's own covariance over its param_names (a previous fit: 6-param, lab, bootstrap);
#   2. start.metadata[HELD_KEY] = {"names": [...], "cov": [[...]]} [raw units²] for names not in 1
#      (set by with_held_uncertainty; every fit here carries its held parameters' entry forward);
#   Neither: the held values are taken as exact (no consider term). A datasheet
#   nominal start has no data behind it but a known spread: wherever one is made, state it with
#   datasheet_held_uncertainty(start) (the ADXL210 spreads of core/model/datasheet.py).
# Parameter names map to directions in (K, o): "s_x" / "s_xx" -> K[0, 0], "s_xy" -> K[0, 1] + K[1, 0],
# "o_x" -> o[0]; directions the parameterization estimates are projected out (its own offsets'
# prior uncertainty is not held: the windows re-estimate them).
HELD_KEY = "held_covariance"
CONSIDER_KEY = "consider"


# (sensitivity std as a fraction of it, zero-g offset std [g]) of an ADXL210 part, from the datasheet
# min/max (core/model/datasheet.py; min/max = +-3 sigma, the model's own convention): 6.7 %, 0.67 g
DATASHEET_SENSITIVITY_REL_STD = (SENS_LIMITS[1] - SENS_LIMITS[0]) / 6.0 / SENS_TYP
DATASHEET_OFFSET_STD_G = (D0_LIMITS[1] - D0_LIMITS[0]) / 6.0 / SENS_TYP


def with_held_uncertainty(cal: Calibration, std: dict[str, float] | None = None, *,
                          names: list[str] | None = None, cov: np.ndarray | None = None,
                          source: str = "stated held uncertainty") -> Calibration:
    """A copy of ``cal`` stating how uncertain its values are, for the parameters a later fit may hold:
    ``std`` {name: std [raw units]} (independent) or ``names`` with a covariance ``cov`` [raw units²]."""
    if std is not None:
        names, cov = list(std), np.diag(np.asarray([float(v) for v in std.values()]) ** 2)
    if names is None or cov is None:
        raise ValueError("with_held_uncertainty needs std={name: std} or names= and cov=")
    cov = np.asarray(cov, dtype=float)
    if cov.shape != (len(names), len(names)) or not np.all(np.isfinite(cov)) or np.any(np.diag(cov) < 0):
        raise ValueError(f"held covariance must be a finite ({len(names)}, {len(names)}) matrix with a "
                         f"non-negative diagonal, got shape {cov.shape}")
    unknown = [n for n in names if _name_direction(n) is None]
    if unknown:
        raise ValueError(f"unknown held parameter name(s) {unknown}: use s_x, s_y, s_z, s_xy, s_xz, s_yz, o_x, o_y, o_z")
    meta = dict(cal.metadata)
    meta[HELD_KEY] = {"names": list(names), "cov": cov.tolist(), "source": source}
    return Calibration(cal.model, cal.offset, cal.sensitivity, covariance=cal.covariance.copy(),
                       param_names=list(cal.param_names), n_windows=cal.n_windows, converged=cal.converged,
                       observable=cal.observable, message=cal.message, metadata=meta)


def datasheet_held_uncertainty(cal: Calibration, *, sensitivity_rel_std: float | None = None,
                               offset_std_g: float | None = None) -> Calibration:
    """``cal`` (a datasheet nominal calibration) stating the datasheet spread of the part: each
    sensitivity +-``sensitivity_rel_std`` of itself, each offset +-``offset_std_g`` [g] (defaults: the
    ADXL210 spreads of core/model/datasheet.py, 6.7 % and 0.67 g)."""
    rs = DATASHEET_SENSITIVITY_REL_STD if sensitivity_rel_std is None else float(sensitivity_rel_std)
    og = DATASHEET_OFFSET_STD_G if offset_std_g is None else float(offset_std_g)
    s = np.abs(np.diag(cal.sensitivity))
    std = {f"s_{a}": rs * s[i] for i, a in enumerate("xyz")}
    std.update({f"o_{a}": og * s[i] for i, a in enumerate("xyz")})
    return with_held_uncertainty(cal, std, source="datasheet spread of a nominal start")


_AXIS = {"x": 0, "y": 1, "z": 2}


def _name_direction(name: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(dK (3, 3), do (3,)) of a parameter name, or None when it is not a plain K or o entry."""
    kind, _, ax = name.partition("_")
    dK, do = np.zeros((3, 3)), np.zeros(3)
    if kind == "o" and len(ax) == 1 and ax in _AXIS:
        do[_AXIS[ax]] = 1.0
    elif kind == "s" and len(ax) == 1 and ax in _AXIS:
        dK[_AXIS[ax], _AXIS[ax]] = 1.0
    elif kind == "s" and len(ax) == 2 and ax[0] in _AXIS and ax[1] in _AXIS:
        i, j = _AXIS[ax[0]], _AXIS[ax[1]]
        dK[i, j] = dK[j, i] = 1.0  # symmetric (in-use 9) entry; s_xx is the diagonal
    else:
        return None
    return dK, do


@dataclass
class HeldUncertainty:
    """Parameters a parameterization holds, with their covariance: names, cov (H, H) [raw units²],
    their directions dK (H, 3, 3) and do (H, 3) with what the parameterization estimates projected
    out, and where the covariance came from."""

    names: list[str]
    cov: np.ndarray
    dK: np.ndarray
    do: np.ndarray
    source: str


def _stated_uncertainty(start: Calibration) -> tuple[list[str], np.ndarray, list[str]]:
    """Names, covariance and the source of each, as the start states them (see the section comment)."""
    names: list[str] = []
    cov = np.zeros((0, 0))
    n = len(start.param_names)
    if n and start.covariance.shape == (n, n) and np.all(np.isfinite(start.covariance)):
        names, cov = list(start.param_names), np.asarray(start.covariance, dtype=float)
    sources = ["the start's covariance"] * len(names)
    held = start.metadata.get(HELD_KEY) if isinstance(start.metadata, dict) else None
    if isinstance(held, dict) and held.get("names"):
        hn = list(held["names"])
        hc = np.asarray(held["cov"], dtype=float).reshape(len(hn), len(hn))
        extra = [k for k, nm in enumerate(hn) if nm not in names]
        if extra and np.all(np.isfinite(hc)):
            C = np.zeros((len(names) + len(extra),) * 2)
            C[:len(names), :len(names)] = cov
            C[len(names):, len(names):] = hc[np.ix_(extra, extra)]
            names, cov = names + [hn[k] for k in extra], C
            sources += [str(held.get("source") or "stated held uncertainty")] * len(extra)
    return names, cov, sources


def held_uncertainty(start: Calibration, par: Parameterization) -> HeldUncertainty | None:
    """The uncertain parameters ``par`` holds at ``start``'s values, or None when there are none
    (nothing stated, or everything stated is estimated by ``par``)."""
    names, cov, sources = _stated_uncertainty(start)
    dirs = [(k, _name_direction(nm)) for k, nm in enumerate(names)]
    dirs = [(k, d) for k, d in dirs if d is not None]
    if not dirs:
        return None
    idx = np.array([k for k, _ in dirs])
    D = np.stack([np.concatenate([d[0].ravel(), d[1]]) for _, d in dirs], axis=1)  # (12, H)
    E = np.concatenate([par.dK.reshape(par.n_params, 9), par.do], axis=1).T  # (12, P): what par estimates
    D_perp = D - E @ np.linalg.lstsq(E, D, rcond=None)[0]
    keep = np.linalg.norm(D_perp, axis=0) > 1e-9 * np.linalg.norm(D, axis=0)
    C = cov[np.ix_(idx, idx)][np.ix_(keep, keep)]
    if not keep.any() or not np.any(np.diag(C) > 0):
        return None
    D_perp = D_perp[:, keep]
    H = D_perp.shape[1]
    kept = idx[keep]
    source = " and ".join(dict.fromkeys(sources[k] for k in kept))
    return HeldUncertainty([names[k] for k in kept], 0.5 * (C + C.T), D_perp[:9].T.reshape(H, 3, 3).copy(),
                           D_perp[9:].T.copy(), source)


def held_jacobian(par: Parameterization, p: np.ndarray, mean: np.ndarray, held: HeldUncertainty) -> np.ndarray:
    """B_h = dh/dtheta (M, H) at p for window means (M, 3): -u^T K^-1 (dK_h a + do_h), as eq. 13a."""
    a, _ = par.accel_and_jacobian(p, mean)  # per-window a (covariates included)
    K, _ = par.unpack(p)
    g = (a / np.linalg.norm(a, axis=1, keepdims=True)) @ np.linalg.inv(K)  # dh/dm (M, 3)
    return -(np.einsum("mi,hij,mj->mh", g, held.dK, a) + g @ held.do.T)


def consider_gain(cov_e: np.ndarray, B_e: np.ndarray, var: np.ndarray, B_h: np.ndarray) -> np.ndarray:
    """G = (B_e^T W B_e)^-1 B_e^T W B_h (P, H), W = diag(1/var), with ``cov_e`` that inverse (eq. 11b):
    q_hat moves by G dtheta when the held values are off by dtheta (so dp_hat/dtheta_0 = -G)."""
    return cov_e @ ((B_e.T / var) @ B_h)


def consider_metadata(held: HeldUncertainty, sens: np.ndarray, cov_noise: np.ndarray, names: list[str],
                       scale_ref: float) -> dict:
    """metadata[CONSIDER_KEY]: what the reported covariance is made of."""
    cons = sens @ held.cov @ sens.T
    return {
        "held": list(held.names),
        "held_source": held.source,
        "sensitivity": sens.tolist(),  # d p_hat / d theta_held (P, H)
        "covariance_noise_only": cov_noise.tolist(),
        "std_g_noise_only": {n: float(s) for n, s in zip(names, np.sqrt(np.clip(np.diag(cov_noise), 0, None)) / scale_ref)},
        "std_g_held": {n: float(s) for n, s in zip(names, np.sqrt(np.clip(np.diag(cons), 0, None)) / scale_ref)},
    }


def held_std_note(par_names: list[str], held: HeldUncertainty, cov_noise: np.ndarray, cons: np.ndarray,
               scale_ref: float) -> str:
    """A note when the held parameters' uncertainty dominates some estimated parameter's std."""
    sn, sc = np.sqrt(np.clip(np.diag(cov_noise), 0, None)), np.sqrt(np.clip(np.diag(cons), 0, None))
    k = int(np.argmax(sc - sn))
    if sc[k] <= sn[k]:
        return ""
    return (f"std includes the uncertainty of the held {', '.join(held.names)} ({held.source}): "
            f"{par_names[k]} std {math.hypot(sn[k], sc[k]) / scale_ref * 1e3:.3g} mg, of which the held "
            f"parameters {sc[k] / scale_ref * 1e3:.3g} mg, the window noise {sn[k] / scale_ref * 1e3:.3g} mg")
