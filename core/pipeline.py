"""Offline calibration of a recording (what `gravcal calibrate` runs), numerics only.

    bootstrap start (start.bootstrap: raw data in unknown units)
      -> block statistics: ONE pass over the samples (core.fastdetect.block_stats: 0.1 s
         block means and within-block scatters), or those the reading pass computed with its
         validation scan (core.datapass, ``blocks=``)
      -> quasi-static windows (detector on the block means, detection signal in g via the start)
      -> re-detection with the fitted calibration if it moved the start a lot (blocks only)
      -> LottersBatch fit (eq. 11a iterated; C_e eq. 11b)
      -> held-out error on 5 contiguous folds of windows (core.heldout)

Scales to a week at 100 Hz (60 M samples): the samples are read once, in chunks (arrays or
np.memmap columns are never copied whole, mapped pages are released after each chunk), and
only block and window statistics are kept. The bootstrap sees at most
``BOOTSTRAP_MAX_SAMPLES`` samples, taken as evenly spaced contiguous segments.
``detection="stream"`` runs the streaming detectors of core.detectors over every sample
instead (the daemon's detector; ~10x slower offline, same windows within a block or two at
the edges: tests/core/test_fastdetect.py); the default "auto" uses blocks for recordings of
BLOCKS_MIN_SAMPLES samples or more.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from gravcal.core.calibration import Calibration
from gravcal.core.detectors import DETECTORS
from gravcal.core.estimators.lotters import START_TOLERANCE, LottersBatch, relative_difference, start_far_note
from gravcal.core.estimators.observability import is_observable
from gravcal.core.estimators.order import extended_terms, reference_start
from gravcal.core.estimators.order_fit import AUTO_EXTENDED_TERMS, OrderNotDetermined  # noqa: F401 (the pipeline's API)
from gravcal.core.estimators.order_fit import fit_order as _fit_order
from gravcal.core.blas import blas_started_single_threaded, single_threaded_blas as _blas_single_threaded  # noqa: F401
from gravcal.core.estimators.single_pose import single_pose
from gravcal.core.estimators.start import bootstrap
from gravcal.core.fastdetect import BlockStats, block_length, block_stats, detect_blocks, pass_chunks
from gravcal.core.model.effect import needed_covariates
from gravcal.core.model.terms import COVARIATES
from gravcal.core.fold_bootstrap import heldout_own_start
from gravcal.core.heldout import HeldoutResult, heldout_error
from gravcal.core.verdict import Candidate, Verdict, choose, judge, lower_models, uncalibrated
from gravcal.core.windows import MAX_WINDOW_STD_G, WindowSet, window_std_g

log = logging.getLogger(__name__)

CHUNK = 1 << 16  # samples per detector block, detection="stream" (the detector's 5 x 0.5 MB workspace stays in the CPU cache)
DETECTIONS = ("auto", "blocks", "stream")  # core.fastdetect on block statistics, or core.detectors sample by sample
BLOCKS_MIN_SAMPLES = 2_000_000  # detection "auto": blocks from here (5.5 h at 100 Hz; streaming costs ~0.3 s below)
DETECTOR_THREADS = min(2, os.cpu_count() or 1)  # the Lötters detector filters half its channels in a 2nd thread
BOOTSTRAP_MAX_SAMPLES = 300_000  # 50 min at 100 Hz, in BOOTSTRAP_SEGMENTS pieces spread over the recording
BOOTSTRAP_SEGMENTS = 30  # 100 s each at 100 Hz
FALLBACK_DETECTOR = "variance"
REDETECT_CHANGE = 0.02  # re-detect when the fit moved the start by more than 2 % of 1 g (eq. 15-16 units)

MODELS = ("auto",)  # model names calibrate_recording accepts beyond PARAMETERIZATIONS (`gravcal calibrate --model`)


@dataclass
class CalibrationReport:
    calibration: Calibration
    windows: WindowSet
    heldout_rms_mg: float  # RMS |a| - 1 g on windows not used for the fit [mg]
    insample_rms_mg: float  # RMS |a| - 1 g on the fitted windows [mg]
    n_windows: int
    notes: list[str] = field(default_factory=list)
    heldout: HeldoutResult | None = None
    start: Calibration | None = None
    order: dict[str, Any] | None = None  # {"model", "reason", "evidence"}: which order was fitted and why
    extended_terms: dict[str, dict[str, Any]] | None = None  # auto: per AUTO_EXTENDED_TERMS term, status and reason
    verdict: Verdict | None = None  # status (core.verdict.STATUSES) and reason
    single_pose: dict[str, Any] | None = None  # one pose: what it determines and what not (single_pose.SinglePose)

    @property
    def status(self) -> str:
        return self.verdict.status if self.verdict is not None else "ok"

    def to_json_dict(self) -> dict[str, Any]:
        """The `gravcal calibrate --json` object (raw units: offset [raw], sensitivity [raw per g])."""
        cal = self.calibration
        v = self.verdict
        d = {
            "status": v.status if v is not None else "ok",
            "reason": v.reason if v is not None else "",
            "model": cal.model,
            "offset": cal.offset.tolist(),
            "sensitivity": cal.sensitivity.tolist(),
            "std": cal.std,
            "n_windows": int(self.n_windows),
            "heldout_rms_mg": _finite_or_none(self.heldout_rms_mg),
            "insample_rms_mg": _finite_or_none(self.insample_rms_mg),
            "converged": bool(cal.converged),
            "observable": bool(cal.observable),
            "message": cal.message,
            "heldout_scheme": None if self.heldout is None else f"{self.heldout.scheme}:{self.heldout.folds}",
            "heldout_fold_rms_mg": [] if self.heldout is None else [_finite_or_none(x) for x in self.heldout.fold_rms_mg],
            "sigma_floor_g": cal.metadata.get("sigma_floor_g"),
            "reduced_chi2": _finite_or_none(cal.metadata.get("reduced_chi2", float("nan"))),
            "notes": list(self.notes),
            "order": _jsonable(self.order if self.order is not None else
                               {"model": cal.model, "reason": "", "evidence": {}}),
            "extended": extended_summary(cal),
            "extended_terms": _jsonable(self.extended_terms),
            "verdict": _jsonable(v.evidence) if v is not None else {},
            "calibration": cal.to_dict(),
        }
        if self.single_pose is not None:  # named instead of printed: what one pose does not determine
            d["single_pose"] = _jsonable(self.single_pose)
            d["undetermined"] = dict(self.single_pose.get("undetermined", {}))
        return d


def extended_summary(cal: Calibration) -> dict[str, Any] | None:
    """The extended terms of ``cal`` (None for a plain calibration): their parameters in raw units with
    std (e.g. oT_x [raw/°C]), the reference (t_ref_c [°C], t0_s [s]) and per-term magnitudes in physical
    units with std (mg/°C, %/°C, mg/h, ...). ``offset``/``sensitivity`` hold at that reference; the
    held-out error applies the terms at each window's temperature and time."""
    ext = cal.metadata.get("extended") if isinstance(cal.metadata, dict) else None
    if not ext:
        return None

    params, std = cal.metadata.get("params") or {}, cal.std
    names = cal.extended_param_names
    return _jsonable({"terms": list(ext.get("terms", [])), "t_ref_c": ext.get("t_ref_c"), "t0_s": ext.get("t0_s"),
                      "params": {n: params[n] for n in names}, "std": {n: std.get(n) for n in names},
                      "magnitudes": ext.get("magnitudes")})


