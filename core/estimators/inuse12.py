"""In-use 9 / 12: the identifiable part of the full sensitivity matrix, and the held frame.

From quasi-static windows alone the estimator sees only |K^-1 (r - o)| = 1 g, which is
unchanged by K -> K R^T for any rotation R. Writing K = S R0 (left polar decomposition:
S symmetric positive definite, R0 orthogonal), the data determine S (6) and o (3); R0 (the
frame: how the sensing axes sit in the capsule) must come from elsewhere:

* "12": R0 held from the latest lab calibration (Bragge, ``estimators/bragge.py``) — or from
  the previous 12-in-use calibration, which carries it unchanged;
* "9":  the convention R0 = I (K symmetric) when there is no lab frame.

See docs/twelve-parameters.md for the argument. The parameterizations themselves are
``NineParameter`` / ``TwelveInUse`` in ``parameterization.py``; this module adds the frame
bookkeeping and a checked batch fit on top of LottersBatch.
"""
from __future__ import annotations

import math

import numpy as np

from ..calibration import Calibration
from ..windows import WindowSet
from .lotters import LottersBatch
from .observability import check_observable
from .parameterization import polar_frame
from .start import ellipsoid_fit

FRAME_CONVENTION = "R0 = I (no lab frame: K symmetric)"


def identifiable_part(cal: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """(S, o): what the gravity norm determines. S = (K K^T)^1/2 [raw/g], o [raw]."""
    return polar_frame(cal.sensitivity)[0], cal.offset.copy()


def frame_of(cal: Calibration) -> np.ndarray:
    """The frame R0 (orthogonal, 3x3) carried by a calibration's K = S R0."""
    return polar_frame(cal.sensitivity)[1]


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle [deg] of the rotation R (0 for the identity)."""
    d = np.linalg.norm(np.asarray(R, dtype=float) - np.eye(3)) / math.sqrt(8.0)  # |R - I|_F^2 = 8 sin^2(angle/2)
    return float(np.degrees(2.0 * np.arcsin(min(d, 1.0))))  # accurate at small angles, unlike arccos(trace)


def with_frame(cal: Calibration, frame: np.ndarray | Calibration | None) -> Calibration:
    """``cal`` re-expressed as K = S R0 with R0 = ``frame`` (a rotation, or a calibration whose frame
    is taken; None: R0 = I). The norm |K^-1 (r - o)| — all the data can check — is unchanged."""
    if isinstance(frame, Calibration):
        R0 = frame_of(frame)
    elif frame is None:
        R0 = np.eye(3)
    else:
        R0 = np.asarray(frame, dtype=float).reshape(3, 3)
        if not np.allclose(R0 @ R0.T, np.eye(3), atol=1e-9):
            raise ValueError("frame must be an orthogonal 3x3 matrix")
    S, _ = polar_frame(cal.sensitivity)
    return Calibration(model=cal.model, offset=cal.offset, sensitivity=S @ R0, covariance=cal.covariance,
                       param_names=list(cal.param_names), n_windows=cal.n_windows, converged=cal.converged,
                       observable=cal.observable, message=cal.message, metadata=dict(cal.metadata))


def fit_inuse(ws: WindowSet, model: str = "12", *, lab: Calibration | None = None, start: Calibration | None = None,
              check: bool = True, **batch_kw) -> Calibration:
    """Batch in-use fit of the 9 identifiable parameters (S, o) with the frame held.

    model "12": frame from ``lab`` (required: a lab calibration, e.g. ``bragge.calibrate_lab``'s or
    a previous 12-in-use calibration); model "9": frame R0 = I. ``start`` (any convention; default
    an ellipsoid fit of the windows) supplies the linearisation point. ``check`` refuses data that
    cannot determine the 9 parameters (``order.check_observable``) with a message saying what is
    missing. ``batch_kw`` go to LottersBatch.
    """
    if model not in ("9", "12"):
        raise ValueError(f"fit_inuse fits model '9' or '12', not {model!r}")
    if model == "12" and lab is None:
        raise ValueError("model 12 holds the frame of a lab calibration: give lab= (gravcal calibrate --lab output), "
                         "or use model 9 (frame convention R0 = I)")
    if start is None:
        start = full_start(ws) if len(ws) >= 9 else ellipsoid_fit(ws)
    frame = frame_of(lab) if model == "12" else np.eye(3)
    start = with_frame(start, frame)
    if check:
        check_observable(ws, model, start)
    cal = LottersBatch(model, **batch_kw).fit(ws, start)
    held = frame_of(cal)
    cal.metadata.update({
        "frame": held.tolist(),
        "frame_source": ("lab calibration" + (f" ({lab.metadata.get('created', '')})" if lab.metadata.get("created") else ""))
        if model == "12" else FRAME_CONVENTION,
        "frame_angle_deg": rotation_angle_deg(held),
        "identifiable": ["S (symmetric, 6)", "o (3)"],
    })
    return cal


def full_start(ws: WindowSet) -> Calibration:
    """A symmetric-K start (the general quadric, ``ellipsoid_fit(full=True)``); the axis-aligned fit when
    the windows cannot determine the general one."""
    try:
        return ellipsoid_fit(ws, full=True)
    except ValueError:
        return ellipsoid_fit(ws)
