"""``gravcal demo``: the in-use calibration running live on a simulated wearer.

The data flow is the service's, with the simulator standing in for the bus::

    source   simulate_blocks: a daily-living session of a sensor drawn off-nominal
      -> RingBuffer            fixed capacity, overwrite-oldest: acquisition and processing decoupled
      -> QuasiStaticDetector   Lötters' norm high-pass/rectify/low-pass detector, streaming -> Windows
      -> OnlineCalibrator      ``feed``: the service's online policy (screen, order the windows
                               determine, batch (re-)seeds, gate, acceptance), the same decisions
                               gravcald makes on the same windows
      -> correction            a = K^-1 (raw - o): the calibrated samples [g] clients would get

The start is the datasheet's nominal part (50 % duty at 0 g, 4 %/g). A part drawn from the
datasheet spreads is typically 0.5-1 g off that: far outside the 5 % region in which the paper's
linearised recursion converges. The online calibrator therefore updates nothing until the windows
determine something (order.is_observable: predicted error <= 10 mg), then fits that order in batch
from the stored window statistics (relinearised, so the start's 1 g does not matter) and recurses
from there; when lying postures add directions the order grows to 6 and the stored windows are
re-fitted. Upright postures alone determine the offsets only: the sensitivities stay at the start's
values, and the offsets absorb their error in the postures seen (reported, never hidden).

The default session starts at 21:00 and runs 6 h, so it contains the evening (upright) and the
first hours of the night (lying with turns): the order grows none -> offsets -> 6. Every line
shows the norm error of the NEXT window under the current calibration, evaluated before that
window is used (held-out), beside the error the true calibration makes on the same window.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from typing import Any, TextIO

import numpy as np

from ..core.estimators.observability import ORDER_LADDER
from ..errors import InputError
from .summaries import SUMMARIES

SOURCE_BLOCK_S = 60.0  # the simulator is cheapest in large blocks (its per-block overhead is ~ms)
AXES = ("x", "y", "z")
ORDER_RANK = ("none", *ORDER_LADDER["9"])  # the orders the demo may reach (no lab frame: full = 9)
MODEL_CHOICES = ("auto", "offsets", "6", "9")
SERVICE_MODEL = {"auto": "9", "offsets": "offsets", "6": "6", "9": "9"}  # --model -> the configured order
K_COVER = 4.0  # "the std covers the error": |error| < K_COVER x reported std (per parameter, ~6e-5 two-sided)
HEADER = ("   sim time   win order    offset x y z [duty]        sensitivity x y z [duty/g]    std o [mg] s [%]"
          "   next win |a|-1g [mg] (truth)   error vs truth o [mg] s [%]")


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "demo", help=SUMMARIES["demo"],
        description="Stream a simulated daily-living session through the quasi-static detector and the online "
                    "Lötters estimator (order by observability) from a deliberately wrong (datasheet nominal) "
                    "start and print the calibration converging, with the held-out norm error of the next windows.",
    )
    p.add_argument("--seed", type=int, default=3, help="seed of the simulated sensor and session (default 3)")
    p.add_argument("--duration", type=float, default=6 * 3600.0, metavar="S",
                   help="simulated seconds (default 21600 = 6 h: an evening, then the first hours of the night)")
    p.add_argument("--start-hour", type=float, default=21.0, metavar="H",
                   help="clock hour at which the session starts (default 21; nights 23:00-07:00 are spent lying "
                        "with turns, which is what determines the sensitivities)")
    p.add_argument("--speed", type=float, default=1800.0, metavar="X",
                   help="simulated time per wall-clock time (default 1800x: 6 h in 12 s; 0 = as fast as possible)")
    p.add_argument("--fs", type=float, default=100.0, help="sample rate [Hz] (default 100)")
    p.add_argument("--model", default="auto",
                   help="highest order the estimator may reach: auto (offsets, 6 or 9 as the windows determine), "
                        "offsets, 6 or 9 (default auto)")
    p.add_argument("--block", type=float, default=10.0, metavar="S",
                   help="seconds of samples the processing side takes from the ring buffer at a time (default 10)")
    p.add_argument("--every", type=int, default=1, metavar="N", help="print every N-th window (default 1)")
    return p


def _time(t: float) -> str:
    t = int(round(t))
    return f"{t // 3600:02d}:{t // 60 % 60:02d}:{t % 60:02d}"


def norm_error_mg(cal, w) -> float:
    """|a| - 1 g [mg] of a window (mean in raw units) under a calibration, at the window's temperature and time."""
    temp = float(w.aux_mean[0]) if len(w.aux_mean) else float("nan")
    return (float(np.linalg.norm(cal.apply(np.asarray(w.mean, dtype=float), temp=temp, t=float(w.t_mid)))) - 1.0) * 1e3


