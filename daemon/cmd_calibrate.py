"""``gravcal calibrate FILE.csv|FILE.npy``: offline in-use calibration of a recording.

Reads and validates the recording (daemon.recordings), runs
gravcal.core.pipeline.calibrate_recording (detector -> start -> model order (``--model auto``,
the default: order.select_order) -> Lötters batch estimator -> held-out error over contiguous
folds of windows), or with ``--lab`` bragge.calibrate_lab (six faces, all 12 parameters), and
prints a summary, or with ``--json`` exactly one JSON object (its "order" says which parameters
were fitted and why; model "none" from auto is an error, exit 2). Exit 3 (with the JSON still printed) when the calibration is not
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
    9, 12) plus any extra names the pipeline declares in ``MODELS`` (e.g.
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
                    "(raw units of any scale), optional gx, gy, gz, temp [°C], vsupply [V]; other columns ignored. "
                    ".npy: a structured array with the same field names.",
    )
    p.add_argument("file", type=Path, help="recording: FILE.csv or FILE.npy")
    # No argparse choices: listing them would import the numerics (a second of scipy) for every
    # `gravcal --help`; run() validates and names the known values.
    from gravcal.core.estimators.parameterization import PARAMETERIZATIONS  # numpy only: cheap

    p.add_argument("--model", default="auto", metavar="|".join(("auto",) + tuple(m for m in PARAMETERIZATIONS if "+" not in m)),
                   help="parameters to estimate: auto (default: the largest order the windows determine - offsets, "
                        "6, or the full identifiable set 9/12 - chosen by observability, then BIC and held-out error; "
                        "the output says which and why), offsets only, 6 (sensitivity + offset per axis), 9 (symmetric "
                        "K + offsets: the identifiable part of the 12), 12 (9 updated + the frame of --lab-calibration)")
    p.add_argument("--lab", action="store_true",
                   help="the recording is a six-position lab session: find the faces (no markers) and fit all 12 "
                        "parameters from the known directions (Bragge); same JSON keys, model 12")
    p.add_argument("--lab-calibration", type=Path, metavar="LAB.json",
                   help="a lab calibration (gravcal JSON from --lab --save, or the --lab --json output): its frame is "
                        "held by --model 12 (and auto's full order), and it is the start unless --start is given")
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


def _load_lab(path: Path):
    """The lab calibration of --lab-calibration: a gravcal calibration JSON, or a `calibrate --lab --json` object."""
    from gravcal.core.calibration import Calibration

    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: no such file (--lab-calibration)") from None
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not JSON ({exc.msg} at line {exc.lineno}) (--lab-calibration)") from None
    try:
        cal = Calibration.from_dict(obj["calibration"] if isinstance(obj, dict) and "calibration" in obj else obj)
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{path}: {exc} (--lab-calibration)") from None
    if cal.model != "12":
        raise InputError(f"{path}: a model {cal.model!r} calibration carries no frame; --lab-calibration needs a lab "
                         f"calibration (model 12, from `gravcal calibrate LAB.csv --lab --save LAB.json`)")
    return cal


def run(args: argparse.Namespace) -> int:
    from gravcal.core.pipeline import calibrate_recording

    from .recordings import jsonable, read_recording

    models = model_choices()
    if "+" in args.model:
        from gravcal.core.estimators.extended import extended_class

        try:
            extended_class(args.model)
        except ValueError as exc:
            raise InputError(f"--model: {exc}") from None
    elif args.model not in models:
        from gravcal.core.model.terms import CALIBRATION_TERMS

        raise InputError(f"unknown --model {args.model!r}; choose one of {', '.join(m for m in models if '+' not in m)}, "
                         f"or an order with registered terms, <order>+<term>[+<term>...], terms: "
                         f"{', '.join(CALIBRATION_TERMS)}")
    if args.lab and args.model not in ("auto", "12"):
        raise InputError(f"--lab fits all 12 parameters from the six faces; --model {args.model} does not apply")
    if args.lab and args.lab_calibration:
        raise InputError("--lab computes a lab calibration; --lab-calibration gives one: use one of them")
    lab = _load_lab(args.lab_calibration) if args.lab_calibration else None
    detectors = detector_choices()
    if args.detector not in detectors:
        raise InputError(f"unknown --detector {args.detector!r}; choose one of {', '.join(detectors)}")
    if args.folds < 2:
        raise InputError(f"--folds must be at least 2 (held-out error needs windows left out), got {args.folds}")
    start = _load_start(args.start) if args.start else None
    t0, c0 = time.perf_counter(), time.process_time()
    rec = read_recording(args.file, check_saturation=args.check_saturation)
    t_read, c_read = time.perf_counter() - t0, time.process_time() - c0
    log.info("read %s: %d samples, %.1f s at %.6g Hz in %.2f s", rec.source, rec.n_samples, rec.duration_s, rec.fs, t_read)
    t0, c0 = time.perf_counter(), time.process_time()
    if args.lab:
        from gravcal.core.estimators.bragge import calibrate_lab

        report = calibrate_lab(rec.t, rec.raw, fs=rec.fs, to_g=start)
    else:
        report = calibrate_recording(rec.t, rec.raw, temp=rec.temp, vsupply=rec.vsupply, model=args.model, fs=rec.fs,
                                     detector=args.detector, start=start, folds=args.folds, lab=lab)
    t_cal, c_cal = time.perf_counter() - t0, time.process_time() - c0
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
    # wall and CPU (all threads) seconds: CPU is the figure that holds on a shared machine
    out["timing_s"] = {"read": t_read, "calibrate": t_cal, "read_cpu": c_read, "calibrate_cpu": c_cal}
    if rec.gyro is not None:  # gyro bias/sensitivity from the same quasi-static windows
        from gravcal.core.gyro import gyro_report

        out["gyro"] = gyro_report(rec.t, rec.gyro, report, fs=rec.fs)
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


def _unit(name: str) -> str:
    """An extended term's unit name (core/estimators/extended.py magnitudes) as printed: mg_per_C -> mg/°C."""
    num, _, den = name.partition("_per_")
    num = {"pct": "%", "c2": "c2"}.get(num, num)
    return f"{num}/{'°C' if den == 'C' else den}" if den else num


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
    order = out.get("order") or {}
    if order.get("reason"):
        lines.append(f"order       {order.get('model')}: {order['reason']}")
    if out.get("faces"):
        lines.append("faces       " + ", ".join(f"{f} ({v['windows']} window(s), tilt {v['tilt_deg']:.2g}°)"
                                             for f, v in out["faces"].items()))
    diagonal = np.allclose(cal.sensitivity, np.diag(np.diag(cal.sensitivity)))
    lines.append("axis        offset [raw]            sensitivity [raw/g]")
    for i, ax in enumerate(AXES):
        o_s = std.get(f"o_{ax}")
        s_s = std.get(f"s_{ax}", std.get(f"s_{ax}{ax}", std.get(f"k_{i + 1}{i + 1}")))
        o = f"{cal.offset[i]:.6g}" + (f" ± {o_s:.2g}" if o_s is not None else " (held)")
        if diagonal:
            s = f"{cal.sensitivity[i, i]:.6g}" + (f" ± {s_s:.2g}" if s_s is not None else " (held)")
        else:
            s = "  ".join(f"{v: .6g}" for v in cal.sensitivity[i])
        lines.append(f"  {ax}         {o:<24}{s}")
    ext = out.get("extended") or {}
    for term, mag in (ext.get("magnitudes") or {}).items():
        sd = mag.get("std") or {}
        vals = ", ".join(f"{k} {_fmt(v, '.3g')}" + (f" ± {_fmt(sd[k], '.2g')}" if sd.get(k) is not None else "")
                         for k, v in mag["value"].items())
        lines.append(f"{term:<11} {vals} [{_unit(mag['unit'])}] "
                     f"(offset and sensitivity above hold at {_fmt(ext.get('t_ref_c'), '.3g')} °C)")
    for term, verdict in (out.get("extended_terms") or {}).items():  # model auto: why a term is (not) in
        if isinstance(verdict, dict) and verdict.get("status") != "chosen":
            lines.append(f"{term:<11} {verdict.get('status')}: {verdict.get('reason', '')}")
    if out.get("heldout_scheme") == "leave-one-face-out":
        lines.append(f"|a - known| held-out RMS {_fmt(out.get('heldout_rms_mg'), '.3g')} mg (leave one face out), "
                     f"in-sample {_fmt(out.get('insample_rms_mg'), '.3g')} mg")
    else:
        lines.append(
            f"|a| - 1 g   held-out RMS {_fmt(out.get('heldout_rms_mg'), '.3g')} mg "
            f"(contiguous folds of windows), in-sample {_fmt(out.get('insample_rms_mg'), '.3g')} mg"
        )
    if cal.message:
        lines.append(f"note        {cal.message}")
    for note in out.get("notes", []) or []:
        if note and note not in (cal.message or ""):
            lines.append(f"note        {note}")
    lines.append("convention  a [g] = sensitivity^-1 (raw - offset)")
    if saved:
        lines.append(f"saved       {saved}")
    return "\n".join(lines)
