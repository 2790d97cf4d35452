"""Starting points for the Lötters estimator without a pre-calibration.

Lötters et al. (1998) linearise eq. 8 around a previous estimate that, for the first
estimation, comes from a laboratory pre-calibration (their Fig. 1, ref. [9]). gravcal
replaces it with a closed-form fit of the quasi-static window means to an ellipsoid
(eq. 4: the static outputs lie on an ellipsoid centred at the offsets with semi-axes s·1 g):

- :func:`ellipsoid_fit` — linear least squares on the algebraic ellipsoid equation,
  iteratively reweighted (Tukey bisquare on the norm residual in g) so that a few windows
  that were not really static do not wreck it;
- :func:`bootstrap` — raw data in UNKNOWN units (counts, volts, g, m/s²): still segments
  from the data's own noise floor, then ellipsoid_fit, falling back to an isotropic scale.

Results are Calibrations with model "start" (metadata says how they were obtained);
they are starts for the estimator, not final results.
"""
from __future__ import annotations

import numpy as np

from ..calibration import Calibration
from ..detectors import MovingVarianceDetector, estimate_fs
from ..model.datasheet import SENS_LIMITS, SENS_TYP
from ..windows import WindowSet
from .consider import with_held_uncertainty

MIN_WINDOWS = {False: 6, True: 9}  # unknowns of the axis-aligned / general quadric
MIN_RESIDUAL_DOF = 3  # kept windows beyond the unknowns for the fit to state its own uncertainty
MIN_CAP_DEG = 20.0  # refuse when every window is within this angle of one direction (Lötters θ)
MAX_COND = 1e8  # condition number of the (normalised) design matrix
HUBER_K, HUBER_ITERS = 1.345, 3  # Huber weights for the first iterations
TUKEY_C = 4.685  # bisquare tuning constant (95 % efficiency under Gaussian residuals)
SIGMA_FLOOR_G = 1e-4  # robust-scale floor [g]: never reject on residuals below ~0.5 mg
MAX_OFFSET_STD_G = 0.05  # refuse when an offset is this uncertain [g] ...
MAX_SENS_REL_STD = 0.05  # ... or a sensitivity entry this uncertain (relative): not observable
# The isotropic fallback assumes equal per-axis gains, for a sensor of unknown make. A MEMS part's gain
# may sit anywhere within +-20 % of its typical value (the ADXL210's 0.032-0.048 duty/g around 0.040,
# core/model/datasheet.py, is such a spread), and the axes may come from different dies. Stating the
# full half-range as one std keeps a fit that holds these gains honest even for a worst case and for
# the median norm's own bias (offset assumed 0).
ISOTROPIC_SENS_REL_STD = (SENS_LIMITS[1] - SENS_LIMITS[0]) / 2.0 / SENS_TYP  # 0.20
# A device file's own nominal scale (1 for a file in g, the counts per g its header states): the
# residual per-axis gain error about it is assumed (1 sigma; not a figure the file states) 1 % for a file
# the device already scaled to g with its own calibration, 3 % for raw counts at the header's nominal
# scale (a MEMS part's gain spread; the ISM_Enabled Link's still norm reads 266 counts for its nominal
# 256). A fit that holds the sensitivities there carries this into its offsets' uncertainty.
# A device's own per-axis calibration of its raw counts (an .agdc's calibration.json) is held at the same 3 %:
# the ActiGraph chamber recording (CPW1C48210013) reads 1.032 g along gravity under its own calibration,
# a 3 % error of the gain or the offset along gravity that the file's figures do not state.
DEVICE_SENS_REL_STD = {"g": 0.01, "counts": 0.03, "device_calibration": 0.03}
FLOOR_CHUNK = 1 << 13  # samples per piece of the noise-floor probe (its temporaries stay in the CPU cache)


