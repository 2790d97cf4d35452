"""Windows of the block detector (core.fastdetect, what `gravcal calibrate` runs from 2 M samples on)
against the streaming detector (core.detectors, every sample: the daemon's) on the same recordings.

    python bench/detector_agreement.py [--json PATH] [--data DIR]

Simulated sessions (six_position, loetters, 2 h of daily living; the true calibration as to_g) and
the measured recordings in ../shared/data (their nominal scale as to_g: thresholds in g). Per
recording and method: windows found by each, the share of the streaming windows that a block window
overlaps by at least half, the agreement of the samples inside windows (intersection over union),
and the distance of matched window edges [s] (median, 95th percentile).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from gravcal.core import detectors, fastdetect
from gravcal.core.calibration import Calibration
from gravcal.core.samples import raw_triad
from gravcal.core.simulate import simulate
from gravcal.io import datasets

MEASURED = ("imu_tk_xsens", "actigraph_cpw_thermal_chamber", "imucal_ferraris", "mpu6050_tomisuarez/calibration")
SIMULATED = (("six_position", 600.0), ("loetters", 600.0), ("daily_living", 7200.0))


def recordings(data: Path | None):
    for name, duration in SIMULATED:
        sim = simulate(name, seed=1, duration=duration)
        yield f"sim {name} {duration / 60:.0f} min", sim.samples["t"], raw_triad(sim.samples), \
            Calibration.from_dict(sim.truth["calibration"])
    for name in MEASURED:
        try:
            rec = datasets.load(name, data_dir=data)
        except Exception as exc:  # noqa: BLE001 - a missing recording is reported, not fatal
            print(f"{name}: not loaded ({type(exc).__name__}: {exc})")
            continue
        per_g = float(rec.meta.get("acc_per_g", 1.0))
        yield name, np.asarray(rec.t, float), np.asarray(rec.acc, float), Calibration("nominal", np.zeros(3), np.eye(3) * per_g)


def agreement(a, b, n: int, fs: float) -> dict:
    """a: the streaming windows (reference), b: the block windows."""
    def mask(w):
        m = np.zeros(n + 1, dtype=np.int64)
        np.add.at(m, w.start, 1)
        np.add.at(m, w.end, -1)
        return np.cumsum(m)[:n] > 0
    ma, mb = mask(a), mask(b)
    union = int((ma | mb).sum())
    out = {"stream": len(a), "blocks": len(b), "iou": float((ma & mb).sum() / union) if union else 1.0}
    if len(a) and len(b):
        ov = np.minimum(a.end[:, None], b.end[None]) - np.maximum(a.start[:, None], b.start[None])
        j = ov.argmax(axis=1)
        hit = ov[np.arange(len(a)), j] >= 0.5 * (a.end - a.start)
        edges = np.abs(np.concatenate([a.start[hit] - b.start[j[hit]], a.end[hit] - b.end[j[hit]]])) / fs
        out.update(matched=float(hit.mean()), edge_median_s=float(np.median(edges)) if edges.size else None,
                   edge_p95_s=float(np.percentile(edges, 95)) if edges.size else None)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path)
    ap.add_argument("--data", type=Path, default=None)
    args = ap.parse_args()
    rows = []
    print(f"{'recording':<40} {'method':<8} {'stream':>6} {'blocks':>6} {'matched':>7} {'IoU':>6} {'edge p50 s':>10} "
          f"{'edge p95 s':>10}")
    for name, t, raw, cal in recordings(args.data):
        fs = detectors.estimate_fs(t)
        for method in ("lotters", "variance"):
            a = detectors.detect(t, raw, method=method, fs=fs, to_g=cal)
            b = fastdetect.detect(t, raw, method=method, fs=fs, to_g=cal)
            r = {"recording": name, "method": method, "samples": int(len(t)), **agreement(a, b, len(t), fs)}
            rows.append(r)
            f = lambda k: "-" if r.get(k) is None else f"{r[k]:.2f}"  # noqa: E731
            print(f"{name:<40} {method:<8} {r['stream']:6d} {r['blocks']:6d} {f('matched'):>7} {r['iou']:6.3f} "
                  f"{f('edge_median_s'):>10} {f('edge_p95_s'):>10}")
    if args.json:
        args.json.write_text(json.dumps({"bench": "detector_agreement", "rows": rows}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
