"""The plain-numpy reference bench_calibrate.py times gravcal against (its own child process).

    python bench/numpy_reference.py FILE.npy [--scale 0.04 --zero 0.5]

What a user would write in ~20 lines instead of installing a calibrator: 10 s windows of the
memory-mapped structured .npy (t, ax, ay, az), a window is still when every axis's std is below
13 mg (van Hees 2014's criterion, through the datasheet scale: ``--scale`` raw units per g), and a
linear least-squares fit of an axis-aligned ellipsoid Σ p_i x_i² + q_i x_i = 1 to the still
window means (offsets and scales per axis, the 6-parameter model). Prints one JSON object:
offset [raw] and sensitivity [raw/g] in gravcal's convention, windows, and timing_s (read+fit).
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

WINDOW = 1000  # samples: 10 s at 100 Hz
CHUNK = 1000  # windows per read (10^6 samples)
STILL_G = 0.013


def reference_fit(path: str, scale: float, zero: float) -> dict:
    rec = np.load(path, mmap_mode="r")
    n = rec.shape[0] // WINDOW * WINDOW
    means, stds = [], []
    for i in range(0, n, CHUNK * WINDOW):
        block = rec[i:min(n, i + CHUNK * WINDOW)]
        x = np.stack([block[c] for c in ("ax", "ay", "az")], axis=1).astype(np.float64).reshape(-1, WINDOW, 3)
        means.append(x.mean(axis=1))
        stds.append(x.std(axis=1))
    m, s = np.concatenate(means), np.concatenate(stds)
    still = m[(s < STILL_G * scale).all(axis=1)]
    A = np.column_stack([still ** 2, still])
    p, q = np.split(np.linalg.lstsq(A, np.ones(len(still)), rcond=None)[0], 2)
    offset = -q / (2 * p)
    gain = 1 + np.sum(p * offset ** 2)  # Σ p_i (x_i - o_i)² = gain on the ellipsoid
    sensitivity = np.sqrt(gain / p)  # raw units per g
    return {"offset": offset.tolist(), "sensitivity": np.diag(sensitivity).tolist(), "n_windows": int(len(still)),
            "model": "6 (numpy reference)", "zero_guess": zero}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file")
    ap.add_argument("--scale", type=float, default=0.04, help="raw units per g (ADXL210 duty cycle: 0.04)")
    ap.add_argument("--zero", type=float, default=0.5, help="raw reading at 0 g (not needed by the fit)")
    args = ap.parse_args()
    t0, c0 = time.perf_counter(), time.process_time()
    out = reference_fit(args.file, args.scale, args.zero)
    out["timing_s"] = {"read": 0.0, "calibrate": time.perf_counter() - t0, "calibrate_cpu": time.process_time() - c0}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