def ellipsoid_fit(ws: WindowSet, *, full: bool = False, max_iter: int = 20,
                  min_cap_deg: float = MIN_CAP_DEG) -> Calibration:
    """Fit raw = K a + o with |a| = 1 g to the window means ``ws.mean`` (M, 3) [raw units].

    full=False: axis-aligned ellipsoid A x² + B y² + C z² + D x + E y + F z = 1 (6 unknowns)
    → offsets and per-axis sensitivities (diagonal K). full=True: general quadric
    (x^T Q x + b·x = 1, 9 unknowns) → offsets and the symmetric K = M^(-1/2), which fixes
    the rotation that an ellipsoid cannot see.

    Raises ValueError when there are too few windows (< 6 / < 9), when they do not cover
    enough orientations (design matrix ill-conditioned, or all windows within
    ``min_cap_deg`` of one direction: the paper's θ; its Figs. 7-12 show the
    sensitivity errors growing steeply as θ shrinks; or an axis that never carries more
    than sin(min_cap_deg) g; or a linearised parameter std above 50 mg / 5 %), or when
    the fit is not an ellipsoid.
    Robustness: Huber weights for 3 iterations, then Tukey bisquare, on the norm residual
    [g] scaled by the MAD of all residuals (floored at 0.1 mg).
    The result states its own uncertainty for fits that hold it (consider.with_held_uncertainty,
    metadata["held_covariance"], raw units²): see _raw_parameter_covariance.
    """
    mean = np.asarray(ws.mean, dtype=float).reshape(-1, 3)
    mean = mean[np.isfinite(mean).all(axis=1)]
    m = mean.shape[0]
    need = MIN_WINDOWS[bool(full)]
    if m < need:
        kind = "general" if full else "axis-aligned"
        raise ValueError(f"ellipsoid_fit ({kind}) needs at least {need} quasi-static windows, got {m}")

    # Normalise so that counts (~3e4) and g (~1) give the same conditioning.
    c0 = np.median(mean, axis=0)
    r0 = float(np.median(np.linalg.norm(mean - c0, axis=1)))
    if not r0 > 0:
        raise ValueError("orientation coverage insufficient: the window means are (nearly) all identical")
    u = (mean - c0) / r0
    design = _design(u, full)
    col = np.linalg.norm(design, axis=0)
    flat = [ax for k, ax in enumerate("xyz") if col[k] <= 1e-9 * col.max()]
    if flat:
        raise ValueError(f"orientation coverage insufficient: axis {', '.join(flat)} never varies across the windows")
    sv = np.linalg.svd(design / col, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
    if cond > MAX_COND:
        raise ValueError(f"orientation coverage insufficient: windows are nearly coplanar or collinear "
                         f"(design matrix condition number {cond:.3g} > {MAX_COND:.0e})")

    w = np.ones(m)
    o_u = K_u = None
    sigma = np.nan
    for it in range(max_iter):
        sw = np.sqrt(w)
        coef = np.linalg.lstsq(design * sw[:, None], sw, rcond=None)[0]
        o_new, K_new = _quadric_to_ellipsoid(coef, full)
        a = np.linalg.solve(K_new, (u - o_new).T).T
        r = np.linalg.norm(a, axis=1) - 1.0  # norm residual [g]
        sigma = max(1.4826 * float(np.median(np.abs(r))), SIGMA_FLOOR_G)
        if it < HUBER_ITERS:  # Huber first: a gentle start that cannot reject the good windows
            w_new = np.minimum(1.0, HUBER_K * sigma / np.maximum(np.abs(r), 1e-300))
        else:  # then Tukey bisquare: windows far off the ellipsoid get weight 0
            z = r / (TUKEY_C * sigma)
            w_new = np.where(np.abs(z) < 1, (1 - z * z) ** 2, 0.0)
        if np.count_nonzero(w_new) < need:
            raise ValueError(f"ellipsoid_fit: only {np.count_nonzero(w_new)} of {m} windows agree with a common "
                             f"ellipsoid (need {need}); the windows are not quasi-static or coverage is too poor")
        done = it >= HUBER_ITERS and o_u is not None and np.allclose(o_new, o_u, atol=1e-12) and np.allclose(K_new, K_u, atol=1e-12)
        o_u, K_u, w = o_new, K_new, w_new
        if done:
            break

    o_std_g, k_std_rel = _parameter_std(coef, design, w, sigma, full)
    offset = c0 + r0 * o_u
    K = r0 * K_u
    a = np.linalg.solve(K, (mean - offset).T).T
    used = w > 0
    cap = _cap_deg(a[used])
    if cap < min_cap_deg:
        raise ValueError(f"orientation coverage insufficient: all windows within {cap:.1f}° of one direction "
                         f"(need postures more than {min_cap_deg:.0f}° apart from their mean direction)")
    load = np.abs(a[used]).max(axis=0)  # most gravity any window puts on each axis [g]
    weak = [f"{ax} ({ld:.2f} g)" for ax, ld in zip("xyz", load) if ld < np.sin(np.radians(min_cap_deg))]
    if weak:  # e.g. pitch-only motion: the fit would explain that axis's noise with a thin ellipsoid
        raise ValueError(f"orientation coverage insufficient: axis {', '.join(weak)} never carries more than "
                         f"sin({min_cap_deg:.0f}°) = {np.sin(np.radians(min_cap_deg)):.2f} g of gravity in any window")
    bad = [f"offset {ax} ±{1e3 * sd:.0f} mg" for ax, sd in zip("xyz", o_std_g) if not sd < MAX_OFFSET_STD_G]
    bad += [f"sensitivity {name} ±{100 * sd:.0f} %" for name, sd in k_std_rel.items() if not sd < MAX_SENS_REL_STD]
    if bad:
        raise ValueError("orientation coverage insufficient: parameters not observable from these windows ("
                         + ", ".join(bad) + "); add postures that load those axes")
    resid_g = np.linalg.norm(a, axis=1) - 1.0
    names, cov_raw = _raw_parameter_covariance(coef, design, w, full, c0, r0)
    cal = Calibration(
        model="start",
        offset=offset,
        sensitivity=K,
        n_windows=int(np.count_nonzero(used)),
        converged=True,
        observable=True,
        message=f"ellipsoid fit ({'general' if full else 'axis-aligned'}) to {np.count_nonzero(used)} window means",
        metadata={
            "method": "ellipsoid_fit",
            "full": bool(full),
            "n_windows_in": int(m),
            "n_rejected": int(m - np.count_nonzero(used)),
            "rms_residual_g": float(np.sqrt(np.mean(resid_g[used] ** 2))),
            "robust_sigma_g": float(sigma),
            "cap_deg": float(cap),
            "condition_number": cond,
            "offset_std_g": o_std_g.tolist(),
            "sensitivity_rel_std": k_std_rel,
        },
    )
    kind = "general" if full else "axis-aligned"
    dof = int(np.count_nonzero(used)) - MIN_WINDOWS[bool(full)]
    if dof < MIN_RESIDUAL_DOF:
        # (nearly) an exact fit: no residual to scale its covariance (6 windows stated their gains to 0.04 %
        # while 15 % off). A start still, but held as uncertain as the equal-gain start: each gain ±20 %, each
        # offset the same fraction of 1 g
        scale = float(np.mean(np.abs(np.diag(K))))
        sd = {n: ISOTROPIC_SENS_REL_STD * (abs(float(K["xyz".index(n[2]), "xyz".index(n[2])]))
                                           if n[0] == "s" and len(n) == 3 else scale) for n in names}
        return with_held_uncertainty(cal, sd, source=f"ellipsoid fit ({kind}) with {dof} window(s) beyond its "
                                                     f"unknowns: no residual to state its uncertainty; held as an "
                                                     f"equal-gain start (±{100 * ISOTROPIC_SENS_REL_STD:.0f} %)")
    return with_held_uncertainty(cal, names=names, cov=cov_raw, source=f"ellipsoid fit ({kind}) linearised LS covariance")


def _raw_parameter_covariance(coef, design, w, full, c0, r0) -> tuple[list[str], np.ndarray]:
    """Names and covariance [raw units²] of the fitted (K, o), for a later fit that holds them.

    The quadric coefficients are a Tukey M-estimate (IRLS with the final robust weights w); their
    covariance is Huber's (Robust Statistics, 1981, eq. 7.6.5-7.6.7):
    cov(coef) = K² [sum (w e)² / (n - P)] / mean(psi')² (D^T D)^-1 over the windows kept, with
    e = D coef - 1 the algebraic residual (its scale from the data, not the floored robust sigma)
    and K = 1 + P/n var(psi')/mean(psi')²; all weights 1 gives the plain LS s² (D^T D)^-1. The
    fixed-weight sandwich was measured too small (NEES 9 vs 6 over 300 seeds): it ignores that the
    weights themselves follow the residuals. Propagated to
    raw units (offset = c0 + r0 o_u, K = r0 K_u) through the central-difference Jacobian of the
    quadric -> ellipsoid map. Axis-aligned: s_x, s_y, s_z, o_x, o_y, o_z. General (full=True):
    the whole symmetric K as well, s_x, s_y, s_z (diagonal), s_xy, s_xz, s_yz (K[i, j] = K[j, i]),
    then o_x, o_y, o_z: the names consider.with_held_uncertainty understands.
    """
    used = w > 0
    D, ww = design[used], w[used]
    n, n_p = D.shape
    e = D @ coef - 1.0  # algebraic residual, ~2 (|a| - 1) in these normalised units
    # final weights are Tukey's (1 - z²)², z = r / (TUKEY_C sigma): psi(z) ∝ w e, psi'(z) = sqrt(w) (5 sqrt(w) - 4)
    sq = np.sqrt(ww)
    dpsi = sq * (5.0 * sq - 4.0)
    mean_dpsi = float(np.mean(dpsi))
    if not mean_dpsi > 0.1:  # cannot happen with most windows near the ellipsoid; stay finite and conservative
        mean_dpsi = 0.1
    corr = 1.0 + n_p / n * float(np.var(dpsi)) / mean_dpsi ** 2  # Huber's small-sample factor
    s2 = float(np.sum((ww * e) ** 2) / max(n - n_p, 1)) * corr ** 2 / mean_dpsi ** 2
    cov_coef = s2 * np.linalg.pinv(D.T @ D)
    pairs = [(0, 0), (1, 1), (2, 2)] + ([(0, 1), (0, 2), (1, 2)] if full else [])
    names = ["s_" + ("xyz"[i] if i == j else "xyz"[i] + "xyz"[j]) for i, j in pairs] + [f"o_{a}" for a in "xyz"]

    def raw_params(c):
        o_u, K_u = _quadric_to_ellipsoid(c, full)
        return np.concatenate([[r0 * K_u[i, j] for i, j in pairs], c0 + r0 * o_u])

    jac = _central_jacobian(raw_params, coef)
    cov = jac @ cov_coef @ jac.T
    return names, 0.5 * (cov + cov.T)


def _central_jacobian(f, coef: np.ndarray) -> np.ndarray:
    """d f(coef) / d coef by central differences, one column per coefficient (step 1e-6 of its size, at
    least 1e-9): how the quadric's covariance reaches the parameters derived from it."""
    jac = []
    for j in range(coef.shape[0]):
        h = 1e-6 * max(abs(coef[j]), 1e-3)
        cp, cm = coef.copy(), coef.copy()
        cp[j] += h
        cm[j] -= h
        jac.append((f(cp) - f(cm)) / (2 * h))
    return np.column_stack(jac)


def _parameter_std(coef, design, w, sigma_g, full) -> tuple[np.ndarray, dict[str, float]]:
    """Linearised std of the offsets [g] and of K's entries (relative to K's mean diagonal).

    The algebraic residual u^T Q u + b·u - 1 ≈ |a|² - 1 ≈ 2 (|a| - 1), so its std is 2 sigma_g;
    cov(coef) = (2 sigma)² (D^T W D)^-1, propagated through the quadric -> (o, K) map by
    central differences.
    """
    dw = design[w > 0] * np.sqrt(w[w > 0])[:, None]
    cov = (2.0 * sigma_g) ** 2 * np.linalg.pinv(dw.T @ dw)
    o0, K0 = _quadric_to_ellipsoid(coef, full)
    scale = float(np.mean(np.diag(K0)))
    jac = _central_jacobian(lambda c: np.concatenate(_quadric_to_ellipsoid(c, full), axis=None), coef) / scale
    sd = np.sqrt(np.clip(np.einsum("ij,jk,ik->i", jac, cov, jac), 0.0, None))
    names = [(i, j) for i in range(3) for j in range(3) if (full and j >= i) or i == j]
    return sd[:3], {("xyz"[i] + "xyz"[j] if i != j else "xyz"[i]): float(sd[3 + 3 * i + j]) for i, j in names}


def _design(u: np.ndarray, full: bool) -> np.ndarray:
    x, y, z = u.T
    if not full:
        return np.column_stack([x * x, y * y, z * z, x, y, z])
    return np.column_stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, x, y, z])


