"""gravcald's CPU per sample with an extended calibration against a plain one (not a test).

    python bench/bench_engine_terms.py [--bus serial] [--clients 1] [--seconds 20] [--repeats 3] [--json PATH]
                                       [--baseline-src DIR]

The same measurement as bench/bench_latency.py (``gravcald --emulate --bus BUS --fs 200``, one raw watcher and
N - 1 more, the process's CPU over the run), with gravcald started from a lab calibration of each model in turn:
plain "6", "6+temperature_offset+supply_offset" (gravcald's default extended terms) and "6" with every term the
online calibrator can publish (daemon/config.py ONLINE_TERMS). The estimator is held from accepting another
calibration ([estimator] min_windows very large), so the start's model corrects every sample; STATUS's model
at the end says it did. Runs interleave (plain, default terms, all terms, plain, ...) so that the machine's
load drifts over all of them alike. Reported per model: the median over the repeats of CPU [% of one core],
µs of CPU per published sample of the whole process and of its acquisition thread (the per-sample path: bus
to sockets; the processing thread's detector and estimator run per window, not per sample), the share of the
samples the C step delivered, and the ratios to plain "6" (the target: within 1.10 for the default terms).

``--baseline-src DIR``: each case is also run with that tree's gravcald (DIR as for bench_latency.py, e.g. an
installed `git archive` of main), interleaved with this tree's, and reported with its ratio to its own plain "6".

First, the engine alone (``--kernel-samples``, 0: skip): Engine.correct on a block of simulated samples per
model, thread CPU per sample [ns], the median of 7 interleaved rounds: what the terms themselves cost.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import tempfile
import time

import numpy as np

from bench_latency import run
from gravcal.core.calibration import Calibration
from gravcal.core.model.terms import CALIBRATION_TERMS, calibration_view
from gravcal.core.simulate import simulate
from gravcal.daemon._fastpath import Engine
from gravcal.daemon.config import ONLINE_TERMS
from gravcal.daemon.processing import engine_params

ACQUISITION = "gravcal-acquisition"  # the per-sample path's thread (daemon/service.py)
# a parameter size [raw units per covariate unit] per (acts_on, covariate): effects of a few mg
SIZE = {("offset", "temp"): 4e-5, ("sensitivity", "temp"): 4e-6, ("offset", "vsupply"): 4e-3,
        ("offset", "time"): 4e-5, ("sensitivity", "time"): 4e-6, ("offset", "accel"): 4e-3}


def calibration(terms: tuple[str, ...]) -> Calibration:
    """The emulator's nominal sensor (ADXL210 datasheet) with ``terms`` at small values."""
    terms = tuple(t for t in CALIBRATION_TERMS if t in terms)
    model = "+".join(("6",) + terms)
    if not terms:
        return Calibration(model, np.full(3, 0.5), 0.04 * np.eye(3))
    rng = np.random.default_rng(1)
    params = {}
    for t in terms:
        view = calibration_view(t)
        params.update({n: float(SIZE[(view.acts_on, view.covariate)] * rng.normal()) for n in view.param_names()})
    meta = {"extended": {"terms": list(terms), "t_ref_c": 25.0, "v_ref": 3.3, "t0_s": 0.0}, "params": params}
    return Calibration(model, np.full(3, 0.5), 0.04 * np.eye(3), metadata=meta)


