"""Wearable device files through their existing readers (the ``formats`` extra).

ActiGraph .gt3x / .agdc with pygt3x (raw counts, or g in the old NHANES-era .gt3x); Axivity .cwa and
GENEActiv .bin with scikit-digital-health (g, as its readers return them; in a child process, isolated.py:
its compiled readers end their process on some damaged files). Temperature, where the
device records it, is interpolated onto the sample times as the ``temp`` covariate [°C].
"""
from __future__ import annotations

import importlib
import importlib.util
import logging
import sys
import warnings
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import InputError
from .isolated import read_in_child
from .sniff import EXTRA_FOR, Sniffed


def _reader_module(path: Path, found: Sniffed, module: str) -> Any:
    try:
        return importlib.import_module(module)
    except ImportError:
        need, extra = EXTRA_FOR[found.kind]
        raise InputError(f"{path}: {found.what}; reading it needs {need}: pip install 'gravcal[{extra}]'") from None


def _installed(module: str) -> bool:
    """Whether ``module`` can be imported, without importing it here."""
    if module in sys.modules:
        return sys.modules[module] is not None
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def _on_sample_times(t: np.ndarray, t_cov: np.ndarray, cov: np.ndarray) -> np.ndarray | None:
    ok = np.isfinite(t_cov) & np.isfinite(cov)
    if ok.sum() < 1:
        return None
    return np.interp(t, t_cov[ok], cov[ok])


# What an ActiGraph file can hold, from its own info.txt: a zip bomb (2 MB on disk, gigabytes of zeros inside)
# would otherwise keep the reader decompressing for half an hour. Python's zipfile never inflates a member past
# the size the central directory declares, so bounding the declared sizes bounds the work.
SAMPLE_BYTES = 6  # log.bin's ACTIVITY2 record: three int16 per sample (the packed formats take less)
SECOND_BYTES = 512  # per-second record headers and checksums, battery, temperature, lux, events
FIXED_BYTES = 16 << 20  # firmware images, metadata and RAM dumps some devices add (neo.gt3x: 0.3 MB)
INFO_BYTES = 1 << 16  # the largest info.txt worth reading (real ones: ~0.5 kB)
RATIO_WITHOUT_INFO = 50  # declared / compressed, when info.txt gives no duration (real log.bin: 1-3)
TICKS_PER_S = 10_000_000  # .NET ticks, info.txt's dates


def _info_fields(z: zipfile.ZipFile) -> dict[str, str]:
    try:
        if z.getinfo("info.txt").file_size > INFO_BYTES:
            return {}
        text = z.read("info.txt").decode("utf-8-sig", "replace")
    except Exception:  # noqa: BLE001 - no usable info.txt (missing, damaged, encrypted, an unknown method)
        return {}
    return {k.strip(): v.strip() for k, _, v in (line.partition(":") for line in text.splitlines()) if _}


def _recorded_span(info: dict[str, str]) -> tuple[float, float] | None:
    """(seconds, Hz) the file says it recorded, or None when info.txt does not say it plausibly."""
    try:
        rate = float(info["Sample Rate"])
        start = int(info["Start Date"])
        ends = [int(info[k]) for k in ("Last Sample Time", "Stop Date", "Download Date") if int(info.get(k) or 0) > start]
    except (KeyError, ValueError):
        return None
    if not (0 < rate <= 10_000 and ends):
        return None
    return (ends[0] - start) / TICKS_PER_S, rate