def _quadric_to_ellipsoid(coef: np.ndarray, full: bool) -> tuple[np.ndarray, np.ndarray]:
    """Centre o and K with (u - o)^T (K K^T)^-1 (u - o) = 1 from the quadric u^T Q u + b·u = 1."""
    if full:
        qa, qb, qc, qd, qe, qf = coef[:6]
        Q = np.array([[qa, qd, qe], [qd, qb, qf], [qe, qf, qc]])
        b = coef[6:]
    else:
        Q = np.diag(coef[:3])
        b = coef[3:]
    try:
        o = -0.5 * np.linalg.solve(Q, b)
    except np.linalg.LinAlgError:
        raise ValueError("orientation coverage insufficient: the fitted quadric is degenerate") from None
    gain = 1.0 + o @ Q @ o  # (u-o)^T Q (u-o) = gain
    evals, evecs = np.linalg.eigh(Q / gain) if gain > 0 else (np.array([-1.0]), None)
    if not np.all(evals > 0):
        raise ValueError("orientation coverage insufficient: the window means do not lie on an ellipsoid "
                         "(fitted quadric is not positive definite)")
    K = (evecs * (1.0 / np.sqrt(evals))) @ evecs.T  # symmetric M^(-1/2); diagonal when Q is
    if not full:
        K = np.diag(np.diag(K))
    return o, K