def param_errors(cal, truth) -> tuple[float, float]:
    """Largest offset error [mg] and sensitivity error [% of the true one] against the truth."""
    s_true = np.diag(truth.sensitivity)
    do = np.max(np.abs(cal.offset - truth.offset) / np.abs(s_true)) * 1e3
    ds = np.max(np.abs(np.diag(cal.sensitivity) - s_true) / np.abs(s_true)) * 1e2
    return float(do), float(ds)


def _stds(cal) -> tuple[float, float]:
    """Largest offset std [mg] and sensitivity std [%] of a calibration (nan when not estimated)."""
    std = cal.std
    s = np.abs(np.diag(cal.sensitivity))
    o_std = [std[f"o_{a}"] / s[i] * 1e3 for i, a in enumerate(AXES) if f"o_{a}" in std]
    s_std = [std[f"s_{a}"] / s[i] * 1e2 for i, a in enumerate(AXES) if f"s_{a}" in std]
    return (max(o_std) if o_std else math.nan), (max(s_std) if s_std else math.nan)


def covered(cal, truth, names: tuple[str, ...], k: float = K_COVER) -> bool:
    """Whether every parameter in ``names`` ("o_x", "s_y", ...) is within k reported std of the truth."""
    std = cal.std
    for name in names:
        kind, i = name[0], AXES.index(name[2])
        est, true = (cal.offset[i], truth.offset[i]) if kind == "o" else (cal.sensitivity[i, i], truth.sensitivity[i, i])
        if name not in std or not abs(est - true) < k * std[name]:
            return False
    return True


def service_model(model: str) -> str:
    """The configured order of the service (``estimator.model``) that ``--model`` stands for."""
    if model not in MODEL_CHOICES:
        raise InputError(f"unknown --model {model!r}; choose one of {', '.join(MODEL_CHOICES)}")
    return SERVICE_MODEL[model]


class DemoPipeline:
    """detector -> online calibrator -> correction, one processing block at a time."""

    def __init__(self, fs: float, start, truth, model: str = "auto", out: TextIO | None = None, every: int = 1):
        from gravcal.core.detectors import QuasiStaticDetector
        from gravcal.core.estimators.online import OnlineCalibrator

        self.start, self.truth = start, truth
        self.out = out if out is not None else sys.stdout
        self.every = every
        self.detector = QuasiStaticDetector(fs, to_g=start)
        # the service's calibrator (gravcald's Processor builds the same): one policy, one set of decisions
        self.estimator = OnlineCalibrator.for_service(start, model=service_model(model), fs=fs)
        self.order = "none"
        self.changes: list[tuple[float, int, str, str]] = []  # (t [s], windows so far, order, reason)
        self.heldout_mg: dict[str, list[float]] = {}  # order -> next-window norm errors under that order [mg]
        self.truth_mg: dict[str, list[float]] = {}  # order -> the true calibration's errors on the same windows [mg]
        self.rejected: dict[str, int] = {}  # order -> windows the recursion's gate rejected at that order
        self.n_calibrated = 0
        self._n_lines = 0

    @property
    def calibration(self):
        return self.estimator.calibration

    def process(self, t: np.ndarray, raw: np.ndarray, temp: np.ndarray) -> np.ndarray:
        """One block (t [s], raw triad (N, 3) [duty], temp [°C]) -> calibrated samples (N, 3) [g]."""
        for w in self.detector.update(t, raw, aux=temp[:, None]):  # quasi-static windows
            self.on_window(w)
        calibrated = self.calibration.apply(raw, temp=temp, t=t)  # the correction clients would receive
        self.n_calibrated += calibrated.shape[0]
        return calibrated

    def on_window(self, w) -> None:
        before = self.calibration
        err = norm_error_mg(before, w)  # held out: before the window is used
        err_truth = norm_error_mg(self.truth, w)
        if self.order != "none":
            self.heldout_mg.setdefault(self.order, []).append(err)
            self.truth_mg.setdefault(self.order, []).append(err_truth)
        step = self.estimator.feed(w)
        if step.screened:
            self._line(w, "screened: not quasi-static (the samples move), not used")
            return
        cal = self.estimator.calibration
        n = self.estimator.n_windows
        if self.estimator.model != self.order:
            self.order = self.estimator.model
            self.changes.append((w.t_mid, n, self.order, self.estimator.reason))
            self.detector.to_g = cal  # the detection signal in g of the new calibration
            self._line(w, f"order: {self.order} — {self.estimator.reason}", force=True)
        if self.order == "none":
            self._line(w, f"collecting: nothing determined yet, holding the start; its error on this window "
                          f"{err:+8.1f} mg (truth {err_truth:+5.1f})")
            return
        so, ss = _stds(cal)
        eo, es = param_errors(cal, self.truth)
        gate = step.rejected
        if gate:
            self.rejected[self.order] = self.rejected.get(self.order, 0) + 1
        s_std = "  held" if math.isnan(ss) else f"{ss:6.3f}"
        self._line(w, f"{self.order:>7s}  {np.array2string(cal.offset, precision=5, floatmode='fixed')}  "
                      f"{np.array2string(np.diag(cal.sensitivity), precision=6, floatmode='fixed')}  "
                      f"{so:7.2f} {s_std}     {err:+9.2f} ({err_truth:+6.2f})            {eo:8.2f} {es:6.3f}"
                      + ("  rejected by the gate" if gate else ""))

    def _line(self, w, text: str, force: bool = False) -> None:
        if force or self._n_lines % self.every == 0:
            print(f"   {_time(w.t_mid)} {self.estimator.n_windows:5d}  {text}", file=self.out)
        self._n_lines += 1

    def finish(self) -> dict[str, int]:
        stats = self.detector.stats()  # flush() resets the counters
        for w in self.detector.flush():
            self.on_window(w)
        return stats


