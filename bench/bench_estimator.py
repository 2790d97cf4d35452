"""Speed of the Lötters estimators (python bench/bench_estimator.py [--json PATH]).

Target: LottersRecursive.step <= 50 µs per quasi-static window (6 parameters).
Also times .update(Window) (which builds a Calibration object each call) and a batch fit.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from gravcal.core.calibration import Calibration
from gravcal.core.estimators.lotters import LottersBatch
from gravcal.core.estimators.recursive import LottersRecursive
from gravcal.core.windows import Window, WindowSet


def synthetic_windows(m: int, seed: int = 0) -> WindowSet:
    rng = np.random.default_rng(seed)
    K = np.diag([0.125, 0.12, 0.13])
    o = np.array([0.5, 0.48, 0.52])
    u = rng.normal(size=(m, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    n, sig = 200, 0.01
    cov = np.repeat((sig**2 * np.eye(3))[None], m, 0)
    mean = u @ K.T + o + rng.normal(size=(m, 3)) * sig / np.sqrt(n)
    return WindowSet(mean, cov, np.full(m, float(n)), np.arange(m) * 10.0, np.zeros((m, 0)),
                     np.arange(m), np.arange(m) + 1)


def best_of(fn, repeat=5):
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", metavar="PATH", help="write the figures here")
    args = ap.parse_args(argv)
    res: dict = {}
    m = 5000
    ws = synthetic_windows(m)
    start = Calibration("start", np.array([0.505, 0.475, 0.525]), np.diag([0.127, 0.118, 0.131]))
    cm = ws.cov_of_mean
    for model in ("offsets", "6"):
        for iters in (1, 2):
            def run_steps():
                r = LottersRecursive(start, model, iterations=iters, process_noise=1e-12)
                for i in range(m):
                    r.step(ws.mean[i], cm[i], float(ws.t[i]))
            dt = best_of(run_steps)
            print(f"LottersRecursive.step   model={model:7s} iterations={iters}: {dt / m * 1e6:6.1f} µs/window")
            res[f"recursive_step_{model}_iter{iters}_us"] = dt / m * 1e6
    wins = [Window(int(ws.start[i]), int(ws.end[i]) + 199, ws.t[i], ws.t[i], ws.mean[i], ws.cov[i]) for i in range(1000)]

    def run_updates():
        r = LottersRecursive(start, "6")
        for w in wins:
            r.update(w)
    dt = best_of(run_updates, 3)
    print(f"LottersRecursive.update model=6       (Window in, Calibration out): {dt / len(wins) * 1e6:6.1f} µs/window")
    res["recursive_update_6_us"] = dt / len(wins) * 1e6
    for mm in (100, 1000, 5000):
        sub = ws.subset(np.arange(mm))
        dt = best_of(lambda: LottersBatch("6").fit(sub, start), 3)
        print(f"LottersBatch.fit        model=6       {mm:5d} windows: {dt * 1e3:7.1f} ms")
        res[f"batch_fit_6_{mm}_windows_ms"] = dt * 1e3
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main()