def _cap_deg(a: np.ndarray) -> float:
    """The largest angle [deg] between a window's direction and the mean direction."""
    d = a / np.linalg.norm(a, axis=1, keepdims=True)
    c = d.mean(axis=0)
    nc = np.linalg.norm(c)
    if nc < 1e-9:  # directions all around: full coverage
        return 180.0
    cosang = np.clip(d @ (c / nc), -1.0, 1.0)
    return float(np.degrees(np.arccos(cosang.min())))


def bootstrap(t, raw, fs: float | None = None, *, noise_factor: float = 4.0, percentile: float = 2.0,
              window_s: float = 1.0, floor_window_s: float = 0.25, min_duration_s: float = 2.0) -> Calibration:
    """A scale-free start from raw triad data (N, 3) in unknown units.

    Still segments: per-axis moving std over ``window_s`` (MovingVarianceDetector with
    to_g=None, so in raw units) below ``noise_factor`` × the data's own noise floor: the
    ``percentile``-th percentile of the moving std over short ``floor_window_s`` windows
    (max over axes; at least half the quantisation step, for data so clean that the
    percentile is 0). Short windows fit inside short pauses, so the floor is the sensor
    noise even when the data are mostly movement; for white noise, the 2nd percentile
    of a 25-sample std is ≈ 0.7 σ, so the threshold is ≈ 2.8 σ while a still 1 s window
    reads σ ± 7 %. Motion of constant intensity throughout cannot be told from noise by
    any scale-free rule: such data give one "still" window and the fallback below. Their means go to
    ellipsoid_fit (axis-aligned). If orientation coverage is too poor for per-axis
    sensitivities, the result has an isotropic sensitivity equal to the median norm of
    the still means, zero offset, observable=False and a message saying so; it states a held
    uncertainty of ISOTROPIC_SENS_REL_STD (20 %) of that scale on each of s_x, s_y, s_z, so an
    offsets-only fit from it reports how much the assumed-equal gains can bias its offsets.
    Raises ValueError if the data have no still segment at all.
    """
    raw = np.asarray(raw, dtype=float)
    t = np.asarray(t, dtype=float).reshape(-1)
    if raw.ndim != 2 or raw.shape[1] != 3 or raw.shape[0] != t.shape[0]:
        raise ValueError(f"bootstrap needs t (N,) and raw (N, 3); got {t.shape} and {raw.shape}")
    fs = estimate_fs(t) if fs is None else float(fs)
    floor = _noise_floor(t, raw, fs, floor_window_s, percentile)
    threshold = noise_factor * floor
    det = MovingVarianceDetector(fs, window_s=window_s, threshold_g=threshold, min_duration_s=min_duration_s,
                                 max_duration_s=None, guard_s=0.5 * window_s)
    windows = det.update(t, raw) + det.flush()
    if not windows:
        raise ValueError(f"bootstrap: no still segment of at least {min_duration_s} s found "
                         f"(noise floor {floor:.3g} raw units, threshold {threshold:.3g})")
    ws = WindowSet.from_windows(windows)
    meta = {"method": "bootstrap", "noise_floor_raw": floor, "threshold_raw": threshold, "fs": fs,
            "n_still_windows": len(ws), "detector": "variance"}
    try:
        cal = ellipsoid_fit(ws)
    except ValueError as exc:
        scale = float(np.median(np.linalg.norm(ws.mean, axis=1)))
        if not scale > 10.0 * floor:  # gravity must stand far above the noise, whatever the units
            raise ValueError(f"bootstrap: no scale can be determined: the still means (median norm {scale:.3g}) "
                             f"do not stand out of the noise floor ({floor:.3g}); is this accelerometer data? "
                             f"({exc})") from exc
        iso = Calibration(
            model="start", offset=np.zeros(3), sensitivity=scale * np.eye(3), n_windows=len(ws), converged=False,
            observable=False,
            message=(f"only an isotropic scale could be determined (sensitivities only assumed equal, "
                     f"±{100 * ISOTROPIC_SENS_REL_STD:.0f} % each; offset assumed 0): {exc}"),
            metadata={**meta, "fallback": "isotropic_median_norm", "reason": str(exc)},
        )
        sd = ISOTROPIC_SENS_REL_STD * scale
        return with_held_uncertainty(iso, {f"s_{a}": sd for a in "xyz"},
                                     source=f"a sensor of unknown make, its per-axis gains assumed equal "
                                            f"within ±{100 * ISOTROPIC_SENS_REL_STD:.0f} %")
    cal.metadata = {**meta, **cal.metadata, "method": "bootstrap+ellipsoid_fit"}
    cal.message = f"bootstrap from {len(ws)} still segments; " + cal.message
    return cal