def kernel_ns(cals: dict[str, Calibration], n: int, rounds: int = 7) -> dict[str, float]:
    """Engine.correct's thread CPU per sample [ns] for each calibration, the median over interleaved rounds."""
    s = simulate("daily_living", seed=1, duration=n / 200.0, fs=200.0).samples
    s["seq"] += 10_000_000  # hours into the session
    acc, gyro, codes = np.empty((s.shape[0], 3)), np.empty(s.shape[0]), np.empty(s.shape[0], np.int8)
    engines = {}
    for name, cal in cals.items():
        engines[name] = Engine()
        engines[name].set_params(engine_params(cal, 200.0, (2048.0, 357.0), (0, True)))
    got: dict[str, list[float]] = {name: [] for name in cals}
    for _ in range(rounds):
        for name, e in engines.items():
            t0 = time.thread_time()
            e.correct(s, acc, gyro, codes)
            got[name].append((time.thread_time() - t0) / s.shape[0] * 1e9)
    return {name: statistics.median(v) for name, v in got.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bus", default="serial")
    ap.add_argument("--clients", type=int, default=1)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", metavar="PATH")
    ap.add_argument("--kernel-samples", type=int, default=400_000)
    ap.add_argument("--no-daemon", action="store_true", help="the engine alone")
    ap.add_argument("--baseline-src", metavar="DIR", help="also run each case with this source tree's gravcald")
    args = ap.parse_args(argv)
    tmp = tempfile.mkdtemp(prefix="bench-engine-terms-")
    conf = os.path.join(tmp, "gravcald.toml")
    with open(conf, "w", encoding="utf-8") as fh:
        fh.write("[estimator]\nmin_windows = 1000000\n")
    cases = {"6": (), "6+temperature_offset+supply_offset": ("temperature_offset", "supply_offset"),
             "6+all online terms": ONLINE_TERMS}
    files = {}
    for name, terms in cases.items():
        files[name] = os.path.join(tmp, f"{len(files)}.json")
        with open(files[name], "w", encoding="utf-8") as fh:
            fh.write(calibration(terms).to_json())
    kernel = kernel_ns({name: calibration(terms) for name, terms in cases.items()}, args.kernel_samples) \
        if args.kernel_samples > 0 else {}
    for name, ns in kernel.items():
        print(f"engine alone {name:36s} {ns:6.1f} ns/sample  x{ns / kernel['6']:.3f} of plain 6", flush=True)
    if args.no_daemon:
        return 0
    trees = {"this tree": None, **({"baseline": args.baseline_src} if args.baseline_src else {})}
    got: dict[tuple[str, str], list[dict]] = {(tree, name): [] for tree in trees for name in cases}
    for k in range(args.repeats):
        for name in cases:
            for tree, src in trees.items():
                r = run(args.bus, args.clients, args.seconds, src,
                        extra_args=("--model", "6", "--lab-calibration", files[name], "--config", conf))
                r["us_per_sample"] = r["cpu_percent"] / 100 * 1e6 / r["samples_per_s"]
                r["us_per_sample_acquisition"] = \
                    r["cpu_percent_by_thread"].get(ACQUISITION, math.nan) / 100 * 1e6 / r["samples_per_s"]
                got[tree, name].append(r)
                in_c = "-" if r["share_in_c"] is None else f"{r['share_in_c']:.3f}"
                print(f"run {k + 1} {tree:9s} {name:36s} model {r['model']}: cpu {r['cpu_percent']:5.2f} %  "
                      f"{r['us_per_sample']:6.1f} µs/sample, acquisition {r['us_per_sample_acquisition']:6.1f}  "
                      f"in C {in_c}", flush=True)
    summary = {}
    for tree in trees:
        base = statistics.median(r["us_per_sample"] for r in got[tree, "6"])
        base_acq = statistics.median(r["us_per_sample_acquisition"] for r in got[tree, "6"])
        for name in cases:
            runs = got[tree, name]
            us = statistics.median(r["us_per_sample"] for r in runs)
            acq = statistics.median(r["us_per_sample_acquisition"] for r in runs)
            share = [r["share_in_c"] for r in runs if r["share_in_c"] is not None]
            summary[f"{tree}: {name}"] = {
                "us_per_sample": us, "us_per_sample_acquisition": acq,
                "cpu_percent": statistics.median(r["cpu_percent"] for r in runs),
                "share_in_c": statistics.median(share) if share else None, "ratio_to_6": us / base,
                "acquisition_ratio_to_6": acq / base_acq, "models": sorted({str(r["model"]) for r in runs})}
            in_c = "-" if not share else f"{statistics.median(share):.3f}"
            print(f"{tree:9s} {name:36s} process {us:6.1f} µs/sample x{us / base:.3f}, acquisition {acq:6.1f} "
                  f"x{acq / base_acq:.3f} of its plain 6 (medians of {len(runs)})  in C {in_c}")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({"bus": args.bus, "clients": args.clients, "seconds": args.seconds, "summary": summary,
                       "engine_ns_per_sample": kernel, "runs": {f"{t}: {n}": v for (t, n), v in got.items()}},
                      fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
