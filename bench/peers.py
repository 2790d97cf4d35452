"""The peer calibrators, each run the way its own users run it (optional: ``pip install -e .[bench]``).

    skdh    scikit-digital-health  skdh.preprocessing.CalibrateAccelerometer().predict(time=, accel=, temperature=)
                                   (van Hees 2014: sd of 10 s blocks < 13 mg = still; ±0.3 g sphere criterion;
                                   a = (y + d) s + (T - T̄) m). Its gate: at least 12 h of data (min_hours is
                                   rounded up to a multiple of 12, default 72; we pass the smallest, 12).
    actipy  actipy                 actipy.processing.calibrate_gravity(DataFrame x,y,z[,temperature] in g with a
                                   DatetimeIndex) (van Hees 2014: 10 s windows, std < 15 mg, >= 50 still
                                   windows, ±0.3 g cube; a = b + s y + sT T). actipy needs a Java runtime
                                   (its device readers run in Java), so it counts as unavailable without one.
    imucal  imucal                 imucal.FerrarisCalibration(grav=1).compute(ferraris_regions_from_section_list(...))
                                   (Ferraris 1995: six annotated static faces + three 360° turns; a = R⁻¹K⁻¹(y - b)).
                                   It needs the annotated section list and the gyro: it applies to imucal_ferraris.

Every adapter takes the same input: t [s], acceleration in NOMINAL g (the recording's raw units
through its datasheet scale: the peers expect g), optional temperature [°C]. The result is put in
one convention (``PeerResult``)::

    a = matrix @ (y - offset_g) + temp_coef * (T - temp_ref)        y: acceleration in nominal g

A peer that declines (too few still points, sphere not populated, too little data) is a
``PeerResult`` with ok=False and the peer's own reason in ``message``; it never raises.
"""
from __future__ import annotations

import importlib
import shutil
import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

PEERS: tuple[str, ...] = ("skdh", "actipy", "imucal")
MODULES = {"skdh": "skdh.preprocessing", "actipy": "actipy.processing", "imucal": "imucal"}
PYPI = {"skdh": "scikit-digital-health", "actipy": "actipy", "imucal": "imucal"}
INSTALL_HINT = "pip install -e .[bench]"
SKDH_MIN_HOURS = 12  # the smallest value CalibrateAccelerometer accepts (it rounds up to a multiple of 12)
FERRARIS_SECTIONS = ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a", "x_rot", "y_rot", "z_rot")


@dataclass
class PeerResult:
    name: str
    ok: bool  # the peer produced a calibration (False: declined or failed; see message)
    message: str  # the peer's own status / reason
    seconds: float  # wall time of the peer's calibration call
    offset_g: np.ndarray = field(default_factory=lambda: np.zeros(3))  # reading at zero acceleration [nominal g]
    scale: np.ndarray = field(default_factory=lambda: np.ones(3))  # diag of matrix [g per nominal g]
    matrix: np.ndarray = field(default_factory=lambda: np.eye(3))  # full correction (3, 3)
    temp_coef: np.ndarray = field(default_factory=lambda: np.zeros(3))  # [g/°C]
    temp_ref: float = 0.0  # [°C]
    info: dict[str, Any] = field(default_factory=dict)  # the peer's raw figures (JSON-able)

    def apply(self, acc_g: np.ndarray, temp_c: np.ndarray | float | None = None) -> np.ndarray:
        """Calibrated acceleration [g] of rows (N, 3) in nominal g (identity when not ok: what the peer hands back)."""
        y = np.asarray(acc_g, dtype=float).reshape(-1, 3)
        if not self.ok:
            return y.copy()
        a = (y - self.offset_g) @ self.matrix.T
        if np.any(self.temp_coef != 0):
            if temp_c is None:
                raise ValueError(f"{self.name}: this calibration has temperature terms; pass temp_c")
            T = np.broadcast_to(np.asarray(temp_c, dtype=float), (y.shape[0],))
            a = a + (T - self.temp_ref)[:, None] * self.temp_coef
        return a

    @property
    def sensitivity_g(self) -> np.ndarray:
        """Nominal g read per true g (3, 3): the inverse of ``matrix`` (gravcal's ``sensitivity`` in nominal g)."""
        return np.linalg.inv(self.matrix)

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "ok": self.ok, "message": self.message, "seconds": self.seconds,
                "offset_g": self.offset_g.tolist(), "scale": self.scale.tolist(), "matrix": self.matrix.tolist(),
                "temp_coef": self.temp_coef.tolist(), "temp_ref": self.temp_ref, "info": self.info}


def _import(name: str):
    return importlib.import_module(MODULES[name])