def device_start(scale: float, device: str, units: str) -> Calibration:
    """The start for a device file: its own nominal scale (``scale`` [units per g] on every axis, offsets 0),
    stating a per-axis gain uncertainty of DEVICE_SENS_REL_STD[units] (assumed) for fits that hold the
    sensitivities."""
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"a device's nominal scale must be a positive number, got {scale!r}")
    rel = DEVICE_SENS_REL_STD["g" if units == "g" else "counts"]
    what = "g" if units == "g" else f"{scale:g} {units} per g"
    cal = Calibration(model="nominal", offset=np.zeros(3), sensitivity=scale * np.eye(3), converged=True, observable=True,
                      message=f"the {device}'s nominal scale ({what})",
                      metadata={"method": "device_nominal", "device": device, "scale": float(scale), "units": units})
    return with_held_uncertainty(cal, {f"s_{a}": rel * scale for a in "xyz"},
                                 source=f"the {device}'s nominal scale, per-axis gains assumed within ±{100 * rel:.0f} %")


def device_calibration_start(sensitivity: np.ndarray, offset: np.ndarray, device: str, source: str) -> Calibration:
    """The start for a device file that carries its own calibration of the raw counts (K [counts per g],
    o [counts]): held sensitivities with a per-axis gain uncertainty of DEVICE_SENS_REL_STD["device_calibration"]
    (assumed) for fits that hold them."""
    K = np.asarray(sensitivity, dtype=float).reshape(3, 3)
    o = np.asarray(offset, dtype=float).reshape(3)
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(o)) and np.all(np.diag(K) > 0)):
        raise ValueError(f"the {device}'s own calibration is not usable (non-finite or non-positive gains)")
    rel = DEVICE_SENS_REL_STD["device_calibration"]
    cal = Calibration(model="nominal", offset=o, sensitivity=K, converged=True, observable=True,
                      message=f"the {device}'s own calibration ({source})",
                      metadata={"method": "device_nominal", "device": device, "source": source, "units": "counts"})
    return with_held_uncertainty(cal, {f"s_{a}": rel * K[i, i] for i, a in enumerate("xyz")},
                                 source=f"the {device}'s own calibration ({source}), per-axis gains assumed within "
                                        f"±{100 * rel:.0f} %")