def check_declared_sizes(path: Path, found: Sniffed) -> None:
    """InputError when the members of an ActiGraph zip declare more bytes than its recording can hold: the
    span and rate of its info.txt (or, without them, ``RATIO_WITHOUT_INFO`` x the compressed size)."""
    try:
        with zipfile.ZipFile(path) as z:
            members = z.infolist()
            span = _recorded_span(_info_fields(z))
    except Exception as exc:  # noqa: BLE001 - zipfile's directory parser, whatever it raises
        raise InputError(f"{path}: {found.what} with a damaged zip directory ({type(exc).__name__})") from None
    declared = sum(m.file_size for m in members)
    biggest = max(members, key=lambda m: m.file_size)
    if span is not None:
        seconds, rate = span
        limit = FIXED_BYTES + seconds * (2 * rate * SAMPLE_BYTES + SECOND_BYTES)
        why = f"more than {seconds:.0f} s at {rate:g} Hz can hold"
    else:
        limit = max(FIXED_BYTES, RATIO_WITHOUT_INFO * sum(m.compress_size for m in members))
        why = f"more than {RATIO_WITHOUT_INFO}x its compressed size, and info.txt gives no span to allow it"
    if declared > limit:
        raise InputError(f"{path}: {found.what} whose members declare {declared >> 20} MiB ({biggest.filename} "
                         f"{biggest.file_size >> 20} MiB), {why} (at most {int(limit) >> 20} MiB): a damaged "
                         f"file or a zip bomb; not read")


def read_actigraph(path: Path, found: Sniffed) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    _reader_module(path, found, "pygt3x")
    check_declared_sizes(path, found)
    from pygt3x.reader import FileReader

    logging.getLogger("pygt3x").setLevel(logging.ERROR)  # per-second sample-count chatter
    try:
        with FileReader(str(path)) as r:
            acc = np.asarray(r.acceleration, dtype=np.float64)
            temps = r.calibrate_temperature() if len(r.temperature) else None
            nhanes = bool(r.nhanes)
            info = r.info
            factory = _factory_calibration(r, info) if not nhanes else None
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
    if factory is not None:
        meta["device_calibration"] = factory
    return cols, {"units": units, **meta}


def _factory_calibration(reader: Any, info: Any) -> dict[str, Any] | None:
    """The device's own calibration of raw counts, as its file states it (an .agdc's calibration.json, method 2,
    at the recording's rate): {"offset": o [counts], "sensitivity": K [counts per g], "source"}, in gravcal's
    convention raw = K a + o; pygt3x's CalibrationV2Service reads the file's fields (a = M (raw - o), K = M^-1).
    None when the file states none, says its samples are already calibrated, or uses another method."""
    cal = getattr(reader, "calibration", None)
    if not isinstance(cal, dict) or cal.get("isCalibrated", True) or cal.get("calibrationMethod") != 2:
        return None
    try:
        from pygt3x.calibration import CalibrationV2Service

        service = CalibrationV2Service(cal, int(info.sample_rate))
        M = np.asarray(service.sensitivity_matrix, dtype=np.float64)
        o = np.asarray(service.offset_vector, dtype=np.float64).reshape(3)
        K = np.linalg.inv(M)
    except Exception:  # noqa: BLE001 - a calibration for another rate, damaged fields: no factory start
        return None
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(o)) and np.all(np.diag(K) > 0)):
        return None
    return {"offset": o.tolist(), "sensitivity": K.tolist(),
            "source": f"calibration.json (method 2, {int(info.sample_rate)} Hz)"}


CWA_HEADER, CWA_BLOCK = 1024, 512  # an Axivity .cwa: a header packet, then whole blocks of samples


SKDH_READER = "gravcal.io.formats.wearables:read_skdh_here"  # run in a child process (isolated.py)


def read_skdh(path: Path, found: Sniffed) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """scikit-digital-health's readers (Fortran and C) in a child process: they end their process on some damaged
    files (a truncated .cwa: "Fortran runtime error: End of file", exit status 2)."""
    if not _installed("skdh"):
        _reader_module(path, found, "skdh")  # the InputError saying which extra installs it
    if found.kind == "cwa" and path.stat().st_size < CWA_HEADER + CWA_BLOCK:
        # refused in one line without starting a child for it
        raise InputError(f"{path}: {found.what} of {path.stat().st_size} bytes, shorter than its {CWA_HEADER}-byte "
                         f"header and one {CWA_BLOCK}-byte block of samples: truncated or not a .cwa")
    return read_in_child(SKDH_READER, path, found, "scikit-digital-health")


def read_skdh_here(path: Path, found: Sniffed) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """scikit-digital-health's reader in this process (the child of read_skdh)."""
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
