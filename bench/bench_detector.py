"""Throughput of the quasi-static detectors in block mode on one core.

Target: >= 5 M samples/s per detector (a week at 100 Hz = 60 M samples in ~12 s).
Run: python bench/bench_detector.py [--samples N] [--block B ...]
Prints wall-clock and CPU-time rates (CPU time is the fairer figure on a shared machine).
"""
from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one core: no threaded BLAS
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from gravcal.core.calibration import Calibration  # noqa: E402
from gravcal.core.detectors import MovingVarianceDetector, QuasiStaticDetector  # noqa: E402


def synthetic_counts(n: int, fs: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Counts (4096/g + 32768): 20 s postures alternating with 5 s of 2 Hz shaking."""
    t = np.arange(n) / fs
    period = int(25 * fs)
    moving = (np.arange(n) % period) >= int(20 * fs)
    f = np.tile([0.0, 0.0, 1.0], (n, 1))
    f[moving] += 0.3 * np.sin(2 * np.pi * 2.0 * t[moving, None] * np.array([1.0, 1.3, 0.7]))
    f += rng.normal(0, 0.0045, f.shape)
    return t, 4096.0 * f + 32768.0


def bench(cls, t, raw, aux, block, **kw) -> tuple[float, float, int]:
    """(samples/s by wall clock, samples/s by this process's CPU time, windows found)."""
    det = cls(100.0, to_g=Calibration.nominal(np.full(3, 32768.0), 4096.0), **kw)
    t0, c0 = time.perf_counter(), time.process_time()
    n_win = 0
    for i in range(0, t.shape[0], block):
        n_win += len(det.update(t[i:i + block], raw[i:i + block], aux[i:i + block]))
    n_win += len(det.flush())
    n = t.shape[0]
    return n / (time.perf_counter() - t0), n / (time.process_time() - c0), n_win


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=10_000_000)
    ap.add_argument("--block", type=int, nargs="*", default=[256, 4096, 65536])
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    t, raw = synthetic_counts(args.samples, 100.0, rng)
    aux = np.full((t.shape[0], 1), 25.0)
    print(f"{args.samples:,} samples at 100 Hz ({args.samples / 100 / 3600:.1f} h), counts + Calibration to_g, 1 aux")
    variants = [("QuasiStaticDetector", QuasiStaticDetector, {}),
                ("  per_axis=False (eq. 1)", QuasiStaticDetector, {"per_axis": False}),
                ("MovingVarianceDetector", MovingVarianceDetector, {})]
    for name, cls, kw in variants:
        for block in args.block:
            wall, cpu, n_win = bench(cls, t, raw, aux, block, **kw)
            print(f"{name:24s} block {block:6d}: {wall / 1e6:6.2f} M samples/s wall, "
                  f"{cpu / 1e6:6.2f} M samples/s CPU  ({n_win} windows)")


if __name__ == "__main__":
    main()
