"""Loaders for the measured recordings in ``$GRAVCAL_DATA`` (default ``../shared/data``).

The data are never copied into the repository: :func:`data_dir` locates them, :func:`load`
reads one into a :class:`MeasuredRecording` (raw units as recorded, units named), and
:func:`to_calibrate_csv` writes the ``gravcal calibrate`` CSV layout (t, ax, ay, az,
[gx, gy, gz], [temp]) so every command can run on them.

Names (``DATASETS``)::

    imu_tk_xsens                         Xsens MTi, 100 Hz, 16-bit counts, acc + gyro, 512 s, 38 poses
    actigraph_cpw_thermal_chamber        ActiGraph CentrePoint, 32 Hz, ADC counts, 3.56 h static in a
                                         thermal chamber; temp = ADXL die temperature [°C] (4 s)
    actigraph_cpw_thermal_chamber/mcu    same, temp = MCU temperature [°C]
    imucal_ferraris                      imucal example Ferraris session, 102.4 Hz, acc [m/s²], gyro [deg/s]
    imucal_ferraris/annotated            the 9 annotated sections, 204.8 Hz, raw a.u. (~2048 counts/g)
    mpu6050_tomisuarez                   = mpu6050_tomisuarez/calibration (Tedaldi-style multi-pose, 102 s)
    mpu6050_tomisuarez/calibration       MPU-6050, 100 Hz, int16 counts (~16384 counts/g)
    mpu6050_tomisuarez/static            one static pose, 449 s (noise / Allan deviation)
    mpu6050_tomisuarez/x_rot             90 deg rotations about x
"""
from __future__ import annotations

import csv
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import InputError

REPO_ROOT = Path(__file__).resolve().parent.parent
"""The repository root (daemon/ sits directly under it)."""

G_STANDARD = 9.80665
"""Standard gravity [m/s² per g], for recordings stored in m/s²."""


def data_dir() -> Path:
    """Folder holding the measured recordings: ``$GRAVCAL_DATA`` or ``<repo>/../shared/data``."""
    env = os.environ.get("GRAVCAL_DATA")
    if env:
        return Path(env).expanduser()
    return (REPO_ROOT.parent / "shared" / "data").resolve()


_default_data_dir = data_dir  # load() has a keyword of the same name


@dataclass
class MeasuredRecording:
    """One measured recording, as recorded (no calibration applied).

    ``t`` (N,) [s] from the first sample (original epoch in ``meta["t0_unix"]`` when there is
    one); ``acc`` (N, 3) in ``acc_units``; ``gyro`` (N, 3) in ``gyro_units`` or None; ``temp``
    (N,) [°C] or None; ``fs`` [Hz] nominal rate; ``sections`` maps a section name to a
    ``(start, end)`` sample range (end exclusive) into these arrays; ``meta`` holds nominal
    scale factors (``acc_per_g``: acc units per g; ``gyro_per_rad_s``) and file notes.
    """

    name: str
    t: np.ndarray
    acc: np.ndarray
    acc_units: str
    fs: float
    source: str
    gyro: np.ndarray | None = None
    gyro_units: str | None = None
    temp: np.ndarray | None = None
    sections: dict[str, tuple[int, int]] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def n_samples(self) -> int:
        return int(self.t.shape[0])

    @property
    def duration_s(self) -> float:
        return float(self.t[-1] - self.t[0]) if self.n_samples else 0.0

    def section(self, name: str) -> "MeasuredRecording":
        """The samples of one named section, as a MeasuredRecording of its own."""
        if name not in self.sections:
            raise InputError(f"{self.name}: no section {name!r} (have: {', '.join(self.sections) or 'none'})")
        a, b = self.sections[name]
        return MeasuredRecording(
            name=f"{self.name}[{name}]", t=self.t[a:b], acc=self.acc[a:b], acc_units=self.acc_units, fs=self.fs,
            source=self.source, gyro=None if self.gyro is None else self.gyro[a:b], gyro_units=self.gyro_units,
            temp=None if self.temp is None else self.temp[a:b], sections={}, meta=dict(self.meta),
        )


# ---------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------
def _folder(root: Path, name: str) -> Path:
    folder = root / name
    if not folder.is_dir():
        raise InputError(
            f"measured data folder {folder} not found (set GRAVCAL_DATA to the folder holding {name}/)"
        )
    return folder


def _file(folder: Path, fname: str) -> Path:
    p = folder / fname
    if not p.is_file():
        raise InputError(f"{p}: missing file of the {folder.name} recording")
    return p


def _source_summary(folder: Path) -> str:
    """The SOURCE.txt text (provenance, device, units, licence) of a recording folder."""
    p = folder / "SOURCE.txt"
    return p.read_text(encoding="utf-8", errors="replace").strip() if p.is_file() else ""


