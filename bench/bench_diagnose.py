"""Magnitude floor of diagnose: detection rate vs planted magnitude in an hour of daily living.

    python bench/bench_diagnose.py [--seeds 10]

Window-level sessions (core/diagnosis/synthetic.py: 200 windows over 1 h, 24-34 °C, 1 mg
quasi-static floor); each effect planted at scale x PLANT (x U(1, 2) per channel, random sign).
Prints the detection rate per effect and scale, and the seconds per diagnosis.
"""
from __future__ import annotations

import argparse
import time

from gravcal.core.diagnosis import diagnose_windows
from gravcal.core.diagnosis.synthetic import PLANT, window_session

REG = ("misalignment", "nonlinearity", "temperature_offset", "temperature_sensitivity", "offset_drift",
       "sensitivity_drift")
SCALES = (0.125, 0.25, 0.5, 1.0)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=10)
    args = ap.parse_args()
    t0, n = time.perf_counter(), 0
    print(f"{'effect':26s} {'unit (per axis, x U(1,2))':28s} " + " ".join(f"x{s:<6g}" for s in SCALES))
    units = {"temperature_offset": ("mg/°C", 1e3), "temperature_sensitivity": ("%/°C", 1e2),
             "offset_drift": ("mg/h", 1e3), "sensitivity_drift": ("%/h", 1e2), "misalignment": ("deg", 57.2958),
             "nonlinearity": ("c2 [1/g]", 1.0)}
    for eff in REG:
        rates = []
        for s in SCALES:
            hit = 0
            for seed in range(args.seeds):
                ses = window_session(7000 + seed, {eff: PLANT[eff] * s})
                d = diagnose_windows(ses.ws, ses.start, has_temp=True, candidates=REG, simulate=False)
                hit += eff in [f["effect"] for f in d.findings]
                n += 1
            rates.append(hit / args.seeds)
        u, k = units[eff]
        print(f"{eff:26s} {PLANT[eff] * k:10.4g} {u:17s} " + " ".join(f"{r:7.0%}" for r in rates))
    print(f"{(time.perf_counter() - t0) / n:.3f} s per diagnosis ({n} sessions of 200 windows)")


if __name__ == "__main__":
    main()
