"""``gravcal diagnose FILE [--json] [--report DIR]``: measured data against the simulation.

Reads a recording in the ``calibrate`` format (daemon.recordings), runs
gravcal.core.diagnosis.procedure (baseline fit and held-out error; window-level re-simulation
with the fitted baseline and the measured noise; catalogue terms tested by held-out error and
BIC; extended model refit and held-out gain; re-simulation with it) and prints a summary, or
with ``--json`` exactly one JSON object ``{"findings": [...], "baseline": {...}, "extended":
{...}, "untestable": [...], ...}``. ``--report DIR`` writes DIR/report.md with PNG plots
(matplotlib optional: without it the page says so and lists the numbers only).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from ..errors import InputError
from .summaries import SUMMARIES


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "diagnose", help=SUMMARIES["diagnose"],
        description="Fit the baseline model, re-simulate the session with it, compare measured vs simulated "
                    "statistics, test the catalogue of sensor-model terms (held-out error and BIC), extend "
                    "the model with the terms found and measure the held-out gain.")
    p.add_argument("file", type=Path, help="recording: .csv, .csv.gz, .npy, .parquet, .gt3x, .agdc, .cwa or .bin, recognised "
                                           "by content as calibrate reads it (temp column optional)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    p.add_argument("--report", type=Path, metavar="DIR", help="write DIR/report.md with PNG plots")
    p.add_argument("--replicas", type=int, default=40, help="simulated replicas of the session (default 40)")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated replicas (default 0)")
    p.add_argument("--offer", default="", metavar="TERMS",
                   help="comma-separated terms to test beyond the default catalogue (e.g. thermal_lag: the zero-g "
                        "level following the temperature through a first-order lag, its time constant profiled)")
    p.add_argument("--no-saturation-check", dest="check_saturation", action="store_false",
                   help="do not treat samples piled up at a channel's extreme value as saturated")
    return p


def run(args: argparse.Namespace) -> int:
    from gravcal.core.diagnosis import diagnose

    from ..io.recordings import jsonable, read_recording

    from gravcal.core.diagnosis import CATALOGUE
    from gravcal.core.estimators.extended import EXTRA_TERMS

    if args.replicas < 1:
        raise InputError(f"--replicas must be >= 1, got {args.replicas}")
    offered = [x.strip() for x in args.offer.split(",") if x.strip()]
    unknown = [x for x in offered if x not in EXTRA_TERMS]
    if unknown:
        raise InputError(f"--offer: unknown term(s) {', '.join(unknown)}; terms: {', '.join(sorted(EXTRA_TERMS))}")
    candidates = tuple(CATALOGUE) + tuple(x for x in offered if x not in CATALOGUE)
    from ..io.offline import device_start_of

    rec = read_recording(args.file, check_saturation=args.check_saturation)
    try:
        d = diagnose(rec.t, rec.raw, temp=rec.temp, vsupply=rec.vsupply, fs=rec.fs, replicas=args.replicas,
                     seed=args.seed, candidates=candidates, start=device_start_of(rec))
    except ValueError as exc:
        raise InputError(f"{args.file}: {exc}") from None
    out = d.to_json_dict()
    out["notes"] = list(rec.warnings) + out["notes"]
    if rec.temp is None:
        out["notes"].append("no temp column: temperature terms untestable")
    if args.report is not None:
        from ..io.report import write_report

        page = write_report(d, args.report, source=str(args.file))
        out["report"] = str(page)
    if args.json:
        json.dump(jsonable(out), sys.stdout, indent=2)
        sys.stdout.write("\n")
        return 0
    print(summary(out, str(args.file)))
    return 0


def summary(out: dict[str, Any], name: str) -> str:
    b, e = out["baseline"], out["extended"]
    fmt = lambda x: "n/a" if x is None else f"{x:.3f}"  # noqa: E731
    lines = [f"{name}: {out['n_windows']} quasi-static windows; baseline {b['model']}: held-out {fmt(b['heldout_rms_mg'])} mg"]
    sim = b.get("simulation")
    if sim:
        lines.append(f"  baseline simulation: measured RMS {sim['measured']['rms_mg']:.3f} mg vs simulated "
                     f"{sim['simulated_mean']['rms_mg']:.3f} mg; disagrees on: {', '.join(sim['disagree']) or 'nothing'}")
    verdict = out.get("verdict") or {}
    if verdict.get("status") == "unexplained":
        lines.append(f"  UNEXPLAINED: {verdict['text'].removeprefix('unexplained: ')}")
    for f in out["findings"]:
        group = f.get("group")
        if group:
            lines.append(f"  FOUND {group['text']}")
            lines.append(f"    if {f['effect']} alone: {magnitude_text(f['magnitude'])}")
            continue
        ev = f["evidence"]
        lines.append(f"  FOUND {f['effect']}: {magnitude_text(f['magnitude'])} " + (
            f"(ΔBIC {ev.get('delta_bic')}, nested held-out gain {fmt(ev.get('nested_heldout_gain_mg'))} mg)"
            if ev.get("delta_bic") is not None or "heldout_gain_mg" not in ev else
            f"(one pose, per channel: held-out {fmt(ev['heldout_rms_mg_without'])} → {fmt(ev['heldout_rms_mg_with'])} "
            f"mg on {ev['folds']} contiguous folds)"))
        for axis, why in f["magnitude"].get("undetermined", {}).items():
            lines.append(f"    {axis} undetermined: {why}")
        for note in f["magnitude"].get("notes", []):
            lines.append(f"    note: {note}")
    for f in out.get("partial", []):
        lines.append(f"  explains part, not the cause: {f['effect']} (the residual it leaves is unexplained)")
    if not out["findings"] and verdict.get("status") != "unexplained":
        lines.append("  no significant effect found")
    for w in verdict.get("withdrawn", []):
        lines.append(f"  not named {w['effect']}: {w['why']}")
    if verdict.get("status") != "unexplained" and verdict.get("text"):
        lines.append(f"  residual: {verdict['text']}")
    lines.append(f"  extended {e['model']}: held-out {fmt(e['heldout_rms_mg'])} mg (gain {fmt(e['heldout_gain_mg'])} mg)")
    for u in out["untestable"]:
        lines.append(f"  untestable {u['effect']}: {u['why']}")
    for q, why in (out.get("undetermined") or {}).items():
        lines.append(f"  undetermined {q}: {why}")
    for n in out["notes"]:
        lines.append(f"  note: {n}")
    if out.get("report"):
        lines.append(f"  report: {out['report']}")
    return "\n".join(lines)


def magnitude_text(mag: dict) -> str:
    """Per axis value ± std in the report unit; an undetermined axis says so instead of printing a number."""
    v, sd = mag.get("value", {}), mag.get("std", {}) or {}
    if not isinstance(v, dict):
        return str(v)
    parts = []
    for k, x in v.items():
        if x is None:
            parts.append(f"{k} undetermined")
        else:
            parts.append(f"{k} {x:.4g}" + (f" ± {sd[k]:.2g}" if sd.get(k) is not None else ""))
    return ", ".join(parts) + f" [{mag.get('unit', '')}]"
