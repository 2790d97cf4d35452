"""One recording (a file, or arrays) to its calibration and the ``calibrate --json`` object.

Shared by ``gravcal calibrate`` (one file or a study) and the Python API (``gravcal.calibrate``),
so all three report the same keys.
"""
from __future__ import annotations

import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Optional

from ..errors import InputError
from .recordings import Recording, read_recording

Progress = Optional[Callable[[int, int], None]]  # progress(done, total)


@dataclass
class Options:
    """What a calibration of one recording may be asked (the ``calibrate`` options)."""

    model: str = "auto"
    detector: str = "lotters"
    folds: int = 5
    start: Any = None  # a core Calibration or None
    lab: Any = None  # a lab calibration (model 12) whose frame is held, or None
    lab_session: bool = False  # the recording is a six-face lab session (Bragge)
    columns: str | dict[str, str] | None = None
    check_saturation: bool = True
    exclude_filler: bool = True


def check_options(opts: Options) -> None:
    """Refuse unknown models, detectors and fold counts with the known values named."""
    from gravcal.core.detectors import DETECTORS
    from gravcal.core.estimators.parameterization import PARAMETERIZATIONS

    if "+" in opts.model:
        from gravcal.core.estimators.extended import extended_class

        try:
            extended_class(opts.model)
        except ValueError as exc:
            raise InputError(f"--model: {exc}") from None
    else:
        from gravcal.core import pipeline

        models = list(PARAMETERIZATIONS) + [m for m in getattr(pipeline, "MODELS", ()) if m not in PARAMETERIZATIONS]
        if opts.model not in models:
            from gravcal.core.model.terms import CALIBRATION_TERMS

            raise InputError(f"unknown --model {opts.model!r}; choose one of {', '.join(m for m in models if '+' not in m)}, "
                             f"or an order with registered terms, <order>+<term>[+<term>...], terms: "
                             f"{', '.join(CALIBRATION_TERMS)}")
    if opts.model.split("+", 1)[0] == "12" and opts.lab is None and not opts.lab_session:
        raise InputError("--model 12 holds the frame of a lab calibration: give --lab-calibration LAB.json (from "
                         "`gravcal calibrate LAB.csv --lab --save LAB.json`), or use --model 9 (frame convention R0 = I)")
    if opts.lab_session and opts.model not in ("auto", "12"):
        raise InputError(f"--lab fits all 12 parameters from the six faces; --model {opts.model} does not apply")
    if opts.detector not in DETECTORS:
        raise InputError(f"unknown --detector {opts.detector!r}; choose one of {', '.join(DETECTORS)}")
    if opts.folds < 2:
        raise InputError(f"--folds must be at least 2 (held-out error needs windows left out), got {opts.folds}")


def read(path: str | Path, opts: Options, progress: Progress = None) -> tuple[Recording, float, float]:
    """The validated recording and the wall and CPU seconds its reading took."""
    t0, c0 = time.perf_counter(), time.process_time()
    rec = read_recording(path, check_saturation=opts.check_saturation, columns=opts.columns,
                         exclude_filler=opts.exclude_filler, progress=progress, blocks=not opts.lab_session)
    return rec, time.perf_counter() - t0, time.process_time() - c0


