"""The peers' own model fits on GIVEN quasi-static windows (the same windows gravcal fits), their gates noted.

    skdh    CalibrateAccelerometer()._do_iterative_closest_point_fit: GGIR's g.calibrate (van Hees 2014) as
            scikit-digital-health ports it: iterative closest point on still means, per axis
            a = (y + d) s + (T - T̄) m, weights min(1/distance, 100), up to 1000 iterations. This is the
            GGIR-style fit: GGIR's own R code is the same iteration (its gates: sphere ±0.3 g, error < 10 mg).
    actipy  actipy.processing.calibrate_gravity on a frame that holds each window as 10 s of its constant
            mean (and temperature), so actipy's own 10 s windowing finds exactly these windows; its gates
            that can be opened through its arguments are (calib_cube=0, calib_min_samples=2); the 10 mg
            post-fit gate is fixed inside it, so a fit above 10 mg is declined by actipy itself.

bench/peers.py runs the same tools on the raw samples, each with its own still detection and gates, as
their users run them; this module separates the model from the detection: every tool gets the same
windows and its full model (offset, scale and, where the recording has a temperature, its temperature
term) is applied to the held-out windows. A gate a tool would have refused on is reported beside the fit.
"""
from __future__ import annotations

import time
import warnings
from types import SimpleNamespace

import numpy as np

from peers import PeerResult, actipy_frame

WINDOWS_PEERS = ("skdh", "actipy")
ACTIPY_WINDOW_S = 10.0


def skdh_fit(means_g: np.ndarray, temp_c: np.ndarray | None) -> PeerResult:
    """skdh's iterative closest-point fit on window means [nominal g] (N, 3) and temperatures [°C] (N,)."""
    from skdh.preprocessing import CalibrateAccelerometer

    y = np.asarray(means_g, dtype=float)
    T = np.zeros(len(y)) if temp_c is None else np.asarray(temp_c, dtype=float)
    store = SimpleNamespace(acc_rsd=np.zeros_like(y), acc_rm=y, tmp_rm=T)  # every window still: they are given
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        finished, d, s, m, t_mean = CalibrateAccelerometer()._do_iterative_closest_point_fit(store)
    dt = time.perf_counter() - t0
    d, s, m = np.asarray(d, float).reshape(3), np.asarray(s, float).reshape(3), np.asarray(m, float).reshape(3)
    if np.allclose(s, 1) and np.allclose(d, 0) and not finished:
        return PeerResult("skdh", False, "sphere not populated: windows must lie beyond ±0.3 g on every axis", dt)
    gate = "" if finished else "; its gate would refuse it (error after >= 10 mg or not below the error before)"
    return PeerResult("skdh", True, f"closest-point fit{gate}", dt, offset_g=-d, scale=s, matrix=np.diag(s),
                      temp_coef=m if temp_c is not None else np.zeros(3), temp_ref=float(t_mean),
                      info={"gate_passed": bool(finished)})


def actipy_fit(means_g: np.ndarray, temp_c: np.ndarray | None) -> PeerResult:
    """actipy's calibrate_gravity on the windows, each as ACTIPY_WINDOW_S s of its constant mean at 1 Hz."""
    y = np.asarray(means_g, dtype=float)
    n = int(ACTIPY_WINDOW_S)
    t = np.arange(len(y) * n, dtype=float)  # window i fills [10 i, 10 i + 10) s: one actipy 10 s window each
    frame = actipy_frame(t, np.repeat(y, n, axis=0), None if temp_c is None else np.repeat(np.asarray(temp_c, float), n))
    return run_actipy_open(frame)


def run_actipy_open(frame) -> PeerResult:
    """run_actipy with the gates its arguments control opened (cube, minimum windows)."""
    from actipy.processing import calibrate_gravity

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0 = time.perf_counter()
        _, info = calibrate_gravity(frame, calib_cube=0.0, calib_min_samples=2, return_coeffs=True)
        dt = time.perf_counter() - t0
    if not info.get("CalibOK"):
        return PeerResult("actipy", False, f"CalibOK=0: error after fit {info.get('CalibErrorAfter(mg)', float('nan')):.1f}"
                          " mg >= 10 mg (actipy's fixed gate) or no convergence", dt, info=_plain(info))
    if "CalibxIntercept" not in info:
        return PeerResult("actipy", True, "already within 10 mg: identity", dt, info=_plain(info))
    b = np.array([info[f"Calib{a}Intercept"] for a in "xyz"], float)
    s = np.array([info[f"Calib{a}Slope"] for a in "xyz"], float)
    sT = np.array([info.get(f"Calib{a}SlopeT", 0.0) for a in "xyz"], float)
    return PeerResult("actipy", True, f"fit ({info.get('CalibErrorAfter(mg)', 0):.1f} mg after)", dt, offset_g=-b / s,
                      scale=s, matrix=np.diag(s), temp_coef=sT, temp_ref=0.0, info=_plain(info))


def _plain(info: dict) -> dict:
    return {k: (float(v) if isinstance(v, (int, float, np.number)) else v) for k, v in info.items()}


def fit(name: str, means_g: np.ndarray, temp_c: np.ndarray | None) -> PeerResult:
    try:
        return {"skdh": skdh_fit, "actipy": actipy_fit}[name](means_g, temp_c)
    except MemoryError:
        raise
    except Exception as exc:  # a tool's own crash on these windows is a result (declined, with its error)
        return PeerResult(name, False, f"failed: {type(exc).__name__}: {exc}", 0.0)
