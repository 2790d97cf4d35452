"""Wearable device files through their existing readers (the ``formats`` extra).

ActiGraph .gt3x / .agdc with pygt3x (raw counts, or g in the old NHANES-era .gt3x); Axivity .cwa and
GENEActiv .bin with scikit-digital-health (g, as its readers return them). Temperature, where the
device records it, is interpolated onto the sample times as the ``temp`` covariate [°C].
"""
from __future__ import annotations

import importlib
import logging
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import InputError
from .sniff import EXTRA_FOR, Sniffed


def _reader_module(path: Path, found: Sniffed, module: str) -> Any:
    try:
        return importlib.import_module(module)
    except ImportError:
        need, extra = EXTRA_FOR[found.kind]
        raise InputError(f"{path}: {found.what}; reading it needs {need}: pip install 'gravcal[{extra}]'") from None


def _on_sample_times(t: np.ndarray, t_cov: np.ndarray, cov: np.ndarray) -> np.ndarray | None:
    ok = np.isfinite(t_cov) & np.isfinite(cov)
    if ok.sum() < 1:
        return None
    return np.interp(t, t_cov[ok], cov[ok])


def read_actigraph(path: Path, found: Sniffed) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    _reader_module(path, found, "pygt3x")
    from pygt3x.reader import FileReader

    logging.getLogger("pygt3x").setLevel(logging.ERROR)  # per-second sample-count chatter
    try:
        with FileReader(str(path)) as r:
            acc = np.asarray(r.acceleration, dtype=np.float64)
            temps = r.calibrate_temperature() if len(r.temperature) else None
            nhanes = bool(r.nhanes)
            info = r.info
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - any reader failure is the file's fault, said in one line
        raise InputError(f"{path}: {found.what} that pygt3x cannot read ({type(exc).__name__})") from None
    if acc.shape[0] == 0:
        raise InputError(f"{path}: {found.what} holding no acceleration samples")
    t = acc[:, 0]
    cols = {"t": t, "ax": acc[:, 1], "ay": acc[:, 2], "az": acc[:, 3]}
    meta: dict[str, Any] = {
        "format": found.kind, "reader": "pygt3x", "device_fs_hz": float(info.sample_rate),
        "serial": str(getattr(info, "serial_number", "") or ""),
        "idle_sleep_flagged": int(np.count_nonzero(acc[:, 4] == 1)),
    }
    if temps is not None and len(temps):
        temps = np.asarray(temps, dtype=np.float64)
        temp = _on_sample_times(t, temps[:, 0], temps[:, 2])  # the ADXL die temperature, next to the sensing element
        if temp is not None:
            cols["temp"] = temp
            meta["temp_source"] = "ADXL die temperature, interpolated from its own rate"
    units = "g" if nhanes else "counts"
    scale = float(getattr(info, "acceleration_scale", 0.0) or 0.0)
    meta["device"] = f"ActiGraph {getattr(info, 'device_type', '') or 'device'}".strip()
    if units == "g" or scale > 1.0:  # the header's counts per g (an .agdc states 1, which is no scale)
        meta["nominal_per_g"] = 1.0 if units == "g" else scale
    return cols, {"units": units, **meta}


def read_skdh(path: Path, found: Sniffed) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    _reader_module(path, found, "skdh")
    from skdh.io import ReadBin, ReadCwa

    reader = ReadCwa() if found.kind == "cwa" else ReadBin()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # naive-time-zone notes
            res = reader.predict(file=str(path))
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"{path}: {found.what} that scikit-digital-health cannot read ({type(exc).__name__})") from None
    acc = np.asarray(res.get("accel", np.empty((0, 3))), dtype=np.float64)
    if acc.ndim != 2 or acc.shape[0] == 0:
        raise InputError(f"{path}: {found.what} holding no acceleration samples")
    t = np.asarray(res["time"], dtype=np.float64)
    cols = {"t": t, "ax": acc[:, 0], "ay": acc[:, 1], "az": acc[:, 2]}
    temp = res.get("temperature")
    if temp is not None and np.shape(temp) == t.shape:
        cols["temp"] = np.asarray(temp, dtype=np.float64)
    meta = {"format": found.kind, "reader": "scikit-digital-health", "device_fs_hz": float(res.get("fs", 0.0)),
            "device": "Axivity" if found.kind == "cwa" else "GENEActiv", "nominal_per_g": 1.0}
    return cols, {"units": "g", **meta}


def read_wearable(path: Path, found: Sniffed) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    if found.kind in ("gt3x", "agdc"):
        return read_actigraph(path, found)
    return read_skdh(path, found)