def _heldout_line(order: str, e: list[float], et: list[float]) -> str:
    e_, et_ = np.array(e), np.array(et)
    return (f"held-out |a|-1g over the {e_.size} windows at order {order}: median |err| "
            f"{np.median(np.abs(e_)):.2f} mg, RMS {np.sqrt(np.mean(e_ ** 2)):.2f} mg; true calibration on the same "
            f"windows: {np.median(np.abs(et_)):.2f} mg, {np.sqrt(np.mean(et_ ** 2)):.2f} mg")


def summary(pipeline: DemoPipeline, truth, start, out: TextIO) -> int:
    """The final lines: which parameters were determined, their error vs truth against the reported std,
    and the held-out norm errors per order. Returns the exit status (3: nothing determined)."""
    est = pipeline.estimator
    cal = est.calibration
    if est.model == "none":
        print(f"no calibration: the {est.n_windows} windows of this session never determined even the offsets "
              f"({est.reason}); try a longer --duration", file=out)
        return 3
    history = " -> ".join(["none"] + [f"{o} at {_time(t)} ({n} windows)" for t, n, o, _ in pipeline.changes])
    print(f"final  order {est.model}: {history}", file=out)
    print(f"       why {est.model}: {pipeline.changes[-1][3]}", file=out)
    if est.reason != pipeline.changes[-1][3]:
        print(f"       now: {est.reason}", file=out)
    gate = ", ".join(f"{k} at order {o}" for o, k in pipeline.rejected.items()) or "none"
    print(f"       offset {np.round(cal.offset, 5)}  sensitivity {np.round(np.diag(cal.sensitivity), 6)}  "
          f"({est.n_windows} windows, {est.n_reseeds} batch re-fit{'' if est.n_reseeds == 1 else 's'} of the stored windows, {est.n_updates} recursive "
          f"updates; rejected by the gate: {gate})", file=out)
    eo, es = param_errors(cal, truth)
    so, ss = _stds(cal)
    offsets = tuple(f"o_{a}" for a in AXES)
    if est.model == "offsets":
        _, es0 = param_errors(start, truth)
        capped = est.candidates[-1] == "offsets"
        why = "--model offsets" if capped else "not observable from these postures"
        print(f"       determined: offsets. error vs truth: offsets {eo:.2f} mg (reported std: {so:.2f} mg); "
              f"sensitivities held at start ({why}), {es:.3f} % off", file=out)
        if not covered(cal, truth, offsets):
            print(f"       the offsets' error exceeds {K_COVER:g} reported std: with the sensitivities held at the "
                  f"start's values ({es0:.1f} % off), the offsets absorb that error in the postures seen; the std "
                  f"covers the noise only." + ("" if capped else " Lying postures (a night) determine the "
                                               "sensitivities."), file=out)
    else:
        names = offsets + tuple(f"s_{a}" for a in AXES)
        what = "offsets and sensitivities" + (" and cross-axis terms" if est.model in ("9", "12") else "")
        print(f"       determined: {what}. error vs truth: offsets {eo:.2f} mg, sensitivities {es:.3f} % "
              f"(reported std: {so:.2f} mg, {ss:.3f} %)", file=out)
        if not covered(cal, truth, names):
            print(f"       the error exceeds {K_COVER:g} reported std for some parameter: the std is too small",
                  file=out)
    for order in ORDER_RANK[1:]:
        if pipeline.heldout_mg.get(order):
            print(f"       {_heldout_line(order, pipeline.heldout_mg[order], pipeline.truth_mg[order])}", file=out)
    flags = ([] if cal.converged else ["NOT converged"]) + ([] if cal.observable else ["NOT observable"])
    if flags:
        print(f"       calibration {' and '.join(flags)}: {cal.message}", file=out)
        return 3
    return 0


