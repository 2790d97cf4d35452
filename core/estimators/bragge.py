"""Lab calibration after Bragge et al.: all 12 parameters from known gravity directions.

Model (eq. 1): z = K a + O + v with K a full 3x3 sensitivity matrix [raw/g] and O [raw].
With theta = (k11, k21, k31, k12, ..., k33, ox, oy, oz) (eq. 2, column-major K) every
window with a known acceleration a^(i) [g] gives z^(i) = H^(i) theta + v; stacking N >= 4
windows whose directions are not coplanar (eq. 3) the least-squares solution is eq. 4,
here weighted by the windows' noise (generalised LS: the minimum-variance unbiased
estimate, whose covariance (H^T W H)^-1 is the Cramér–Rao bound, ``crlb.crlb_lab``).

The six-position session (each face perpendicular to gravity in turn) is found without
markers: quasi-static windows from the detector are classified by direction and matched to
the faces ±x, ±y, ±z. Convention: face "+z" is the posture in which the sensor reads
a = (0, 0, +1) g, i.e. its +z axis points up; raw values grow with acceleration along
each axis (positive diagonal of K), as for the ADXL210 duty cycle.

The frame of the result (the orthogonal polar factor of K) is what in-use "12" holds
(``inuse12.py``, docs/twelve-parameters.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage

from ..calibration import Calibration
from ..crlb import BRAGGE_NAMES, bragge_H
from ..detectors import detect
from ..pipeline import CalibrationReport
from ..windows import WindowSet, validate_windows
from .start import bootstrap

FACES = ("+x", "-x", "+y", "-y", "+z", "-z")
FACE_DIRECTIONS = {f: (1.0 if f[0] == "+" else -1.0) * np.eye(3)["xyz".index(f[1])] for f in FACES}
MAX_TILT_DEG = 15.0  # a window further than this from every face normal is not a face (transitions, edges)
MERGE_TOL_DEG = 5.0  # windows of one face closer than this are one attitude (a hold split, or put down again)
PLACEMENT_DEG = 1.0  # RMS tilt [deg] of a face against the horizontal, per axis: hand placement on a flat table


@dataclass
class FaceHold:
    """One face of the six-position session: the pooled windows that held it."""

    face: str
    direction: np.ndarray  # (3,) the known acceleration [g]
    mean: np.ndarray  # (3,) pooled raw mean
    cov_of_mean: np.ndarray  # (3, 3) [raw^2]
    n: int  # samples
    windows: list[int]  # indices into the WindowSet
    t_start: float
    t_end: float
    tilt_deg: float  # angle between the data's direction and the face normal (coarse, before the fit)


def _window_times(ws: WindowSet, idx: list[int]) -> tuple[float, float]:
    return float(np.min(ws.t[idx])), float(np.max(ws.t[idx]))


def _coarse_directions(ws: WindowSet) -> np.ndarray:
    """Unit directions of the window means without any calibration: centre = per-axis median of the
    distinct postures (for six faces every axis is at 0 g in four of them, so the median is its zero-g
    level even with a face missing), scale = largest excursion from it per axis."""
    X = ws.mean
    half = np.maximum((X.max(axis=0) - X.min(axis=0)) / 2, 1e-12)
    if len(X) > 1:
        labels = fcluster(linkage(X / half, "average"), t=0.5, criterion="distance")
        centres = np.array([X[labels == k].mean(axis=0) for k in np.unique(labels)])
    else:
        centres = X
    c = np.median(centres, axis=0)
    scale = np.max(np.abs(centres - c), axis=0)
    ok = scale > 0.3 * scale.max()  # an axis with no face held only shows cross-axis excursions
    scale = np.where(ok, scale, np.median(scale[ok]) if ok.any() else 1.0)
    u = (X - c) / scale
    return u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)


def find_faces(ws: WindowSet, *, to_g: Calibration | None = None, max_tilt_deg: float = MAX_TILT_DEG,
               merge_tol_deg: float = MERGE_TOL_DEG, require: tuple[str, ...] = FACES) -> tuple[list[FaceHold], list[int], list[str]]:
    """Match quasi-static windows to the six faces.

    Returns (faces in FACES order, indices of windows that are no face, notes). Raises ValueError
    naming the face when a required face is missing, or held at two attitudes (its windows form
    separate clusters more than ``merge_tol_deg`` apart). Windows of one face within ``merge_tol_deg``
    of each other are merged (a long hold split by the detector, or the face put down twice the
    same way). ``to_g``: an approximate calibration to classify with (default: from the data)."""
    if len(ws) == 0:
        raise ValueError("no quasi-static windows in the lab session: hold each of the six faces still for a few seconds")
    if to_g is not None:
        a = to_g.apply(ws.mean)
        u = a / np.linalg.norm(a, axis=1, keepdims=True)
    else:
        u = _coarse_directions(ws)
    axis = np.argmax(np.abs(u), axis=1)
    sign = np.sign(u[np.arange(len(u)), axis])
    tilt = np.degrees(np.arccos(np.clip(np.abs(u[np.arange(len(u)), axis]), -1, 1)))
    names = np.array([("+" if s > 0 else "-") + "xyz"[k] for s, k in zip(sign, axis)])
    is_face = tilt <= max_tilt_deg
    notes: list[str] = []
    holds: list[FaceHold] = []
    problems: list[str] = []
    for f in FACES:
        idx = np.flatnonzero(is_face & (names == f))
        if idx.size == 0:
            if f in require:
                problems.append(f"face {f} missing")
            continue
        if idx.size > 1:
            labels = fcluster(linkage(u[idx], "single"), t=2 * math.sin(math.radians(merge_tol_deg) / 2),
                              criterion="distance")
        else:
            labels = np.ones(1, dtype=int)
        groups = [idx[labels == k].tolist() for k in np.unique(labels)]
        if len(groups) > 1:
            cents = [u[g].mean(axis=0) for g in groups]
            apart = max(math.degrees(math.acos(np.clip(ci @ cj / np.linalg.norm(ci) / np.linalg.norm(cj), -1, 1)))
                        for i, ci in enumerate(cents) for cj in cents[i + 1:])
            spans = ", ".join("t = {:.1f}-{:.1f} s".format(*_window_times(ws, g)) for g in groups)
            problems.append(f"face {f} held in {len(groups)} separate window clusters up to {apart:.1f}° apart "
                            f"({spans}): hold each face at one attitude, or drop the extra hold")
            continue
        n = ws.n[idx]
        N = float(n.sum())
        mean = (n[:, None] * ws.mean[idx]).sum(axis=0) / N
        cov = (n[:, None, None] * ws.cov[idx]).sum(axis=0) / N**2  # covariance of the pooled mean
        t0, t1 = _window_times(ws, idx.tolist())
        tl = float(np.degrees(np.arccos(np.clip(np.abs(u[idx].mean(axis=0) @ FACE_DIRECTIONS[f])
                                                / np.linalg.norm(u[idx].mean(axis=0)), -1, 1))))
        holds.append(FaceHold(f, FACE_DIRECTIONS[f].copy(), mean, cov, int(N), idx.tolist(), t0, t1, tl))
        if idx.size > 1:
            notes.append(f"face {f}: {idx.size} windows merged (same attitude within {merge_tol_deg:g}°)")
    if problems:
        found = [h.face for h in holds]
        raise ValueError("; ".join(problems) + f" (faces found: {', '.join(found) or 'none'}; "
                         f"{int((~is_face).sum())} window(s) near no face)")
    others = np.flatnonzero(~is_face).tolist()
    if others:
        notes.append(f"{len(others)} window(s) more than {max_tilt_deg:g}° from every face: not used for the fit "
                     f"(held-out check)")
    return holds, others, notes


def bragge_fit(directions: np.ndarray, means: np.ndarray, cov_of_mean: np.ndarray | None = None, *,
               placement_deg: float = 0.0) -> Calibration:
    """All 12 parameters by (weighted) least squares from known accelerations, eq. 2-4.

    directions (N, 3) [g]; means (N, 3) raw; cov_of_mean (N, 3, 3) [raw^2] or None (ordinary LS, eq. 4,
    noise from the residuals). ``placement_deg``: RMS error [deg per axis] of the "known" directions
    (a face tilted by d moves the mean by K d with d perpendicular to a): added to each window's
    covariance as K (I - a a^T) K^T d^2, because a pair of opposite faces tilted differently is absorbed
    into the cross-axis terms without leaving any residual. Covariance: (H^T W H)^-1, scaled by the
    reduced chi-square when that exceeds 1."""
    a = np.asarray(directions, dtype=float).reshape(-1, 3)
    z = np.asarray(means, dtype=float).reshape(-1, 3)
    n = a.shape[0]
    if z.shape[0] != n:
        raise ValueError(f"{n} directions but {z.shape[0]} window means")
    bad = [name for name, v in (("directions", a), ("window means", z), ("covariances", cov_of_mean))
           if v is not None and not np.all(np.isfinite(v))]
    if bad:  # the SVD below (LAPACK) may loop forever on a NaN
        raise ValueError(f"the {' and '.join(bad)} hold NaN/inf values: Bragge's fit needs finite ones")
    if n < 4:
        raise ValueError(f"Bragge's lab calibration has 12 parameters and needs N >= 4 windows with known, "
                         f"non-coplanar directions; got {n}")
    aug = np.column_stack([a, np.ones(n)])
    sv = np.linalg.svd(aug, compute_uv=False)
    if sv[-1] < 1e-6 * sv[0]:
        raise ValueError(f"the {n} known directions are coplanar (or repeated): K and O are not separable "
                         f"(singular values of [a 1]: {np.array2string(sv, precision=3)}); use at least 4 postures "
                         f"not in one plane, e.g. the six faces")
    d2 = math.radians(placement_deg) ** 2
    # a face tilted by d (rms d per perpendicular axis) reads a.e = cos|d| ~ 1 - |d|^2/2 along its normal,
    # on average 1 - d^2: the expected known direction is shortened by that (0.3 mg at 1 deg, not negligible)
    H = bragge_H(a * (1.0 - d2))
    zz = z.reshape(-1)
    if cov_of_mean is None:
        W = np.eye(3 * n)
    else:
        C = np.asarray(cov_of_mean, dtype=float).reshape(n, 3, 3)
        W = np.zeros((3 * n, 3 * n))
        for i, Ci in enumerate(C):
            W[3 * i:3 * i + 3, 3 * i:3 * i + 3] = np.linalg.inv(Ci)
    F = H.T @ W @ H
    theta = np.linalg.solve(F, H.T @ W @ zz)  # eq. 4, weighted
    if placement_deg > 0:  # second pass: the tilt term needs K; the estimate is good to far better than 1 %
        if cov_of_mean is None:
            raise ValueError("placement_deg needs the windows' covariances")
        K1 = theta[:9].reshape(3, 3, order="F")
        W = np.zeros((3 * n, 3 * n))
        for i, Ci in enumerate(C):
            E = np.outer(a[i], a[i]) / (a[i] @ a[i])
            tilt_cov = d2 * (np.eye(3) - E) + d2 * d2 * E  # perpendicular shift; spread of the cosine along a
            W[3 * i:3 * i + 3, 3 * i:3 * i + 3] = np.linalg.inv(Ci + K1 @ tilt_cov @ K1.T)
        F = H.T @ W @ H
        theta = np.linalg.solve(F, H.T @ W @ zz)
    r = zz - H @ theta
    chi2 = float(r @ W @ r)
    dof = 3 * n - 12
    cov = np.linalg.inv(F)
    scale = 1.0
    if cov_of_mean is None:
        scale = chi2 / dof if dof > 0 else math.nan
    elif dof > 0 and chi2 / dof > 1.0:
        scale = chi2 / dof  # Birge ratio
    cov = cov * scale
    K = theta[:9].reshape(3, 3, order="F")
    o = theta[9:]
    return Calibration(model="12", offset=o, sensitivity=K, covariance=cov, param_names=list(BRAGGE_NAMES),
                       n_windows=n, converged=True, observable=True,
                       metadata={"estimator": "bragge", "chi2": chi2, "dof": dof, "placement_deg": float(placement_deg),
                                 "reduced_chi2": chi2 / dof if dof > 0 else None, "cov_scale": scale})


@dataclass
class LabReport(CalibrationReport):
    """Result of ``calibrate_lab``: a CalibrationReport (same ``to_json_dict`` keys as the in-use
    ``gravcal calibrate --json``, model "12") plus the faces. heldout_rms_mg: leave-one-face-out vector
    error of the left-out face [mg]; insample_rms_mg: vector error of the fitted faces [mg]."""

    faces: list[FaceHold] = field(default_factory=list)
    other_norm_rms_mg: float | None = None  # norm error of the windows that are no face (not fitted) [mg]

    def to_json_dict(self) -> dict[str, Any]:
        d = super().to_json_dict()
        d["heldout_scheme"] = "leave-one-face-out"
        d["faces"] = {h.face: {"t_start": h.t_start, "t_end": h.t_end, "windows": len(h.windows),
                               "tilt_deg": round(h.tilt_deg, 3)} for h in self.faces}
        d["other_windows_norm_rms_mg"] = self.other_norm_rms_mg
        return d


def _vector_errors_mg(cal: Calibration, holds: list[FaceHold]) -> np.ndarray:
    a = cal.apply(np.array([h.mean for h in holds]))
    return np.linalg.norm(a - np.array([h.direction for h in holds]), axis=1) * 1e3


def calibrate_faces(ws: WindowSet, *, to_g: Calibration | None = None, placement_deg: float = PLACEMENT_DEG,
                    **face_kw) -> LabReport:
    """Bragge fit of a WindowSet from a six-position session (faces found automatically)."""
    validate_windows(ws)  # a NaN/inf window: clustering and eigvalsh (LAPACK) must not see it
    holds, others, notes = find_faces(ws, to_g=to_g, **face_kw)
    dirs = np.array([h.direction for h in holds])
    means = np.array([h.mean for h in holds])
    covs = np.array([h.cov_of_mean for h in holds])
    if np.any(np.linalg.eigvalsh(covs)[:, 0] <= 0):
        raise ValueError("a face window has a singular sample covariance (constant or quantised-flat signal): "
                         "cannot weight it; record with noise or longer holds")
    cal = bragge_fit(dirs, means, covs, placement_deg=placement_deg)
    ins = float(np.sqrt(np.mean(_vector_errors_mg(cal, holds) ** 2)))
    held: list[float] = []
    for i in range(len(holds)):  # leave one face out: 5 faces still determine all 12 (a column each)
        keep = [j for j in range(len(holds)) if j != i]
        try:
            c = bragge_fit(dirs[keep], means[keep], covs[keep], placement_deg=placement_deg)
        except (ValueError, np.linalg.LinAlgError):
            continue
        held.append(float(_vector_errors_mg(c, [holds[i]])[0]))
    heldout = float(np.sqrt(np.mean(np.square(held)))) if held else None
    other = None
    if others:
        r = 1.0 - np.linalg.norm(cal.apply(ws.mean[others]), axis=1)
        other = float(np.sqrt(np.mean(r * r)) * 1e3)
    if cal.metadata["cov_scale"] > 1.0:
        notes.append(f"reduced chi² {cal.metadata['reduced_chi2']:.3g} > 1: the faces were not exactly perpendicular "
                     f"to gravity (or noise is correlated); covariance scaled by it")
    tilts = {h.face: h.tilt_deg for h in holds}
    worst = max(tilts, key=tilts.get)
    notes.append(f"faces matched without markers; largest coarse tilt {tilts[worst]:.2f}° ({worst})")
    cal.message = "; ".join(notes)
    cal.metadata.update({"faces": {h.face: h.windows for h in holds}, "heldout_rms_mg": heldout,
                         "insample_rms_mg": ins})
    order = {"model": "12",
             "reason": (f"lab session (Bragge): faces {', '.join(h.face for h in holds)} found without markers in "
                        f"{len(ws)} windows; all 12 parameters from the known directions (eq. 2-4), "
                        f"leave-one-face-out error {'n/a' if heldout is None else f'{heldout:.3g} mg'}"),
             "evidence": {"faces": {h.face: len(h.windows) for h in holds}, "windows_not_on_a_face": len(others),
                          "reduced_chi2": cal.metadata["reduced_chi2"], "placement_deg": placement_deg}}
    return LabReport(calibration=cal, windows=ws, heldout_rms_mg=math.nan if heldout is None else heldout,
                     insample_rms_mg=ins, n_windows=len(ws), notes=notes, order=order, faces=holds,
                     other_norm_rms_mg=other)


def _isotropic_scale(raw: np.ndarray) -> Calibration:
    """Fallback raw -> g for the detector's threshold: centre and half-range of the recording (a
    six-position session spans -1..+1 g on every axis)."""
    lo, hi = np.nanpercentile(raw, [1, 99], axis=0)
    s = float(np.median((hi - lo) / 2))
    if not s > 0:
        raise ValueError("the recording is constant: no postures to calibrate from")
    return Calibration("scale", (hi + lo) / 2, np.eye(3) * s)


def calibrate_lab(t: np.ndarray, raw: np.ndarray, *, fs: float | None = None, detector: str = "variance",
                  to_g: Calibration | None = None, max_tilt_deg: float = MAX_TILT_DEG,
                  merge_tol_deg: float = MERGE_TOL_DEG, placement_deg: float = PLACEMENT_DEG,
                  **detect_kw: Any) -> LabReport:
    """``gravcal calibrate FILE --lab``: detect the quasi-static windows of a six-position session
    (t [s], raw (N, 3) triad in raw units), match them to the faces and fit all 12 parameters.

    ``to_g``: an approximate calibration for the detector's threshold in g and for classifying
    (default: the scale-free ``bootstrap`` of the recording). ``detector`` defaults to the
    moving-variance detector: turning the box from face to face by hand is a rotation that leaves the
    norm (all Lötters' detector looks at, eq. 1) nearly unchanged, but moves every axis."""
    t = np.asarray(t, dtype=float)
    raw = np.asarray(raw, dtype=float)
    if raw.ndim != 2 or raw.shape[1] != 3 or raw.shape[0] != t.shape[0]:
        raise ValueError(f"raw must be (N, 3) with N = len(t) = {t.shape[0]}, got {raw.shape}")
    det_to_g = to_g
    if det_to_g is None:
        try:
            det_to_g = bootstrap(t, raw, fs)
            if det_to_g.metadata.get("fallback"):  # no ellipsoid from the data (e.g. 7 postures, one off-face):
                det_to_g = _isotropic_scale(raw)  # a six-face session spans -1..+1 g on every axis
        except ValueError:
            det_to_g = _isotropic_scale(raw)
    ws = detect(t, raw, method=detector, fs=fs, to_g=det_to_g, **detect_kw)
    return calibrate_faces(ws, to_g=to_g, max_tilt_deg=max_tilt_deg, merge_tol_deg=merge_tol_deg,
                           placement_deg=placement_deg)
