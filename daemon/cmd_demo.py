"""``gravcal demo``: the in-use calibration running live on a simulated wearer.

The data flow is the service's, with the simulator standing in for the bus::

    source   simulate_blocks: a daily-living session of a sensor drawn off-nominal
      -> RingBuffer            fixed capacity, overwrite-oldest: acquisition and processing decoupled
      -> QuasiStaticDetector   Lötters' norm high-pass/rectify/low-pass detector, streaming -> Windows
      -> LottersRecursive      one linearised MVU update per window (eq. 9-14)
      -> correction            a = K^-1 (raw - o): the calibrated samples [g] clients would get

The start is the datasheet's nominal part (50 % duty at 0 g, 4 %/g). A part drawn from the
datasheet spreads is typically 0.5-1 g off that: far outside the 5 % region in which the paper's
linearisation converges, and a recursion started there locks onto a wrong solution that fits
the few postures seen so far. So the demo first collects windows, and as soon as they
determine every parameter (a batch fit from an ellipsoid-fit start is converged and
observable: no pre-calibration needed, issue item 7) it seeds the recursion with that fit,
which then tracks the calibration window by window. Every line shows the norm error of the
NEXT window under the current calibration, evaluated before that window is used (held-out),
beside the error the true calibration makes on the same window.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from typing import Any, TextIO

import numpy as np

from .errors import InputError

SEED_MIN_WINDOWS = 9  # below this the batch fit (and its ellipsoid start) cannot determine 6+ parameters
NOVEL_DEG = 15.0  # a window whose direction is this far from all earlier ones may complete the coverage
SEED_RETRY_EVERY = 25  # ... otherwise retry the seed fit every this many windows
SOURCE_BLOCK_S = 60.0  # the simulator is cheapest in large blocks (its per-block overhead is ~ms)
AXES = ("x", "y", "z")
HEADER = ("   sim time   win  offset x y z [duty]          sensitivity x y z [duty/g]    std o [mg] s [%]"
          "   next win |a|-1g [mg] (truth)   error vs truth o [mg] s [%]")


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "demo", help="simulated wearer -> ring buffer -> detector -> recursive estimator, converging live",
        description="Stream a simulated daily-living session through the quasi-static detector and the recursive "
                    "Lötters estimator from a deliberately wrong (datasheet nominal) start and print the "
                    "calibration converging, with the held-out norm error of the next windows.",
    )
    p.add_argument("--seed", type=int, default=1, help="seed of the simulated sensor and session (default 1)")
    p.add_argument("--duration", type=float, default=2 * 3600.0, metavar="S",
                   help="simulated seconds (default 7200 = 2 h, with one lie-down episode)")
    p.add_argument("--speed", type=float, default=600.0, metavar="X",
                   help="simulated time per wall-clock time (default 600x: 2 h in 12 s; 0 = as fast as possible)")
    p.add_argument("--fs", type=float, default=100.0, help="sample rate [Hz] (default 100)")
    p.add_argument("--model", default="6", help="parameters the estimator tracks (default 6)")
    p.add_argument("--block", type=float, default=10.0, metavar="S",
                   help="seconds of samples the processing side takes from the ring buffer at a time (default 10)")
    p.add_argument("--every", type=int, default=1, metavar="N", help="print every N-th window (default 1)")
    return p


def _time(t: float) -> str:
    t = int(round(t))
    return f"{t // 3600:02d}:{t // 60 % 60:02d}:{t % 60:02d}"


def norm_error_mg(cal, mean: np.ndarray) -> float:
    """|a| - 1 g [mg] of a window mean (raw units) under a calibration."""
    return (float(np.linalg.norm(cal.apply(mean))) - 1.0) * 1e3


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


class DemoPipeline:
    """detector -> (seed) -> recursive estimator -> correction, one processing block at a time."""

    def __init__(self, fs: float, start, truth, model: str = "6", out: TextIO | None = None, every: int = 1):
        from gravcal.core.detectors import QuasiStaticDetector

        self.start, self.truth, self.model = start, truth, model
        self.out = out if out is not None else sys.stdout
        self.every = every
        self.detector = QuasiStaticDetector(fs, to_g=start)
        self.estimator = None  # LottersRecursive, once seeded
        self.windows: list = []  # every window so far (the seed fit uses them)
        self._novel: list[np.ndarray] = []  # directions (under the start) of the windows that widened the coverage
        self._since_try = 0
        self.seeded_at: float | None = None
        self.heldout_mg: list[float] = []  # next-window norm errors after seeding [mg]
        self.truth_mg: list[float] = []  # the true calibration's errors on the same windows [mg]
        self.n_calibrated = 0
        self._n_lines = 0

    @property
    def calibration(self):
        return self.start if self.estimator is None else self.estimator.calibration

    def process(self, t: np.ndarray, raw: np.ndarray, temp: np.ndarray) -> np.ndarray:
        """One block (t [s], raw triad (N, 3) [duty], temp [°C]) -> calibrated samples (N, 3) [g]."""
        for w in self.detector.update(t, raw, aux=temp[:, None]):  # quasi-static windows
            self.on_window(w)
        calibrated = self.calibration.apply(raw)  # the correction clients would receive
        self.n_calibrated += calibrated.shape[0]
        return calibrated

    def on_window(self, w) -> None:
        from gravcal.core.estimators.lotters import LottersRecursive

        err = norm_error_mg(self.calibration, w.mean)  # held out: before the window is used
        err_truth = norm_error_mg(self.truth, w.mean)
        self.windows.append(w)
        if self.estimator is None:
            seeded = self._try_seed(w)
            if seeded is None:
                self._line(w, f"collecting: the windows do not determine the {self.model} parameters yet; "
                              f"the start's error on this window {err:+8.1f} mg (truth {err_truth:+5.1f})")
                return
            self.estimator = LottersRecursive(seeded, model=self.model)
            self.detector.to_g = seeded  # the detection signal in g of the new calibration
            self.seeded_at = w.t_mid
            self._line(w, f"seeded: a batch fit (ellipsoid start) of these {len(self.windows)} windows is converged "
                          f"and observable; the recursion takes over", force=True)
            return
        accepted = self.estimator.step(w.mean, w.cov / w.n, w.t_mid)  # eq. 9-14, one window
        self.heldout_mg.append(err)
        self.truth_mg.append(err_truth)
        cal = self.estimator.calibration
        so, ss = _stds(cal)
        eo, es = param_errors(cal, self.truth)
        self._line(w, f"{np.array2string(cal.offset, precision=5, floatmode='fixed')}  "
                      f"{np.array2string(np.diag(cal.sensitivity), precision=6, floatmode='fixed')}  "
                      f"{so:7.2f} {ss:6.3f}     {err:+9.2f} ({err_truth:+6.2f})            {eo:8.2f} {es:6.3f}"
                      + ("" if accepted else "  rejected by the gate"), force=not accepted)

    def _line(self, w, text: str, force: bool = False) -> None:
        if force or self._n_lines % self.every == 0:
            print(f"   {_time(w.t_mid)} {len(self.windows):5d}  {text}", file=self.out)
        self._n_lines += 1

    def _try_seed(self, w):
        """The batch fit of the windows so far, or None while they do not determine the parameters.
        Tried when a window widens the orientation coverage (and every SEED_RETRY_EVERY windows)."""
        from gravcal.core.estimators.lotters import LottersBatch
        from gravcal.core.windows import WindowSet

        d = self.start.apply(w.mean)
        d = d / np.linalg.norm(d)
        novel = all(np.degrees(np.arccos(np.clip(d @ e, -1, 1))) > NOVEL_DEG for e in self._novel)
        if novel:
            self._novel.append(d)
        self._since_try += 1
        if len(self.windows) < SEED_MIN_WINDOWS or not (novel or self._since_try >= SEED_RETRY_EVERY):
            return None
        self._since_try = 0
        try:
            cal = LottersBatch(self.model).fit(WindowSet.from_windows(self.windows))
        except ValueError:
            return None
        return cal if (cal.converged and cal.observable) else None

    def finish(self) -> dict[str, int]:
        stats = self.detector.stats()  # flush() resets the counters
        for w in self.detector.flush():
            self.on_window(w)
        return stats


def run(args: argparse.Namespace) -> int:
    from gravcal.core.model.defaults import default_model, triad_truth
    from gravcal.core.ringbuffer import RingBuffer
    from gravcal.core.samples import raw_triad
    from gravcal.core.simulate import simulate_blocks

    if not (args.duration > 0 and args.fs > 0 and args.block > 0 and args.speed >= 0 and args.every >= 1):
        raise InputError("--duration, --fs and --block must be > 0, --speed >= 0 and --every >= 1")
    out = sys.stdout

    # The sensor: drawn from the datasheet spreads (the truth); the start: the datasheet's nominal part.
    model = default_model(np.random.default_rng(args.seed))
    truth = triad_truth(model)
    start = triad_truth(default_model(nominal=True))
    start.model, start.message = "nominal", "datasheet nominal values"
    do0, ds0 = param_errors(start, truth)
    print(f"gravcal demo: seed {args.seed}, {args.duration / 3600:.3g} h daily-living session at {args.fs:g} Hz, "
          f"speed {'max' if args.speed == 0 else f'{args.speed:g}x'}", file=out)
    print(f"truth  offset {np.round(truth.offset, 5)} [duty]  sensitivity {np.round(np.diag(truth.sensitivity), 6)} "
          f"[duty/g]", file=out)
    print(f"start  datasheet nominal: offsets off by up to {do0:.0f} mg, sensitivities by up to {ds0:.1f} % "
          f"(the paper's linearisation needs < 5 % = 50 mg)", file=out)
    print(HEADER, file=out)

    block_n = max(1, int(round(args.block * args.fs)))
    source_n = max(block_n, int(round(SOURCE_BLOCK_S * args.fs)))
    bus = simulate_blocks("daily_living", model, seed=args.seed, duration=args.duration, fs=args.fs, block=source_n)
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
    if pipeline.estimator is None:
        print(f"no calibration: the {len(pipeline.windows)} windows of this session never determined the "
              f"{args.model} parameters (too few orientations); try a longer --duration", file=out)
        return 3
    cal = pipeline.estimator.calibration
    eo, es = param_errors(cal, truth)
    so, ss = _stds(cal)
    print(f"final  offset {np.round(cal.offset, 5)}  sensitivity {np.round(np.diag(cal.sensitivity), 6)}  "
          f"(seeded at {_time(pipeline.seeded_at)}, then {cal.n_windows} windows used, "
          f"{pipeline.estimator.n_rejected} rejected)", file=out)
    print(f"       error vs truth: offsets {eo:.2f} mg, sensitivities {es:.3f} % "
          f"(reported std: {so:.2f} mg, {ss:.3f} %)", file=out)
    if pipeline.heldout_mg:
        e, et = np.array(pipeline.heldout_mg), np.array(pipeline.truth_mg)
        print(f"       held-out |a|-1g over the {e.size} windows after seeding: median |err| "
              f"{np.median(np.abs(e)):.2f} mg, RMS {np.sqrt(np.mean(e ** 2)):.2f} mg; true calibration on the same "
              f"windows: {np.median(np.abs(et)):.2f} mg, {np.sqrt(np.mean(et ** 2)):.2f} mg "
              f"(what remains is the windows' own motion and noise)", file=out)
    st = ring.stats()
    print(f"       {st['pushed']} samples through the ring buffer ({st['overwritten']} overwritten), "
          f"{pipeline.n_calibrated} calibrated; detector: {det_stats['windows']} windows; "
          f"{args.duration / wall:.0f}x real time ({wall:.1f} s)", file=out)
    flags = ([] if cal.converged else ["NOT converged"]) + ([] if cal.observable else ["NOT observable"])
    if flags:
        print(f"       calibration {' and '.join(flags)}: {cal.message}", file=out)
        return 3
    return 0