def _jsonable(x: Any) -> Any:
    """Evidence dicts hold numpy scalars/arrays and non-finite floats: plain JSON values (None for nan/inf)."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items() if not str(k).startswith("_")}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    return x


def _finite_or_none(x: Any) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if np.isfinite(v) else None


class _Columns:
    """Uniform chunked access to raw as an (N, 3) array/memmap or a sequence of three (N,) columns."""

    def __init__(self, raw: Any):
        if isinstance(raw, (list, tuple)):
            if len(raw) != 3:
                raise ValueError(f"raw must be (N, 3) or three columns, got {len(raw)} columns")
            self.cols: Sequence[np.ndarray] | None = [np.asarray(c) if not isinstance(c, np.ndarray) else c for c in raw]
            n = {c.shape[0] for c in self.cols}
            if len(n) != 1 or any(c.ndim != 1 for c in self.cols):
                raise ValueError("raw columns must be 1-D and of equal length")
            self.n = n.pop()
            self.arr = None
        else:
            arr = raw if isinstance(raw, np.ndarray) else np.asarray(raw)
            if arr.ndim != 2 or arr.shape[1] != 3:
                raise ValueError(f"raw must be (N, 3) (ax, ay, az in raw units), got shape {arr.shape}")
            self.arr, self.cols, self.n = arr, None, arr.shape[0]

    def block(self, i: int, j: int) -> np.ndarray:
        """Rows i..j as float64 (j - i, 3) in Fortran order: each channel converted on its own
        into a contiguous row (3x faster than converting interleaved rows of a structured
        memmap), which is the layout the detectors work in (no further copy)."""
        out = np.empty((3, j - i))
        for k in range(3):
            out[k] = self.arr[i:j, k] if self.arr is not None else self.cols[k][i:j]
        return out.T


def _estimate_fs(t: np.ndarray) -> float:
    head = np.asarray(t[: min(len(t), 100_000)], dtype=float)
    dt = np.diff(head[np.isfinite(head)])
    dt = dt[dt > 0]
    if dt.size == 0:
        raise ValueError("cannot estimate the sample rate from t: pass fs")
    return float(1.0 / np.median(dt))


def _bootstrap(t: np.ndarray, cols: _Columns, fs: float) -> Calibration:
    n = cols.n
    if n <= BOOTSTRAP_MAX_SAMPLES:
        return bootstrap(np.asarray(t, dtype=float), cols.block(0, n), fs)
    # evenly spaced contiguous segments, re-timed as one continuous stream (the joins look like
    # movement to a variance detector, which only costs a few seconds per join)
    seg = BOOTSTRAP_MAX_SAMPLES // BOOTSTRAP_SEGMENTS
    starts = np.linspace(0, n - seg, BOOTSTRAP_SEGMENTS).astype(np.int64)
    raw = np.concatenate([cols.block(int(s), int(s) + seg) for s in starts])
    tt = np.arange(raw.shape[0]) / fs
    return bootstrap(tt, raw, fs)


def data_start(t: np.ndarray, raw: Any, fs: float | None = None) -> Calibration:
    """The start calibrate_recording derives from the data when none is given (scale-free bootstrap
    on at most BOOTSTRAP_MAX_SAMPLES, in evenly spaced pieces for long recordings)."""
    t = np.asarray(t, dtype=float)
    return _bootstrap(t, _Columns(raw), float(fs) if fs else _estimate_fs(t))


def covariate_columns(n: int, temp: Any, vsupply: Any) -> Any:
    """The windows' aux channels for the samples, in AUX_COLUMNS order: None, temp (N,) [°C] alone, or
    (N, 2) temp and vsupply [V] (temp NaN when the recording has none)."""
    if vsupply is None:
        return temp
    v = np.asarray(vsupply, dtype=float)
    if v.shape != (n,):
        raise ValueError(f"vsupply must have one value per raw row ({n}), got {v.shape[0] if v.ndim else 'a scalar'}")
    T = np.full(n, np.nan) if temp is None else np.asarray(temp, dtype=float)
    return np.column_stack([T, v])


def _block_stats(t: np.ndarray, cols: _Columns, fs: float, temp: Any, progress: Any = None) -> Any:
    """One pass over the samples: core.fastdetect.BlockStats (mapped pages released as it goes)."""
    if cols.arr is not None:
        arr = cols.arr

        def channel(c: int, i: int, j: int) -> np.ndarray:
            return arr[i:j, c]
    else:
        columns = cols.cols

        def channel(c: int, i: int, j: int) -> np.ndarray:
            return columns[c][i:j]
    release = [a for a in ([t, cols.arr] if cols.arr is not None else [t, *cols.cols]) if isinstance(a, np.ndarray)]
    aux = None if temp is None else (temp if isinstance(temp, np.ndarray) else np.asarray(temp, dtype=float))
    return block_stats(t, channel, cols.n, fs, aux=aux, release=release, progress=progress)


def _check_blocks(bs: BlockStats, n: int, fs: float, aux: Any) -> None:
    """Refuse block statistics of other samples: another rate, length or aux channel count."""
    k = 0 if aux is None else (1 if np.ndim(aux) == 1 else np.shape(aux)[1])
    if not (bs.fs == fs and bs.block_n == block_length(fs) and len(bs) == n // bs.block_n and bs.aux.shape[0] == k):
        raise ValueError(f"blocks are not this recording's: {len(bs)} blocks of {bs.block_n} samples at {bs.fs} Hz with "
                         f"{bs.aux.shape[0]} aux channel(s), for {n} samples at {fs} Hz with {k}")


def _detect(t: np.ndarray, cols: _Columns, fs: float, detector: str, to_g: Calibration, temp: Any,
            detector_kw: dict[str, Any], blocks: Any = None, detection: str = "blocks") -> WindowSet:
    """Quasi-static windows: on block statistics (``blocks``, computed when None) or, with
    detection="stream", by the streaming detector over every sample."""

    if detector not in DETECTORS:
        raise ValueError(f"unknown detector {detector!r}; choose one of {sorted(DETECTORS)}")
    if detection == "blocks":
        bs = blocks if blocks is not None else _block_stats(t, cols, fs, temp)
        return detect_blocks(bs, t, detector, to_g, **detector_kw)
    kw = dict(detector_kw)
    if detector == "lotters" and "threads" not in kw:
        kw["threads"] = DETECTOR_THREADS
    det = DETECTORS[detector](fs, to_g=to_g, **kw)
    windows = []
    for i in range(0, cols.n, CHUNK):
        j = min(i + CHUNK, cols.n)
        aux = None if temp is None else np.asarray(temp[i:j], dtype=float).reshape(j - i, -1)
        windows += det.update(np.asarray(t[i:j], dtype=float), cols.block(i, j), aux)
    windows += det.flush()
    if not windows:
        k = 0 if temp is None else (1 if np.ndim(temp) == 1 else np.shape(temp)[1])
        return WindowSet(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0), np.zeros(0), np.zeros((0, k)),
                         np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    return WindowSet.from_windows(windows)


def screen_windows(ws: WindowSet, cal: Calibration, max_std_g: float) -> tuple[WindowSet, int]:
    """Drop windows whose samples move more than ``max_std_g`` on some axis.

    A detector working on |a| (Lötters eq. 1-2) cannot see a slow rotation at constant |a|: such a
    window averages several postures and its mean lies INSIDE the ellipsoid (|a| of the mean
    shrinks by ~std²/2), which biases the fit. Per-axis spread exposes it.
    """
    keep = window_std_g(ws, cal) <= max_std_g
    return ws.subset(np.flatnonzero(keep)), int((~keep).sum())


class _Steps:
    """Progress of calibrate_recording: ``pass_units`` chunks of the block pass, then 4 stages
    (detection, fit, re-detection (counted when skipped), held-out error)."""

    def __init__(self, callback: Callable[[int, int], None] | None, pass_units: int):
        self.callback, self.pass_units, self.total, self.done = callback, pass_units, pass_units + 4, 0
        self.pass_progress = None if callback is None else self._pass
        self._report(0)

    def _report(self, done: int) -> None:
        self.done = done
        if self.callback is not None:
            self.callback(done, self.total)

    def _pass(self, done: int, _total: int) -> None:
        self._report(done)

    def stage(self) -> None:
        self._report(max(self.done, self.pass_units) + 1)


@_blas_single_threaded
def calibrate_recording(
    t: Any,
    raw: Any,
    *,
    temp: Any = None,
    vsupply: Any = None,
    model: Any = "auto",
    fs: float | None = None,
    detector: str = "lotters",
    start: Calibration | None = None,
    folds: int = 5,
    sigma_floor_g: float | None = None,
    detector_kw: dict[str, Any] | None = None,
    max_window_std_g: float = MAX_WINDOW_STD_G,
    lab: Calibration | None = None,
    detection: str = "auto",
    progress: Callable[[int, int], None] | None = None,
    blocks: BlockStats | None = None,
) -> CalibrationReport:
    """Calibrate a recording: t (N,) [s], raw (N, 3) or three (N,) columns [raw units: ax, ay, az],
    optional temp (N,) [°C] and vsupply (N,) [V] (kept as the windows' aux means). Raises ValueError with a precise
    message on unusable input (no quasi-static windows, too few, bad shapes).

    ``model``: "auto" (default: ``order.select_order`` on the windows chooses offsets, 6, or the full
    identifiable set 9 / 12 and the report's ``order`` says why; OrderNotDetermined, a ValueError, when
    nothing is determined; then AUTO_EXTENDED_TERMS on top of it where testable, observable and warranted,
    each term's verdict in the report's ``extended_terms``), or an order name ("offsets", "6", "9", "12", an extended name). Explicit
    offsets/6/9/12 are refused (ValueError saying what is missing) when the windows cannot determine
    them to Lötters' 3 %. ``lab``: a lab calibration (Bragge, ``gravcal calibrate --lab``) whose frame
    model "12" holds; it is also the start when ``start`` is not given. ``detection``: "blocks"
    (one pass over the samples, detection on 0.1 s block statistics, core.fastdetect), "stream"
    (the streaming detector over every sample, core.detectors), or "auto" (default: blocks from
    BLOCKS_MIN_SAMPLES samples on, where the streaming detector's cost matters; stream below, where
    its sample-exact edges are cheap). ``progress(done, total)``: called with increasing ``done`` up to
    ``total`` (fixed for the call): one unit per chunk of the block pass, then one per stage
    (detection, fit, re-detection, held-out error). ``blocks``: the block statistics of exactly
    these samples at ``fs`` when already computed (daemon.recordings.read_recording(blocks=True):
    the reading pass computes them), used instead of a pass over the samples."""
    cols = _Columns(raw)
    t = t if isinstance(t, np.ndarray) else np.asarray(t)
    if t.ndim != 1 or t.shape[0] != cols.n:
        raise ValueError(f"t must be 1-D with one time per raw row: t {t.shape}, raw has {cols.n} rows")
    if temp is not None and np.shape(temp)[0] != cols.n:
        raise ValueError(f"temp must have one value per raw row ({cols.n}), got {np.shape(temp)[0]}")
    if cols.n < 2:
        raise ValueError(f"recording too short: {cols.n} sample(s)")
    if folds < 2:
        raise ValueError(f"folds must be >= 2, got {folds}")
    if detection not in DETECTIONS:
        raise ValueError(f"unknown detection {detection!r}; choose one of {', '.join(DETECTIONS)}")
    if detection == "auto":
        detection = "blocks" if cols.n >= BLOCKS_MIN_SAMPLES else "stream"
    detector_kw = dict(detector_kw or {})
    fs = _estimate_fs(t) if fs is None else float(fs)
    notes: list[str] = []

    if not (model == "auto" or isinstance(model, str)):
        raise ValueError(f"model must be 'auto' or a model name, not {type(model).__name__}")
    if "+" in model:
        given = {"temp": temp, "vsupply": vsupply, "time": t}
        missing = [c for c in needed_covariates(extended_terms(model)) if given[c] is None]
        if missing:
            raise ValueError(f"model {model!r} has terms that need a {' and a '.join(COVARIATES[c].label for c in missing)} "
                             f"column; the recording has none")
    temp = covariate_columns(cols.n, temp, vsupply)
    user_start = start
    baseline = start if start is not None else lab  # no calibration: what the user had before (None: nothing)
    if start is None and lab is not None:
        start = lab
        notes.append("start: the lab calibration")
    if start is None:
        start = _bootstrap(t, cols, fs)
        notes.append(f"start: {start.message or 'bootstrap'}")
    if detection == "blocks" and blocks is not None:
        _check_blocks(blocks, cols.n, fs, temp)
    else:
        blocks = None
    steps = _Steps(progress, pass_chunks(cols.n, block_length(fs)) if detection == "blocks" and blocks is None else 0)
    if detection == "blocks" and blocks is None:
        blocks = _block_stats(t, cols, fs, temp, steps.pass_progress)

    def detect(name: str, to_g: Calibration, kw: dict[str, Any]) -> WindowSet:
        return _detect(t, cols, fs, name, to_g, temp, kw, blocks, detection)

    ws, dropped = screen_windows(detect(detector, start, detector_kw), start, max_window_std_g)
    if dropped:
        notes.append(f"dropped {dropped} window(s) moving more than {max_window_std_g * 1e3:.0f} mg on an axis")
    if dropped > len(ws) and detector != FALLBACK_DETECTOR:
        # most "still" periods spanned posture changes: the |a| detector cannot see rotations at 1 g
        ws2, dropped2 = screen_windows(detect(FALLBACK_DETECTOR, start, {}), start, max_window_std_g)
        if len(ws2) > len(ws):
            notes.append(f"detector {detector!r} mostly found periods spanning posture changes; used "
                         f"{FALLBACK_DETECTOR!r} instead ({len(ws2)} windows)")
            ws, detector, detector_kw = ws2, FALLBACK_DETECTOR, {}
    steps.stage()
    if len(ws) == 0:
        raise ValueError("no quasi-static windows found in the recording (is it all motion? is the start in the "
                         "right units?)")
    try:
        fitted = _fit_order(ws, model, start, lab, sigma_floor_g, folds)
    except OrderNotDetermined as exc:  # the norm determines nothing: what one pose determines, if it is one
        sp = single_pose(ws, start, folds=folds, why_not_norm=" ".join(str(exc).split()))
        if sp is None:
            raise
        if sp.status != "partial":  # nothing to apply: the refusal, with what the one pose showed
            why = "; ".join(f"{k}: {v}" for k, v in sp.undetermined.items() if k == "temperature slopes")
            raise OrderNotDetermined(f"{exc}; {sp.reason}" + (f" ({why})" if why else "")) from None
        ho = sp.heldout
        return CalibrationReport(sp.calibration, sp.windows, np.nan if ho is None else ho.heldout_rms_mg,
                                 np.nan if ho is None else ho.insample_rms_mg, len(sp.windows), notes, ho, start,
                                 {"model": sp.calibration.model, "reason": sp.reason, "evidence": {}}, None,
                                 Verdict(sp.status, sp.reason), sp.to_json_dict())
    cal = fitted.calibration
    steps.stage()
    change = relative_difference(cal, start)
    if change > REDETECT_CHANGE and cal.converged:
        # the detection signal |a| used the start: with a better calibration the still/moving split changes
        ws2, _ = screen_windows(detect(detector, cal, detector_kw), cal, max_window_std_g)
        if len(ws2) >= fitted.n_params:
            notes.append(f"re-detected windows with the fitted calibration (it moved the start by {change * 100:.1f} % "
                         f"of 1 g): {len(ws)} -> {len(ws2)} windows")
            ws = ws2
            fitted = _fit_order(ws, model, cal, lab, sigma_floor_g, folds)
            cal = fitted.calibration
    steps.stage()
    if user_start is not None:
        off = relative_difference(cal, user_start)
        if off > START_TOLERANCE and "too far off" not in cal.message:
            note = start_far_note(off)
            cal.message = f"{cal.message}; {note}" if cal.message else note
    ho = chosen_heldout(ws, fitted, min(folds, len(ws)), data_start=baseline is None)
    notes += ho.notes
    # the verdict: no order returned as good that holds out worse than a lower one or than no calibration
    chosen = Candidate(fitted.model, cal, ho, fitted)
    lower = _lower_candidates(ws, fitted.model, start, lab, sigma_floor_g, folds, from_data=baseline is None)
    pick, guard_note = choose(chosen, lower, auto=model == "auto")
    none = None if baseline is None else uncalibrated(baseline, ws)
    verdict = judge(pick, baseline=none, baseline_name=_baseline_name(baseline), guard_note=guard_note,
                    auto=model == "auto", baseline_origin_unknown=user_start is not None
                    and user_start.metadata.get("method") != "device_nominal")
    verdict.evidence["heldout_by_order"] = {c.model: c.heldout_mg for c in [*lower, chosen]}
    if baseline is None and "offsets" in lower_models(fitted.model):
        verdict.evidence["not_compared"] = {"offsets": "its held sensitivities would be the bootstrap's, fitted to "
                                                       "these same windows: no lower order"}
    order = dict(fitted.order or {})
    terms = fitted.extended_terms
    if pick is not chosen:
        cal, ho = pick.calibration, pick.heldout
        order["model"], order["reason"] = pick.model, f"{order.get('reason', '')}; {guard_note}"
        terms = {k: ({**v, "status": "not warranted", "reason": f"{v.get('reason', '')}; dropped: the held-out "
                                                               f"guard returned {pick.model}"}
                     if v.get("status") == "chosen" else v) for k, v in (terms or {}).items()} or terms
    if verdict.status == "not_improved":  # the start is what the user gets: its error is the one reported
        cal, ho = unchanged(baseline, verdict.reason), none.heldout
    steps.stage()
    log.info("calibrated %d windows (order %s, %s): held-out %.3g mg, in-sample %.3g mg", len(ws), order.get("model"),
             verdict.status, ho.heldout_rms_mg, ho.insample_rms_mg)
    return CalibrationReport(cal, ws, ho.heldout_rms_mg, ho.insample_rms_mg, len(ws), notes, ho, start, order,
                             terms, verdict)


def refused_report(reason: str, start: Calibration | None) -> CalibrationReport:
    """The report of a recording whose windows determine nothing (``reason``: the ValueError's message of
    calibrate_recording): the start returned unchanged (when there is one; else an identity marked "none",
    not converged, not observable), status "refused"."""
    if start is None:
        cal = Calibration("none", np.zeros(3), np.eye(3), converged=False, observable=False, message=reason)
    else:
        cal = unchanged(start, reason)
        cal.converged, cal.observable = False, False
    empty = WindowSet(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0), np.zeros(0), np.zeros((0, 0)),
                      np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    return CalibrationReport(cal, empty, float("nan"), float("nan"), 0, [], None, start,
                             {"model": "none", "reason": reason, "evidence": {}}, None, Verdict("refused", reason))


def _baseline_name(baseline: Calibration | None) -> str:
    if baseline is None:
        return ""
    return baseline.message or f"the start ({baseline.model})"


def unchanged(start: Calibration, reason: str) -> Calibration:
    """The start returned as the result (nothing fitted improved on it), saying why."""
    return Calibration(start.model, start.offset, start.sensitivity, covariance=start.covariance.copy(),
                       param_names=list(start.param_names), n_windows=start.n_windows, converged=start.converged,
                       observable=start.observable, message=reason, metadata=dict(start.metadata))


def _lower_candidates(ws: WindowSet, model: str, start: Calibration, lab: Calibration | None,
                      sigma_floor_g: float | None, folds: int, from_data: bool) -> list[Candidate]:
    """The observable orders below ``model`` (verdict.lower_models), each fitted on all windows and scored on
    the same contiguous folds as the chosen one. An offsets-only fit holds the start's sensitivities: when
    the start came from these windows (the bootstrap's ellipsoid fit) it is no lower order (its
    sensitivities were fitted to the same windows) and is not compared."""
    out = []
    for k in lower_models(model):
        if k == "offsets" and from_data:
            continue
        fit_start = start if k == "offsets" else reference_start(k, start, lab)
        try:
            ok, _ = is_observable(ws, fit_start, k)
            if not ok:
                continue
            est = LottersBatch(k, sigma_floor_g=sigma_floor_g)
            fit = est.fit(ws, fit_start)
            ho = heldout_error(ws, k, scheme="contiguous", folds=min(folds, len(ws)), start=fit_start, full_fit=fit,
                               estimator=est)
        except (ValueError, np.linalg.LinAlgError) as exc:
            log.info("guard: order %s not scored (%s)", k, exc)
            continue
        out.append(Candidate(k, fit, ho))
    return out



def chosen_heldout(ws: WindowSet, fitted: Any, folds: int, *, data_start: bool) -> HeldoutResult:
    """The held-out error of the fitted order (order_fit.Fitted) on contiguous folds. Its folds start from
    ``fitted.fold_start``, except an offsets-only fit from a start drawn from these windows (``data_start``:
    the bootstrap): its held sensitivities came from every window, the held-out fold's included, so each fold
    bootstraps its own from its training windows (``heldout_own_start``)."""
    if data_start and fitted.model.split("+", 1)[0] == "offsets":
        return heldout_own_start(ws, fitted.estimator, folds, full_fit=fitted.calibration)
    return heldout_error(ws, fitted.model, scheme="contiguous", folds=folds, start=fitted.fold_start,
                         full_fit=fitted.calibration, estimator=fitted.estimator)