def available(only: str | None = None) -> dict[str, str | None]:
    """Peer name -> None if usable, else why not and how to fix it. ``only``: check (import) just
    that peer, so a measured child does not pay for importing the others."""
    out: dict[str, str | None] = {}
    for name in PEERS if only is None else (only,):
        try:
            _import(name)
        except ImportError as exc:
            out[name] = f"not installed ({PYPI[name]}: {exc}): {INSTALL_HINT}"
            continue
        except Exception as exc:  # a broken install: say so, do not crash the bench
            out[name] = f"import failed ({type(exc).__name__}: {exc}): reinstall with {INSTALL_HINT}"
            continue
        if name == "actipy" and shutil.which("java") is None:
            out[name] = "needs a Java runtime (java not on PATH): install one, e.g. apt-get install default-jre-headless"
            continue
        out[name] = None
    return out


def versions() -> dict[str, str | None]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for name in PEERS:
        try:
            out[PYPI[name]] = version(PYPI[name])
        except PackageNotFoundError:
            out[PYPI[name]] = None
    return out


def _declined(name: str, message: str, seconds: float = 0.0, **info: Any) -> PeerResult:
    return PeerResult(name, False, message, seconds, info=info)


def _warning_text(caught: list) -> str:
    return "; ".join(str(w.message) for w in caught)


def _skdh(t_s, acc_g, fs_hz, temp_c, **_) -> PeerResult:
    from skdh.preprocessing import CalibrateAccelerometer

    cal = CalibrateAccelerometer(min_hours=SKDH_MIN_HOURS)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t0 = time.perf_counter()
        # apply=True, as its users run it (the calibrated acceleration is what they keep); it also
        # gives T̄_c, the mean temperature of its still blocks, which it does not return
        res = cal.predict(time=t_s, accel=acc_g, fs=fs_hz, apply=True, temperature=temp_c)
        dt = time.perf_counter() - t0
    text = _warning_text(caught)
    if not res or "offset" not in res:
        return _declined("skdh", text or "no calibration returned", dt)
    if "insufficient non-movement" in text or "Recalibration not done" in text:
        return _declined("skdh", text, dt)
    d = np.asarray(res["offset"], dtype=float).reshape(3)
    s = np.asarray(res["scale"], dtype=float).reshape(3)
    m = np.asarray(res["temperature scale"], dtype=float).reshape(3)
    t_ref = 0.0
    if temp_c is not None and np.any(m != 0):
        # a = (y + d) s + (T - T̄_c) m  at the first sample, on the axis with the largest m
        k = int(np.argmax(np.abs(m)))
        a0 = np.asarray(res["accel"], dtype=float)[0]
        t_ref = float(temp_c[0] - (a0[k] - (acc_g[0, k] + d[k]) * s[k]) / m[k])
    return PeerResult("skdh", True, text or "calibrated", dt, offset_g=-d, scale=s, matrix=np.diag(s), temp_coef=m,
                      temp_ref=t_ref, info={"offset": d.tolist(), "scale": s.tolist(), "temperature_scale": m.tolist(),
                                            "temperature_mean": t_ref})


def actipy_frame(t_s: np.ndarray, acc_g: np.ndarray, temp_c: np.ndarray | None = None):
    """What actipy's readers hand their users: x, y, z [g] (and temperature) on a DatetimeIndex."""
    import pandas as pd

    # integer nanoseconds (a float product rounds a week's stamps), and one (N, 3) block not copied:
    # a 7-day recording would otherwise be held twice (+1.4 GB)
    idx = pd.DatetimeIndex(np.rint(np.asarray(t_s, dtype=float) * 1e9).astype("int64").view("datetime64[ns]"),
                           name="time")
    df = pd.DataFrame(acc_g, columns=["x", "y", "z"], index=idx, copy=False)
    if temp_c is not None:
        df["temperature"] = np.asarray(temp_c, dtype=float)
    return df


def run_actipy(df, calib_cube: float | None = None) -> PeerResult:
    """calibrate_gravity(df, return_coeffs=True) as its users call it, its coefficients read back.
    ``calib_cube``: its still-point gate [g] (None: actipy's default 0.3; a diagnostic only)."""
    from actipy.processing import calibrate_gravity

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t0 = time.perf_counter()
        kw = {} if calib_cube is None else {"calib_cube": calib_cube}
        _, info = calibrate_gravity(df, return_coeffs=True, **kw)
        dt = time.perf_counter() - t0
    info = {k: (float(v) if isinstance(v, (int, float, np.number)) else v) for k, v in info.items()}
    text = _warning_text(caught)
    n = info.get("CalibNumSamples")
    if not info.get("CalibOK"):
        gate = 0.3 if calib_cube is None else calib_cube
        why = text or (f"sphere not populated: still points must lie beyond ±{gate:g} g on every axis ({n} still 10 s "
                       "windows)" if info.get("CalibNumIters") == 0 else
                       f"error after fit {info.get('CalibErrorAfter(mg)', float('nan')):.1f} mg >= 10 mg or no convergence")
        return _declined("actipy", f"CalibOK=0: {why}", dt, **info)
    if "CalibxIntercept" not in info:  # below 10 mg before any fit: actipy leaves the data as they are
        return PeerResult("actipy", True, f"already within 10 mg ({info.get('CalibErrorBefore(mg)', 0):.1f} mg): "
                          "identity", dt, info=info)
    b = np.array([info[f"Calib{a}Intercept"] for a in "xyz"])
    s = np.array([info[f"Calib{a}Slope"] for a in "xyz"])
    sT = np.array([info.get(f"Calib{a}SlopeT", 0.0) for a in "xyz"])
    return PeerResult("actipy", True, f"calibrated ({n} still windows, {info.get('CalibErrorAfter(mg)', 0):.1f} mg)", dt,
                      offset_g=-b / s, scale=s, matrix=np.diag(s), temp_coef=sT, temp_ref=0.0, info=info)