def _noise_floor(t, raw, fs, window_s, percentile) -> float:
    """Noise floor [raw units]: a low percentile of the max-over-axes moving std."""
    # only the detection signal is used: a threshold that only an exactly constant signal is below spares
    # the probe the work of building still windows (the signal does not depend on the threshold)
    probe = MovingVarianceDetector(fs, window_s=window_s, threshold_g=np.finfo(float).tiny, max_duration_s=None)
    # in cache-sized pieces (the probe's moving sums carry over bit for bit; a minimum is exact): on the
    # whole segment at once, each of ~20 temporaries of N x 6 floats is fresh memory, page faults included
    parts, quantum = [], np.inf
    for i in range(0, t.shape[0], FLOOR_CHUNK):
        probe.update(t[i:i + FLOOR_CHUNK], raw[i:i + FLOOR_CHUNK])
        parts.append(probe.last_detection)
        steps = np.abs(np.diff(raw[max(i - 1, 0):i + FLOOR_CHUNK], axis=0))  # with the step into the piece
        steps = steps[np.isfinite(steps) & (steps > 0)]
        if steps.shape[0]:
            quantum = min(quantum, float(steps.min()))
    det = np.concatenate(parts) if parts else probe.last_detection
    det = det[np.isfinite(det) & (np.arange(det.shape[0]) >= probe.w - 1)]
    if det.shape[0] == 0:
        raise ValueError(f"bootstrap: fewer than {probe.w} finite samples; need at least one {window_s} s window")
    floor = float(np.percentile(det, percentile))
    floor = max(floor, 0.5 * quantum if np.isfinite(quantum) else 0.0)
    if not floor > 0:
        raise ValueError("bootstrap: the data are constant; no still/moving contrast to detect")
    return floor