def calibrate(rec: Recording, opts: Options, read_s: tuple[float, float] = (0.0, 0.0),
              progress: Progress = None) -> tuple[Any, dict[str, Any]]:
    """(CalibrationReport, the ``calibrate --json`` object) of a validated recording;
    ``progress(done, total)`` follows calibrate_recording's stages (not a --lab session's)."""
    from gravcal.core.pipeline import calibrate_recording

    from gravcal.core.pipeline import refused_report

    t0, c0 = time.perf_counter(), time.process_time()
    start = opts.start if opts.start is not None or opts.lab is not None else device_start_of(rec)
    if "+" in opts.model:  # a model whose terms need a column the recording lacks: the option is wrong (exit 2)
        from gravcal.core.estimators.order import extended_terms
        from gravcal.core.model.effect import needed_covariates

        have = {"temp": rec.temp is not None, "vsupply": rec.vsupply is not None, "time": True}
        missing = [c for c in needed_covariates(extended_terms(opts.model)) if not have[c]]
        if missing:
            raise InputError(f"--model {opts.model} has terms that need a {' and a '.join(missing)} column; "
                             f"{rec.source} has none")
    if opts.lab_session:  # a six-face session missing a face is refused as bad input (exit 2)
        from gravcal.core.estimators.bragge import calibrate_lab

        report = calibrate_lab(rec.t, rec.raw, fs=rec.fs, to_g=opts.start)
    else:
        report = None
    try:
        if report is None:
            report = calibrate_recording(rec.t, rec.raw, temp=rec.temp, vsupply=rec.vsupply, model=opts.model,
                                         fs=rec.fs, detector=opts.detector, start=start, folds=opts.folds,
                                         lab=opts.lab, progress=progress, blocks=rec.blocks)
    except InputError:
        raise
    except ValueError as exc:  # a readable recording whose windows determine nothing: a verdict, not an error
        report = refused_report(" ".join(str(exc).split()), start if start is not None else opts.lab)
    t_cal, c_cal = time.perf_counter() - t0, time.process_time() - c0
    cal = report.calibration
    out = dict(report.to_json_dict())
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
    if "status" not in out:  # a lab session (Bragge): converged and observable, or not to be trusted
        ok = bool(cal.converged and cal.observable)
        out["status"] = "ok" if ok else "unreliable"
        out["reason"] = f"lab session, model {cal.model}" + ("" if ok else f": {cal.message or 'not converged'}")
    out["input"] = {
        "file": str(rec.source), "format": rec.metadata.get("format"), "units": rec.units,
        "n_samples": rec.n_samples, "duration_s": rec.duration_s, "fs_hz": rec.fs,
        "n_dropped_nonfinite": rec.n_dropped, "n_dropped_saturated": rec.n_saturated,
        "n_excluded_filler": rec.n_filler, "warnings": list(rec.warnings),
    }
    # wall and CPU (all threads) seconds: CPU is the figure that holds on a shared machine
    out["timing_s"] = {"read": read_s[0], "calibrate": t_cal, "read_cpu": read_s[1], "calibrate_cpu": c_cal}
    if rec.gyro is not None:  # gyro bias/sensitivity from the same quasi-static windows
        from gravcal.core.gyro import gyro_report

        out["gyro"] = gyro_report(rec.t, rec.gyro, report, fs=rec.fs)
    return report, out


def device_start_of(rec: Recording) -> Any:
    """The device's own calibration as the start, for a device file whose reader states it
    (``metadata["device_calibration"]``: the K and o of its counts), else its nominal scale
    (``metadata["nominal_per_g"]``: 1 for a file in g, the header's counts per g); None otherwise (the
    pipeline then bootstraps a scale-free start from the data)."""
    meta = rec.metadata if isinstance(rec.metadata, dict) else {}
    device = str(meta.get("device") or meta.get("format") or "device")
    own = meta.get("device_calibration")
    if isinstance(own, dict):  # the device's own calibration of its counts (an .agdc's calibration.json)
        from gravcal.core.estimators.start import device_calibration_start

        return device_calibration_start(own["sensitivity"], own["offset"], device, str(own.get("source", "")))
    scale = meta.get("nominal_per_g")
    if not scale:
        return None
    from gravcal.core.estimators.start import device_start

    return device_start(float(scale), device, rec.units)


@contextmanager
def progress_bar(desc: str, show: bool) -> Iterator[Progress]:
    """A progress(done, total) callback drawing a tqdm bar on stderr, or None when not shown (or
    tqdm is not installed); the bar is closed when the step ends, also on an error."""
    if not show:
        yield None
        return
    try:
        from tqdm.auto import tqdm
    except ImportError:
        yield None
        return
    bar = tqdm(desc=desc, total=1, file=sys.stderr, leave=False)  # tqdm.auto: a widget in a notebook

    def update(done: int, total: int) -> None:
        if bar.total != total:
            bar.total = total
        bar.update(done - bar.n)

    try:
        yield update
    finally:
        bar.close()
