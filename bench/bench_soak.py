"""Week-long soak of the daemon's estimator path at accelerated time, not a test.

    python bench/bench_soak.py [--days 7] [--seed 0] [--process-noise 3e-12] [--max-window-s 10] [--adapt-walk] [--adapt-floor] [--quick] [--json PATH]
    python bench/bench_soak.py --controls 20        # false selection rate of the temperature term
    python bench/bench_soak.py --remount-seeds 10   # re-mount detection rate, delay, angle, false alarms

soak: a simulated wearer (core.scenarios daily_living, window level: core.estimators.remount.session_windows)
with a sensor whose offsets and sensitivities drift (the model's offset_drift 1 mg/h and sensitivity_drift
0.02 %/h typical rates, core/model/defaults.py), fed window by window through gravcald's Processor (the
datasheet start, bootstrap, OnlineCalibrator with the configured process noise (``--adapt-walk``: adapted
per parameter; ``--adapt-floor``: the recursion's floor from successive windows), acceptance, re-mount
detector) -- the daemon minus the threads and the socket, as fast as the estimator goes. Every sensor hour
each accepted parameter is compared with the truth at that time: the fraction within the reported 1σ and 2σ
(68 % / 95 % for honest Gaussian uncertainties). Memory: RSS (/proc/self/statm) and the number of live
Python objects (gc) sampled every sensor hour after a warm-up day; the least-squares slope per day is the
figure (flat = bounded). ``--quick``: 2 days.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from support.soak import run_controls, run_remount, run_soak  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--days", type=float, default=7.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--process-noise", type=float, default=3e-12,
                    help="[estimator] process_noise [raw²/s] (3e-12: an offset walk of 2.6 mg/sqrt(h) at 0.04 raw/g; "
                         "with --adapt-walk the start of each parameter's walk)")
    ap.add_argument("--max-window-s", type=float, default=10.0,
                    help="longest quasi-static window [s] (60: a quarter of the windows, the same information, 4x faster)")
    ap.add_argument("--adapt-walk", action="store_true",
                    help="adapt each parameter's walk from --process-noise (core/estimators/adaptive_walk.py; not the "
                         "service's default)")
    ap.add_argument("--adapt-floor", action="store_true",
                    help="estimate the recursion's floor from its residuals (core/estimators/adaptive_floor.py; not the "
                         "service's default)")
    ap.add_argument("--quick", action="store_true", help="2 days instead of --days")
    ap.add_argument("--controls", type=int, default=0, help="only: temperature-term false selections over N seeds")
    ap.add_argument("--remount-seeds", type=int, default=0, help="only: re-mount detection over N seeds")
    ap.add_argument("--progress", action="store_true")
    ap.add_argument("--json", metavar="PATH")
    a = ap.parse_args(argv)
    if a.controls:
        out = run_controls(a.controls)
    elif a.remount_seeds:
        out = run_remount(a.remount_seeds)
    else:
        out = run_soak(2.0 if a.quick else a.days, a.seed, process_noise=a.process_noise, progress=a.progress,
                       max_window_s=a.max_window_s, adapt_walk=a.adapt_walk, adapt_floor=a.adapt_floor)
        out.pop("_processor")
    print(json.dumps(out, indent=2))
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(out, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