# ---------------------------------------------------------------------------------------
# the recordings
# ---------------------------------------------------------------------------------------
def _load_xsens(root: Path, variant: str | None) -> MeasuredRecording:
    folder = _folder(root, "imu_tk_xsens")
    acc = np.loadtxt(_file(folder, "xsens_acc.mat"), dtype=np.float64, ndmin=2)
    gyr = np.loadtxt(_file(folder, "xsens_gyro.mat"), dtype=np.float64, ndmin=2)
    if acc.shape != gyr.shape or not np.array_equal(acc[:, 0], gyr[:, 0]):
        raise InputError(f"{folder}: xsens_acc.mat and xsens_gyro.mat do not share timestamps")
    return MeasuredRecording(
        name="imu_tk_xsens", t=acc[:, 0] - acc[0, 0], acc=acc[:, 1:4], gyro=gyr[:, 1:4],
        acc_units="counts (16-bit unsigned ADC, zero ~32768)", gyro_units="counts (16-bit unsigned ADC, zero ~32768)",
        fs=100.0, source=_source_summary(folder),
        meta={"device": "Xsens MTi", "acc_per_g": 4066.0, "gyro_per_rad_s": 6258.0, "t0_file_s": float(acc[0, 0]),
              "local_g_m_s2": 9.81744, "files": ["xsens_acc.mat", "xsens_gyro.mat"]},
    )


def _load_actigraph(root: Path, variant: str | None) -> MeasuredRecording:
    folder = _folder(root, "actigraph_cpw_thermal_chamber")
    raw = np.loadtxt(_file(folder, "cpw_chamber_raw_counts.csv.gz"), delimiter=",", skiprows=1, dtype=np.float64, ndmin=2)
    tc = np.loadtxt(_file(folder, "cpw_chamber_temperature_C.csv"), delimiter=",", skiprows=1, dtype=np.float64, ndmin=2)
    col = 1 if variant == "mcu" else 2  # t_unix, temp_mcu_C, temp_adxl_C
    t_unix = raw[:, 0]
    # Temperature every 4 s: linear interpolation onto the 32 Hz samples (held at the ends).
    temp = np.interp(t_unix, tc[:, 0], tc[:, col])
    return MeasuredRecording(
        name="actigraph_cpw_thermal_chamber" + (f"/{variant}" if variant else ""),
        t=t_unix - t_unix[0], acc=raw[:, 1:4], acc_units="counts (raw ADC, ~256 counts/g nominal, +-8 g)",
        fs=32.0, temp=temp, source=_source_summary(folder),
        meta={"device": "ActiGraph CentrePoint Insight Watch CPW1C48210013", "acc_per_g": 256.0,
              "t0_unix": float(t_unix[0]), "temp_source": "MCU" if col == 1 else "ADXL",
              "temp_interpolated_from_s": float(np.median(np.diff(tc[:, 0]))),
              "files": ["cpw_chamber_raw_counts.csv.gz", "cpw_chamber_temperature_C.csv"]},
    )


def _load_ferraris(root: Path, variant: str | None) -> MeasuredRecording:
    folder = _folder(root, "imucal_ferraris")
    if variant == "annotated":
        with open(_file(folder, "annotated_session.csv"), encoding="utf-8", newline="") as f:
            rows = list(csv.reader(f))
        header, rows = rows[0], rows[1:]
        idx = {n: i for i, n in enumerate(header)}
        sample = np.array([int(r[idx["samples"]]) for r in rows])
        order = np.argsort(sample, kind="stable")  # the file is grouped by part name; time order is by sample
        parts = [rows[i][idx["part"]] for i in order]
        vals = np.array([[float(rows[i][idx[c]]) for c in ("acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z")]
                         for i in order])
        fs = 204.8
        sections: dict[str, tuple[int, int]] = {}
        start = 0
        for k in range(1, len(parts) + 1):
            if k == len(parts) or parts[k] != parts[start]:
                sections[parts[start]] = (start, k)
                start = k
        return MeasuredRecording(
            name="imucal_ferraris/annotated", t=sample[order] / fs, acc=vals[:, :3], gyro=vals[:, 3:],
            acc_units="a.u. (raw counts, ~2048 counts/g)", gyro_units="a.u. (raw counts)", fs=fs,
            source=_source_summary(folder), sections=sections,
            meta={"acc_per_g": 2048.0, "files": ["annotated_session.csv"],
                  "note": "only the 9 annotated sections, concatenated; t = sample index / fs"},
        )
    d = np.loadtxt(_file(folder, "example_ferraris_session.csv"), delimiter=",", skiprows=1, dtype=np.float64, ndmin=2)
    fs = 102.4
    spans = json.loads(_file(folder, "example_ferraris_session_list.json").read_text(encoding="utf-8"))
    sections = {k: (int(v["start"]), int(v["end"])) for k, v in spans.items()}
    return MeasuredRecording(
        name="imucal_ferraris", t=d[:, 0] / fs, acc=d[:, 4:7], gyro=d[:, 1:4], acc_units="m/s^2 (nominally scaled, uncalibrated)",
        gyro_units="deg/s (nominally scaled, uncalibrated)", fs=fs, source=_source_summary(folder), sections=sections,
        meta={"acc_per_g": G_STANDARD, "gyro_per_rad_s": float(np.degrees(1.0)),
              "files": ["example_ferraris_session.csv", "example_ferraris_session_list.json"]},
    )


