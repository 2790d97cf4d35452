"""``gravcal calibrate FILE|DIR...``: offline in-use calibration of one recording or a whole study.

One file: reads and validates it (daemon.recordings, any format it recognises), runs
gravcal.core.pipeline.calibrate_recording through daemon.offline (detector -> start -> model order
(``--model auto``, the default: order.select_order) -> Lötters batch estimator -> held-out error over
contiguous folds of windows), or with ``--lab`` bragge.calibrate_lab (six faces, all 12 parameters),
and prints a summary, or with ``--json`` exactly one JSON object (its "order" says which parameters
were fitted and why). Every readable recording gets a verdict: "status" (ok, partial, not_improved, unreliable,
refused; gravcal.core.verdict) and "reason", in the JSON and the summary; exit 0 for ok and partial,
exit 3 (the JSON still printed) for the others.

Several files, a directory, or ``--out``: a study (io.study), one results row per file, on Dask worker
processes forked from this one (``--workers``; io.study_plan) or a dask.distributed cluster (``--scheduler``).
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..jsonbounds import JSONInputError
from ..jsonbounds import loads as bounded_loads
from ..io.report import unit_text
from .summaries import SUMMARIES

TRUSTED = ("ok", "partial")  # statuses that exit 0 (gravcal.core.verdict.TRUSTED; not imported: --help stays light)

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
        "calibrate", help=SUMMARIES["calibrate"],
        description="Offline in-use calibration of recordings. CSV (or .csv.gz): header row; columns t [s], ax, ay, "
                    "az (raw units of any scale), optional gx, gy, gz, temp [°C], vsupply [V]; other columns ignored "
                    "(or mapped with --columns). .npy: a structured array with the same field names; .parquet: the same "
                    "column names. ActiGraph "
                    ".gt3x/.agdc, Axivity .cwa, GENEActiv .bin: through their readers (pip install 'gravcal[formats]'). "
                    "Exactly repeated filler (idle sleep) is excluded and reported.",
    )
    p.add_argument("files", type=Path, nargs="+", metavar="FILE|DIR",
                   help="recording(s): .csv, .csv.gz, .npy, .parquet, .gt3x, .agdc, .cwa, .bin (recognised by content), or a "
                        "directory of them; more than one, a directory, or --out: a study, one results row per file")
    p.add_argument("--columns", metavar="t=NAME,ax=NAME,...",
                   help="map the CSV's own column names, e.g. t=t_unix,ax=x_counts,ay=y_counts,az=z_counts")
    p.add_argument("--out", type=Path, metavar="RESULTS.csv",
                   help="study results, one row per file, written as each finishes; files already in it are skipped")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="study: Dask workers (processes forked from this one), started when timing the first file shows idle "
                        "cores to gain from (default: the CPU count; 0: in this process, no Dask)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="study: an existing dask.distributed scheduler, e.g. "
                                                          "tcp://head-node:8786, instead of local workers")
    p.add_argument("--quiet", action="store_true", help="no progress bar (one is shown only on a terminal)")
    p.add_argument("--report", type=Path, metavar="DIR",
                   help="study: also write DIR/index.html, the study's QC page (error before/after, model orders, "
                        "statuses; one row per file, each linked to its page), drawn from the results file")
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
    p.add_argument("--write", type=Path, metavar="OUT", help="also write the calibrated samples: t [s], a [g] with every "
                   "term applied, flags (saturated, filler) as .npy, .csv, .csv.gz or .parquet (by OUT's ending), the "
                   "calibration in OUT.json (parquet: in its metadata); only for a calibration with status ok or partial")
    p.add_argument("--write-dir", type=Path, metavar="DIR", help="study: write each file's calibrated samples into "
                   "DIR as NAME.calibrated.<--write-format> (see --write); the row names the file")
    p.add_argument("--write-format", default="npy", metavar="npy|csv|csv.gz|parquet",
                   help="study: the format --write-dir writes (default npy)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    p.add_argument("--no-saturation-check", dest="check_saturation", action="store_false",
                   help="do not treat samples piled up at a channel's extreme value as saturated")
    return p


def _read_json(path: Path, option: str):
    """The JSON object a calibration option names, read with bounded nesting and size; one line when it is not."""
    try:
        return bounded_loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{path}: no such file ({option})") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot be read: {exc.strerror or exc} ({option})") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file, expected a calibration JSON ({option})") from None
    except JSONInputError as exc:
        raise InputError(f"{path}: {exc} ({option})") from None


def _load_start(path: Path):
    from gravcal.core.calibration import Calibration

    obj = _read_json(path, "--start")
    try:
        if not isinstance(obj, dict):
            raise ValueError("calibration JSON must be an object")
        return Calibration.from_dict(obj)
    except ValueError as exc:
        raise InputError(f"{path}: {exc} (--start)") from None


def _load_lab(path: Path):
    """The lab calibration of --lab-calibration: a gravcal calibration JSON, or a `calibrate --lab --json` object."""
    from gravcal.core.calibration import Calibration

    obj = _read_json(path, "--lab-calibration")
    try:
        cal = Calibration.from_dict(obj["calibration"] if isinstance(obj, dict) and "calibration" in obj else obj)
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{path}: {exc} (--lab-calibration)") from None
    if cal.model != "12":
        raise InputError(f"{path}: a model {cal.model!r} calibration carries no frame; --lab-calibration needs a lab "
                         f"calibration (model 12, from `gravcal calibrate LAB.csv --lab --save LAB.json`)")
    return cal


def options(args: argparse.Namespace):
    """The checked daemon.offline.Options of the command line."""
    from ..io.offline import Options, check_options

    if args.lab and args.lab_calibration:
        raise InputError("--lab computes a lab calibration; --lab-calibration gives one: use one of them")
    opts = Options(model=args.model, detector=args.detector, folds=args.folds,
                   start=_load_start(args.start) if args.start else None,
                   lab=_load_lab(args.lab_calibration) if args.lab_calibration else None,
                   lab_session=args.lab, columns=args.columns, check_saturation=args.check_saturation)
    check_options(opts)
    return opts


def run(args: argparse.Namespace) -> int:
    if args.report:
        return run_with_report(args)
    from ..io.formats.csvtext import parse_columns

    parse_columns(args.columns)  # a bad mapping is refused before anything is read
    _check_write(args)
    opts = options(args)
    if len(args.files) > 1 or args.out or args.files[0].is_dir():
        from ..io.study import run_study

        if args.save or args.json:
            raise InputError("--save and --json are for one file; a study writes its rows to --out RESULTS.csv")
        if not args.out:
            raise InputError("several files or a directory: name the results file with --out RESULTS.csv")
        return run_study(args.files, args.out, opts, workers=args.workers, scheduler=args.scheduler,
                         quiet=args.quiet, **({"write_dir": args.write_dir, "write_format": args.write_format}
                                             if args.write_dir else {}))
    if args.write_dir:
        raise InputError("--write-dir is for a study; for one file name the output with --write OUT")
    if args.workers is not None or args.scheduler:
        raise InputError("--workers and --scheduler are for a study (several files or a directory with --out)")
    return calibrate_one(args.files[0], opts, args)


def run_with_report(args: argparse.Namespace) -> int:
    """The study, then its QC page drawn from the results (whatever the study's exit status)."""
    if not (len(args.files) > 1 or args.out or args.files[0].is_dir()):
        raise InputError("--report draws a study's results: give several files or a directory with --out RESULTS.csv")
    code = run(argparse.Namespace(**{**vars(args), "report": None}))
    from ..io.study_report import write_report

    page = write_report(args.out, args.report)
    if not args.quiet:
        print(f"gravcal: study report in {page}", file=sys.stderr)
    return code


def calibrate_one(path: Path, opts: Any, args: argparse.Namespace) -> int:
    from ..io import offline
    from .main import request_prompt_exit
    from ..io.recordings import jsonable

    show = not (args.quiet or args.json) and sys.stderr.isatty()
    with offline.progress_bar("reading", show) as bar:
        rec, t_read, c_read = offline.read(path, opts, bar)
    log.info("read %s: %d samples, %.1f s at %.6g Hz in %.2f s", rec.source, rec.n_samples, rec.duration_s, rec.fs, t_read)
    with offline.progress_bar("calibrating", show) as bar:
        report, out = offline.calibrate(rec, opts, (t_read, c_read), bar)
    cal = report.calibration
    status, reason = out["status"], " ".join(str(out.get("reason") or "").split())
    saved = None
    if args.save and status != "refused":  # a refusal has no calibration to save: nothing was fitted
        args.save.write_text(cal.to_json(indent=2) + "\n", encoding="utf-8")
        saved = args.save
    if args.write and status in TRUSTED:
        from ..io.calibrated import write_for

        out["written"] = str(write_for(args.write, rec, cal, columns=opts.columns,
                                       check_saturation=opts.check_saturation, report=jsonable(out)))
    if args.json:
        print(json.dumps(jsonable(out)))
    else:
        print(summary(out, cal, saved=saved) + (f"\nwritten     {out['written']}" if out.get("written") else ""))
    if status not in TRUSTED:
        print(f"gravcal: calibration {status.replace('_', ' ')}: {reason}"
              + (f" (--save {args.save} not written)" if args.save and saved is None else "")
              + (f" (--write {args.write} not written)" if args.write else ""), file=sys.stderr)
    request_prompt_exit()  # the output is printed, --save written and closed: nothing left to tear down
    return EXIT_OK if status in TRUSTED else EXIT_NOT_TRUSTWORTHY


def _check_write(args: argparse.Namespace) -> None:
    """Refuse a calibrated output the command cannot write before anything is computed."""
    from ..io.calibrated import FORMATS, format_of

    if args.write:
        format_of(args.write)
        if not args.write.parent.is_dir():
            raise InputError(f"--write {args.write}: no such directory {args.write.parent}")
    if args.write_dir and args.write_format not in FORMATS:
        raise InputError(f"--write-format {args.write_format!r}: choose one of {', '.join(FORMATS)}")
    if args.write and (len(args.files) > 1 or args.out or args.files[0].is_dir()):
        raise InputError("--write names one output; a study writes one per file with --write-dir DIR")


def _fmt(v: Any, spec: str = ".6g") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return format(float(v), spec)


def summary(out: dict[str, Any], cal: Any, saved: Path | None = None) -> str:
    """A readable account of the result (the --json object holds the same numbers)."""
    inp = out["input"]
    std = cal.std
    lines = [
        f"recording   {inp['file']}: {inp['n_samples']} samples, {inp['duration_s']:.1f} s at {inp['fs_hz']:.6g} Hz"
        + (f" ({inp['format']}, {inp['units']})" if inp.get("format") else ""),
    ]
    for w in inp["warnings"]:
        lines.append(f"warning     {w}")
    lines.append(f"verdict     {out.get('status', 'ok')}: {' '.join(str(out.get('reason') or '').split())}")
    state = ("converged" if cal.converged else "NOT CONVERGED") + ", " + ("observable" if cal.observable else "NOT OBSERVABLE")
    lines.append(f"model       {cal.model}: {out.get('n_windows', cal.n_windows)} quasi-static windows, {state}")
    order = out.get("order") or {}
    said = " ".join(str(out.get("reason") or "").split())  # the verdict's reason: said once
    if order.get("reason") and " ".join(order["reason"].split()) != said:
        lines.append(f"order       {order.get('model')}: {order['reason']}")
    if out.get("faces"):
        lines.append("faces       " + ", ".join(f"{f} ({v['windows']} window(s), tilt {v['tilt_deg']:.2g}°)"
                                             for f, v in out["faces"].items()))
    diagonal = np.allclose(cal.sensitivity, np.diag(np.diag(cal.sensitivity)))
    lines.append("axis        offset [raw]            sensitivity [raw/g]"
                 + ("   (applied as held: not determined here)" if out.get("undetermined") else ""))
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
        lines.append(f"{term:<11} {vals} [{unit_text(mag['unit'])}] "
                     f"(offset and sensitivity above hold at {_fmt(ext.get('t_ref_c'), '.3g')} °C)")
    for term, verdict in (out.get("extended_terms") or {}).items():  # model auto: why a term is (not) in
        if isinstance(verdict, dict) and verdict.get("status") != "chosen":
            lines.append(f"{term:<11} {verdict.get('status')}: {verdict.get('reason', '')}")
    for name, why in (out.get("undetermined") or {}).items():  # one pose: named, not printed as results
        lines.append(f"undetermined {name}: {why}")
    if str(out.get("heldout_scheme") or "").startswith("contiguous per-channel"):
        lines.append(f"per channel held-out RMS {_fmt(out.get('heldout_rms_mg'), '.3g')} mg (each channel's reading in "
                     f"contiguous folds, one pose), in-sample {_fmt(out.get('insample_rms_mg'), '.3g')} mg")
    elif str(out.get("heldout_scheme") or "").startswith("none"):  # not improved: the start, nothing fitted
        lines.append(f"|a| - 1 g   RMS {_fmt(out.get('heldout_rms_mg'), '.3g')} mg over every window under the start "
                     f"(nothing fitted: every window is held out)")
    elif out.get("heldout_scheme") == "leave-one-face-out":
        lines.append(f"|a - known| held-out RMS {_fmt(out.get('heldout_rms_mg'), '.3g')} mg (leave one face out), "
                     f"in-sample {_fmt(out.get('insample_rms_mg'), '.3g')} mg")
    else:
        lines.append(
            f"|a| - 1 g   held-out RMS {_fmt(out.get('heldout_rms_mg'), '.3g')} mg "
            f"(contiguous folds of windows), in-sample {_fmt(out.get('insample_rms_mg'), '.3g')} mg"
        )
    if cal.message and " ".join(cal.message.split()) not in said:
        lines.append(f"note        {cal.message}")
    for note in out.get("notes", []) or []:
        if note and note not in (cal.message or "") and note not in said:
            lines.append(f"note        {note}")
    lines.append("convention  a [g] = sensitivity^-1 (raw - offset)")
    if saved:
        lines.append(f"saved       {saved}")
    return "\n".join(lines)