def run(args: argparse.Namespace) -> int:
    from gravcal.core.model.defaults import default_model, triad_truth
    from gravcal.core.estimators.consider import datasheet_held_uncertainty
    from gravcal.core.ringbuffer import RingBuffer
    from gravcal.core.samples import raw_triad
    from gravcal.core.simulate import simulate_blocks

    if not (args.duration > 0 and args.fs > 0 and args.block > 0 and args.speed >= 0 and args.every >= 1):
        raise InputError("--duration, --fs and --block must be > 0, --speed >= 0 and --every >= 1")
    if not 0 <= args.start_hour < 24:
        raise InputError(f"--start-hour must be in [0, 24), got {args.start_hour:g}")
    service_model(args.model)  # a bad --model is refused before the session starts
    out = sys.stdout

    # The sensor: drawn from the datasheet spreads (the truth); the start: the datasheet's nominal part.
    model = default_model(np.random.default_rng(args.seed))
    truth = triad_truth(model)
    # The start says how uncertain it is (the ADXL210 spreads), so parameters held at it (the
    # sensitivities at order offsets) enter the reported std: no confident offsets biased by them.
    start = datasheet_held_uncertainty(triad_truth(default_model(nominal=True)))
    start.model, start.message = "nominal", "datasheet nominal values"
    do0, ds0 = param_errors(start, truth)
    print(f"gravcal demo: seed {args.seed}, {args.duration / 3600:.3g} h daily-living session from "
          f"{int(args.start_hour):02d}:{int(round(args.start_hour % 1 * 60)):02d} at {args.fs:g} Hz, "
          f"speed {'max' if args.speed == 0 else f'{args.speed:g}x'}, model {args.model}", file=out)
    print(f"truth  offset {np.round(truth.offset, 5)} [duty]  sensitivity {np.round(np.diag(truth.sensitivity), 6)} "
          f"[duty/g]", file=out)
    print(f"start  datasheet nominal: offsets off by up to {do0:.0f} mg, sensitivities by up to {ds0:.1f} % "
          f"(the paper's linearisation needs < 5 % = 50 mg)", file=out)
    print(HEADER, file=out)

    block_n = max(1, int(round(args.block * args.fs)))
    source_n = max(block_n, int(round(SOURCE_BLOCK_S * args.fs)))
    bus = simulate_blocks("daily_living", model, seed=args.seed, duration=args.duration, fs=args.fs, block=source_n,
                          day_start_h=args.start_hour)
    ring = RingBuffer(capacity=2 * source_n)  # room for two bus deliveries
    pipeline = DemoPipeline(args.fs, start, truth, model=args.model, out=out, every=args.every)
    wall0 = time.perf_counter()
    t_first: float | None = None
    for delivery in bus:  # 1. the bus delivers samples (SAMPLE_DTYPE rows)
        ring.push(delivery)  # 2. acquisition side: into the ring buffer
        while len(ring):
            block = ring.pop(block_n)  # 3. processing side: a block at a time
            pipeline.process(block["t"], raw_triad(block), block["temp"])  # 4-6. detect, estimate, correct
        out.flush()
        if args.speed > 0:  # pace: simulated time runs `speed` times faster than the wall clock
            t_first = float(delivery["t"][0]) if t_first is None else t_first
            ahead = (float(delivery["t"][-1]) - t_first) / args.speed - (time.perf_counter() - wall0)
            if ahead > 0:
                time.sleep(ahead)
    det_stats = pipeline.finish()
    wall = time.perf_counter() - wall0

    print("", file=out)
    code = summary(pipeline, truth, start, out)
    st = ring.stats()
    print(f"       {st['pushed']} samples through the ring buffer ({st['overwritten']} overwritten), "
          f"{pipeline.n_calibrated} calibrated; detector: {det_stats['windows']} windows; "
          f"{args.duration / wall:.0f}x real time ({wall:.1f} s)", file=out)
    return code