_MPU_FILES = {"calibration": "example_data_calibration.csv", "static": "example_data_tinit_calc.csv",
              "x_rot": "imu_90_x_rot.csv"}


def _load_mpu6050(root: Path, variant: str | None) -> MeasuredRecording:
    folder = _folder(root, "mpu6050_tomisuarez")
    variant = variant or "calibration"
    path = _file(folder, _MPU_FILES[variant])
    header: dict[str, str] = {}
    with open(path, encoding="utf-8") as f:
        for _ in range(4):  # Fs / Logging Type / Initialization time / Waiting time
            key, _, value = f.readline().strip().partition(",")
            header[key.strip()] = value.strip()
    try:
        fs = float(header["Fs"])
    except (KeyError, ValueError):
        raise InputError(f"{path}: first header line is not 'Fs,<rate>'") from None
    d = np.loadtxt(path, delimiter=",", skiprows=5, dtype=np.float64, ndmin=2)  # 4 header lines + column names
    sections: dict[str, tuple[int, int]] = {}
    t_init = float(header.get("Initialization time", "-1"))
    if t_init > 0:
        sections["initial_static"] = (0, min(len(d), int(round(t_init * fs))))
    return MeasuredRecording(
        name=f"mpu6050_tomisuarez/{variant}", t=np.arange(len(d)) / fs, acc=d[:, 0:3], gyro=d[:, 3:6],
        acc_units="counts (int16, ~16384 counts/g at +-2 g)", gyro_units="counts (int16, ~131 counts/(deg/s))", fs=fs,
        source=_source_summary(folder), sections=sections,
        meta={"device": "MPU-6050", "acc_per_g": 16384.0, "gyro_per_rad_s": 131.0 * float(np.degrees(1.0)),
              "header": header, "files": [path.name], "note": "t = sample index / Fs (the file has no time column)"},
    )


_LOADERS: dict[str, tuple[Callable[[Path, str | None], MeasuredRecording], str | None]] = {
    "imu_tk_xsens": (_load_xsens, None),
    "actigraph_cpw_thermal_chamber": (_load_actigraph, None),
    "actigraph_cpw_thermal_chamber/mcu": (_load_actigraph, "mcu"),
    "imucal_ferraris": (_load_ferraris, None),
    "imucal_ferraris/annotated": (_load_ferraris, "annotated"),
    "mpu6050_tomisuarez": (_load_mpu6050, None),
    "mpu6050_tomisuarez/calibration": (_load_mpu6050, "calibration"),
    "mpu6050_tomisuarez/static": (_load_mpu6050, "static"),
    "mpu6050_tomisuarez/x_rot": (_load_mpu6050, "x_rot"),
}

DATASETS: tuple[str, ...] = tuple(_LOADERS)
"""Every loadable name: the four recordings and their variants (``folder/variant``)."""

RECORDINGS: tuple[str, ...] = ("imu_tk_xsens", "actigraph_cpw_thermal_chamber", "imucal_ferraris", "mpu6050_tomisuarez")
"""The four recordings (one default variant each)."""


def load(name: str, *, data_dir: str | Path | None = None) -> MeasuredRecording:
    """Load the measured recording ``name`` (one of :data:`DATASETS`) from ``data_dir`` (default :func:`data_dir`)."""
    if name not in _LOADERS:
        raise InputError(f"unknown dataset {name!r}; known: {', '.join(DATASETS)}")
    root = Path(data_dir) if data_dir is not None else _default_data_dir()
    loader, variant = _LOADERS[name]
    return loader(root, variant)


def to_calibrate_csv(rec: MeasuredRecording, path: str | Path) -> Path:
    """Write ``rec`` in the ``gravcal calibrate`` CSV layout: t, ax, ay, az, [gx, gy, gz], [temp].

    Values stay in the recording's units (the calibrate/diagnose commands work in raw units);
    a ``#`` comment line names the source and units. Returns the path written.
    """
    path = Path(path)
    cols = [rec.t, rec.acc[:, 0], rec.acc[:, 1], rec.acc[:, 2]]
    names = ["t", "ax", "ay", "az"]
    fmt = ["%.6f", "%.10g", "%.10g", "%.10g"]
    if rec.gyro is not None:
        cols += [rec.gyro[:, 0], rec.gyro[:, 1], rec.gyro[:, 2]]
        names += ["gx", "gy", "gz"]
        fmt += ["%.10g"] * 3
    if rec.temp is not None:
        cols.append(rec.temp)
        names.append("temp")
        fmt.append("%.4f")
    comment = f"# {rec.name}: acc [{rec.acc_units}]"
    if rec.gyro is not None:
        comment += f", gyro [{rec.gyro_units}]"
    if rec.temp is not None:
        comment += ", temp [degC]"
    comment += f", fs {rec.fs:g} Hz"
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(comment + "\n" + ",".join(names) + "\n")
        np.savetxt(f, np.column_stack(cols), fmt=fmt, delimiter=",")
    return path
