"""``gravcal calibrate FILE.csv|FILE.npy``: offline in-use calibration of a recording.

Reads and validates the recording (daemon.recordings), runs
gravcal.core.pipeline.calibrate_recording (detector -> start -> Lötters batch estimator ->
held-out error over contiguous folds of windows) and prints a summary, or with ``--json``
exactly one JSON object. Exit 3 (with the JSON still printed) when the calibration is not
converged or not observable.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError

log = logging.getLogger(__name__)

EXIT_OK = 0
EXIT_NOT_TRUSTWORTHY = 3
AXES = ("x", "y", "z")


def model_choices() -> list[str]:
    """Model names the pipeline accepts: the registered parameterizations (offsets, 6, and
    whatever H-twelve adds) plus any extra names the pipeline declares in ``MODELS`` (e.g.
    "auto"). Imports the pipeline, so it is only called when a calibration runs."""
    from gravcal.core.estimators.parameterization import PARAMETERIZATIONS

    choices = list(PARAMETERIZATIONS)
    try:
        from gravcal.core import pipeline
    except ImportError:
        return choices
    return choices + [m for m in getattr(pipeline, "MODELS", ()) if m not in choices]


def detector_choices() -> list[str]:
    from gravcal.core.detectors import DETECTORS

    return list(DETECTORS)


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "calibrate", help="calibrate a recording (CSV or .npy) from its quasi-static moments",
        description="Offline in-use calibration of a recording. CSV: header row; columns t [s], ax, ay, az "
                    "(raw units of any scale), optional gx, gy, gz, temp [°C]; other columns ignored. "
                    ".npy: a structured array with the same field names.",
    )
    p.add_argument("file", type=Path, help="recording: FILE.csv or FILE.npy")
    # No argparse choices: listing them would import the numerics (a second of scipy) for every
    # `gravcal --help`; run() validates and names the known values.
    from gravcal.core.estimators.parameterization import PARAMETERIZATIONS  # numpy only: cheap

    p.add_argument("--model", default="6", metavar="|".join(PARAMETERIZATIONS),
                   help="parameters to estimate: offsets only, 6 (sensitivity + offset per axis), ... (default 6)")
    p.add_argument("--detector", default="lotters", metavar="lotters|variance",
                   help="quasi-static detector (default lotters: Lötters' norm high-pass/rectify/low-pass; "
                        "variance: moving variance)")
    p.add_argument("--folds", type=int, default=5,
                   help="contiguous folds of windows for the held-out error (default 5)")
    p.add_argument("--start", type=Path, metavar="CAL.json",
                   help="start from this calibration (gravcal JSON) instead of the ellipsoid fit of the data")
    p.add_argument("--save", type=Path, metavar="CAL.json", help="also write the calibration (gravcal JSON) here")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    p.add_argument("--no-saturation-check", dest="check_saturation", action="store_false",
                   help="do not treat samples piled up at a channel's extreme value as saturated")
    return p


def _load_start(path: Path):
    from gravcal.core.calibration import Calibration

    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: no such file (--start)") from None
    try:
        return Calibration.from_json(text)
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None


def run(args: argparse.Namespace) -> int:
    from gravcal.core.pipeline import calibrate_recording

    from .recordings import jsonable, read_recording

    models = model_choices()
    if args.model not in models:
        raise InputError(f"unknown --model {args.model!r}; choose one of {', '.join(models)}")
    detectors = detector_choices()
    if args.detector not in detectors:
        raise InputError(f"unknown --detector {args.detector!r}; choose one of {', '.join(detectors)}")
    if args.folds < 2:
        raise InputError(f"--folds must be at least 2 (held-out error needs windows left out), got {args.folds}")
    start = _load_start(args.start) if args.start else None
    t0 = time.perf_counter()
    rec = read_recording(args.file, check_saturation=args.check_saturation)
    t_read = time.perf_counter() - t0
    log.info("read %s: %d samples, %.1f s at %.6g Hz in %.2f s", rec.source, rec.n_samples, rec.duration_s, rec.fs, t_read)
    t0 = time.perf_counter()
    report = calibrate_recording(rec.t, rec.raw, temp=rec.temp, model=args.model, fs=rec.fs,
                                 detector=args.detector, start=start, folds=args.folds)
    t_cal = time.perf_counter() - t0
    cal = report.calibration
    out = dict(report.to_json_dict())
    # The keys promised by the issue, whatever the report already holds.
    out.setdefault("model", cal.model)
    out.setdefault("offset", cal.offset.tolist())
    out.setdefault("sensitivity", cal.sensitivity.tolist())
    out.setdefault("std", cal.std)
    out.setdefault("n_windows", int(cal.n_windows))
    out.setdefault("heldout_rms_mg", getattr(report, "heldout_rms_mg", None))
    out.setdefault("insample_rms_mg", getattr(report, "insample_rms_mg", None))
    out.setdefault("converged", bool(cal.converged))
    out.setdefault("observable", bool(cal.observable))
    out.setdefault("message", cal.message)
    out["input"] = {
        "file": str(rec.source), "n_samples": rec.n_samples, "duration_s": rec.duration_s, "fs_hz": rec.fs,
        "n_dropped_nonfinite": rec.n_dropped, "n_dropped_saturated": rec.n_saturated, "warnings": list(rec.warnings),
    }
    out["timing_s"] = {"read": t_read, "calibrate": t_cal}
    if args.save:
        args.save.write_text(cal.to_json(indent=2) + "\n", encoding="utf-8")
    trustworthy = bool(cal.converged and cal.observable)
    if args.json:
        print(json.dumps(jsonable(out)))
    else:
        print(summary(out, cal, saved=args.save))
    if not trustworthy:
        why = cal.message or ("not converged" if not cal.converged else "not observable")
        print(f"gravcal: calibration not trustworthy: {' '.join(why.split())}", file=sys.stderr)
        return EXIT_NOT_TRUSTWORTHY
    return EXIT_OK


def _fmt(v: Any, spec: str = ".6g") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return format(float(v), spec)


def summary(out: dict[str, Any], cal: Any, saved: Path | None = None) -> str:
    """A readable account of the result (the --json object holds the same numbers)."""
    inp = out["input"]
    std = cal.std
    lines = [
        f"recording   {inp['file']}: {inp['n_samples']} samples, {inp['duration_s']:.1f} s at {inp['fs_hz']:.6g} Hz",
    ]
    for w in inp["warnings"]:
        lines.append(f"warning     {w}")
    state = ("converged" if cal.converged else "NOT CONVERGED") + ", " + ("observable" if cal.observable else "NOT OBSERVABLE")
    lines.append(f"model       {cal.model}: {out.get('n_windows', cal.n_windows)} quasi-static windows, {state}")
    diagonal = np.allclose(cal.sensitivity, np.diag(np.diag(cal.sensitivity)))
    lines.append("axis        offset [raw]            sensitivity [raw/g]")
    for i, ax in enumerate(AXES):
        o_s = std.get(f"o_{ax}")
        s_s = std.get(f"s_{ax}", std.get(f"s_{ax}{ax}"))
        o = f"{cal.offset[i]:.6g}" + (f" ± {o_s:.2g}" if o_s is not None else " (held)")
        if diagonal:
            s = f"{cal.sensitivity[i, i]:.6g}" + (f" ± {s_s:.2g}" if s_s is not None else " (held)")
        else:
            s = "  ".join(f"{v: .6g}" for v in cal.sensitivity[i])
        lines.append(f"  {ax}         {o:<24}{s}")
    lines.append(
        f"|a| - 1 g   held-out RMS {_fmt(out.get('heldout_rms_mg'), '.3g')} mg "
        f"(contiguous folds of windows), in-sample {_fmt(out.get('insample_rms_mg'), '.3g')} mg"
    )
    if cal.message:
        lines.append(f"note        {cal.message}")
    for note in out.get("notes", []) or []:
        if note and note != cal.message:
            lines.append(f"note        {note}")
    lines.append("convention  a [g] = sensitivity^-1 (raw - offset)")
    if saved:
        lines.append(f"saved       {saved}")
    return "\n".join(lines)
