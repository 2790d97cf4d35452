"""``gravcal gyro DATASET|FILE.csv``: in-use gyro calibration of a recording, with checks.

Runs the accelerometer calibration (core.pipeline.calibrate_recording) to get the
quasi-static windows and raw -> g, then the gyro calibration on the same windows
(core.gyro.calibrate_gyro: bias from the windows, sensitivity from pose-to-pose rotations).
For a measured dataset with turn sections (imucal_ferraris: x_rot, y_rot, z_rot, 360° each)
it integrates every turn before calibration (nominal scale, as recorded) and after. The
numbers in docs/gyro.md come from ``gravcal gyro imucal_ferraris`` and ``gravcal gyro imu_tk_xsens``.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError

TURN_TOLERANCE_DEG = 5.0  # stated tolerance of the measured 360° turns after calibration (docs/gyro.md)


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "gyro", help="in-use gyro calibration (bias, sensitivity) of a recording or measured dataset",
        description="Gyro bias from the quasi-static windows and sensitivity from the rotations between them "
                    "(gravity direction before and after vs the integrated gyro). SOURCE: a measured dataset name "
                    "(gravcal.io.datasets, e.g. imucal_ferraris, imu_tk_xsens) or a CSV/.npy recording with "
                    "columns t, ax, ay, az, gx, gy, gz.",
    )
    p.add_argument("source", help="dataset name or recording file")
    p.add_argument("--start", type=float, default=None, metavar="RAW_PER_RAD_S",
                   help="start sensitivity [raw units per rad/s] (default: bootstrap from the data)")
    p.add_argument("--hp-hz", type=float, default=None, help="board high-pass corner [Hz] to undo (ENC-03J board: 0.3)")
    p.add_argument("--detector", default="lotters", metavar="lotters|variance", help="quasi-static detector")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    return p


def _load(source: str) -> dict[str, Any]:
    from ..io import datasets

    if source in datasets.DATASETS:
        rec = datasets.load(source)
        if rec.gyro is None:
            raise InputError(f"dataset {source!r} has no gyro")
        return {"t": rec.t, "acc": rec.acc, "gyro": rec.gyro, "fs": rec.fs, "sections": rec.sections,
                "nominal": rec.meta.get("gyro_per_rad_s"), "name": rec.name}
    path = Path(source)
    if not path.exists():
        raise InputError(f"{source}: neither a dataset ({', '.join(datasets.DATASETS)}) nor a file")
    from ..io.recordings import read_recording

    rec = read_recording(path)
    if rec.gyro is None:
        raise InputError(f"{path}: no gx, gy, gz columns")
    return {"t": rec.t, "acc": rec.raw, "gyro": rec.gyro, "fs": rec.fs, "sections": {}, "nominal": None,
            "name": str(path)}


def run(args: argparse.Namespace) -> int:
    from gravcal.core.gyro import calibrate_gyro
    from gravcal.core.gyro.check import check_turns
    from gravcal.core.pipeline import calibrate_recording

    d = _load(args.source)
    report = calibrate_recording(d["t"], d["acc"], fs=d["fs"], detector=args.detector)
    cal = calibrate_gyro(d["t"], d["gyro"], report.windows, report.calibration, fs=d["fs"], hp_hz=args.hp_hz,
                         start=args.start)
    out: dict[str, Any] = {"source": d["name"], "acc_windows": report.n_windows,
                           "acc_insample_rms_mg": report.insample_rms_mg, "gyro": cal.to_json_dict()}
    if d["nominal"]:  # the nominal scale (bias from the windows): how wrong are the recorded units?
        from gravcal.core.gyro.calibrate import pairs_rms_deg

        rms, n = pairs_rms_deg(d["gyro"], report.windows, report.calibration, float(d["nominal"]), cal.bias,
                               fs=d["fs"], hp_hz=args.hp_hz)
        out["pairs_rms_deg_nominal"] = {"rms_deg": rms, "n_pairs": n, "nominal_per_rad_s": float(d["nominal"])}
    turns = {k: v for k, v in d["sections"].items() if k.endswith("_rot")}
    if turns and cal.sensitivity is not None:
        before = check_turns(d["gyro"], turns, d["fs"], nominal_per_rad_s=d["nominal"]) if d["nominal"] else []
        after = check_turns(d["gyro"], turns, d["fs"], calibration=cal)
        out["turns_deg"] = {
            "expected": 360.0, "tolerance": TURN_TOLERANCE_DEG,
            "before": {c.name: c.angle_deg for c in before}, "after": {c.name: c.angle_deg for c in after},
        }
    if args.json:
        print(json.dumps(out, default=_num))
    else:
        print(_summary(out, cal))
    if cal.sensitivity is None:
        print(f"gravcal: gyro sensitivity not determined: {cal.message}", file=sys.stderr)
        return 3
    return 0


def _num(x: Any) -> Any:
    if isinstance(x, np.generic):
        return x.item()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def _summary(out: dict[str, Any], cal: Any) -> str:
    g = out["gyro"]
    lines = [f"source      {out['source']}: {out['acc_windows']} quasi-static windows "
             f"(accelerometer in-sample {out['acc_insample_rms_mg']:.3g} mg)",
             f"bias        {np.round(cal.bias, 4).tolist()} ± {np.round(cal.bias_std, 4).tolist()} [raw]"]
    if cal.sensitivity is not None:
        sd = np.sqrt(np.diag(cal.sensitivity_cov)).reshape(cal.sensitivity.shape)
        for r in range(cal.sensitivity.shape[0]):
            lines.append("sensitivity " + "  ".join(f"{v:10.5g} ± {s:.2g}" for v, s in zip(cal.sensitivity[r], sd[r]))
                         + "   [raw per rad/s]")
        ho, ho0 = g["heldout_rms_deg"], g["heldout_rms_deg_start"]
        if ho is not None:
            lines.append(f"held-out    gravity direction after the rotations: {ho:.3g}° rms (start values: {ho0:.3g}°)")
    lines.append(f"pairs       {g['message']}")
    nom = out.get("pairs_rms_deg_nominal")
    if nom:
        lines.append(f"nominal     {nom['nominal_per_rad_s']:.6g} raw per rad/s (bias from the windows): gravity direction "
                     f"after the rotations {nom['rms_deg']:.3g}° rms over {nom['n_pairs']} pairs")
    t = out.get("turns_deg")
    if t:
        for name in t["after"]:
            b = t["before"].get(name, math.nan)
            lines.append(f"turn        {name}: before {b:.2f}°, after {t['after'][name]:.2f}° (expected 360 ± "
                         f"{t['tolerance']:g})")
    lines.append("convention  omega [rad/s] = sensitivity^-1 (raw - bias)")
    return "\n".join(lines)