def _actipy(t_s, acc_g, fs_hz, temp_c, **_) -> PeerResult:
    return run_actipy(actipy_frame(t_s, acc_g, temp_c))


def _imucal(t_s, acc_g, fs_hz, temp_c, *, sections=None, gyro_dps=None, **_) -> PeerResult:
    import pandas as pd
    from imucal import FerrarisCalibration, ferraris_regions_from_section_list

    if not sections:
        return _declined("imucal", "Ferraris calibration needs the annotated sections (x_p ... z_rot); none given")
    missing = [s for s in FERRARIS_SECTIONS if s not in sections]
    if missing:
        return _declined("imucal", f"Ferraris calibration needs all 9 sections; missing {', '.join(missing)}")
    if gyro_dps is None:
        return _declined("imucal", "Ferraris calibration needs the gyro (its x/y/z_rot sections); none given")
    n = acc_g.shape[0]
    bad = [s for s in FERRARIS_SECTIONS if not (0 <= sections[s][0] < sections[s][1] <= n)]
    if bad:
        return _declined("imucal", f"sections outside the data: {', '.join(bad)}")
    data = pd.DataFrame(np.column_stack([acc_g, gyro_dps]),
                        columns=["acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z"])
    section_list = pd.DataFrame({"start": [int(sections[s][0]) for s in FERRARIS_SECTIONS],
                                 "end": [int(sections[s][1]) for s in FERRARIS_SECTIONS]}, index=list(FERRARIS_SECTIONS))
    t0 = time.perf_counter()
    try:
        regions = ferraris_regions_from_section_list(data, section_list)
        info = FerrarisCalibration(grav=1.0).compute(regions, sampling_rate_hz=fs_hz, from_acc_unit="g",
                                                    from_gyr_unit="deg/s")
    except (ValueError, np.linalg.LinAlgError) as exc:
        return _declined("imucal", f"Ferraris calibration failed: {exc}", time.perf_counter() - t0)
    dt = time.perf_counter() - t0
    M = np.linalg.inv(info.R_a) @ np.linalg.inv(info.K_a)
    return PeerResult("imucal", True, "Ferraris calibration (6 faces + 3 turns)", dt, offset_g=np.asarray(info.b_a, float),
                      scale=np.diag(M).copy(), matrix=M,
                      info={"K_a": np.asarray(info.K_a).tolist(), "R_a": np.asarray(info.R_a).tolist(),
                            "b_a": np.asarray(info.b_a).tolist()})


_ADAPTERS: dict[str, Callable[..., PeerResult]] = {"skdh": _skdh, "actipy": _actipy, "imucal": _imucal}


def calibrate(name: str, t_s: np.ndarray, acc_g: np.ndarray, fs_hz: float, temp_c: np.ndarray | None = None, *,
              sections: dict[str, tuple[int, int]] | None = None, gyro_dps: np.ndarray | None = None) -> PeerResult:
    """Run peer ``name`` on t [s] (N,), acceleration in nominal g (N, 3), temperature [°C] (N,) or None.

    ``sections`` (sample ranges into these arrays) and ``gyro_dps`` [deg/s] are only used by imucal.
    Never raises for data the peer declines: ok=False and the reason. Raises ValueError for an
    unknown or unavailable peer, or malformed arrays.
    """
    if name not in _ADAPTERS:
        raise ValueError(f"unknown peer {name!r}; known: {', '.join(PEERS)}")
    why = available(name)[name]
    if why is not None:
        raise ValueError(f"peer {name} unavailable: {why}")
    t_s = np.asarray(t_s, dtype=float)
    acc_g = np.ascontiguousarray(acc_g, dtype=float)
    if acc_g.ndim != 2 or acc_g.shape[1] != 3 or t_s.shape != (acc_g.shape[0],):
        raise ValueError(f"need t (N,) and acc_g (N, 3); got t {t_s.shape}, acc_g {acc_g.shape}")
    if temp_c is not None:
        temp_c = np.asarray(temp_c, dtype=float)
        if temp_c.shape != t_s.shape:
            raise ValueError(f"temp_c must be (N,) like t; got {temp_c.shape}")
    try:
        return _ADAPTERS[name](t_s, acc_g, float(fs_hz), temp_c, sections=sections, gyro_dps=gyro_dps)
    except MemoryError:
        raise
    except Exception as exc:  # a peer's own crash on this data is a result too (declined, with its error)
        return _declined(name, f"failed: {type(exc).__name__}: {exc}")
