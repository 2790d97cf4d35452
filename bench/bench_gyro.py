"""Gyro in use: Scapellato's step-height search vs pose-to-pose vs the truth, across seeds.

For each seed one ENC-03J board is drawn (datasheet spreads: scale factor +-20 %), worn on the
foot instep for (a) 20 everyday sagittal foot poses and (b) 10 foot placements onto 17 cm
steps. Both methods estimate the sensitivity [counts per rad/s]; the table gives their error
against the truth in units of their own reported std and in %. Also: time per calibration.

    python bench/bench_gyro.py [n_seeds]
"""
from __future__ import annotations

import sys
import time

import numpy as np

from gravcal.core.detectors import detect
from gravcal.core.gyro import calibrate_gyro
from gravcal.core.gyro.footmotion import foot_poses, simulate_foot, stair_climb
from gravcal.core.gyro.scapellato import placements, step_height_search

FS = 100.0
NOMINAL = 357.36  # counts per rad/s: 0.67 mV/(°/s) x 7.5 x 4096 / 3.3 V


def main(n_seeds: int = 10) -> None:
    rows = []
    t_pose = t_step = 0.0
    for seed in range(n_seeds):
        s = simulate_foot(foot_poses(np.random.default_rng(1000 + seed), n_poses=20), seed)
        tr = s.truth
        S = tr["sensitivity_counts_per_rad_s"]
        ws = detect(s.t, s.acc_raw, fs=FS, to_g=s.acc_calibration)
        t0 = time.perf_counter()
        pose = calibrate_gyro(s.t, s.gyro, ws, s.acc_calibration, fs=FS, hp_hz=tr["hp_hz"], axis=tr["axis"],
                              range_rad_s=tr["range_rad_s"], rails=(0, 4095), folds=0)
        t_pose += time.perf_counter() - t0
        sc = stair_climb(np.random.default_rng(2000 + seed), n_steps=10, step_height_m=0.17)
        st = simulate_foot(sc.motion, seed)  # the same board (model drawn from the same seed)
        t0 = time.perf_counter()
        pl = placements(st.gyro, st.acc_raw, st.acc_calibration, sc.stances, bias=pose.bias[0], fs=FS,
                        hp_hz=tr["hp_hz"], acc_lowpass_hz=st.model["analog_lowpass"].f3db_hz[:3])
        step = step_height_search(pl, 0.17, start=NOMINAL)
        t_step += time.perf_counter() - t0
        rows.append((seed, S, S / NOMINAL - 1, pose.sensitivity[0, 0], pose.std["S"], step.sensitivity, step.std,
                     pose.bias[0] - tr["bias_counts"], pose.bias_std[0]))
    print(f"{'seed':>4} {'S true':>8} {'vs nom':>7} | {'pose S':>8} {'err %':>6} {'z':>5} | {'step S':>8} {'err %':>6} "
          f"{'z':>5} | {'bias err':>8} {'z':>5}")
    for seed, S, nom, ps, psd, ss, ssd, be, bsd in rows:
        print(f"{seed:4d} {S:8.2f} {nom * 100:6.1f}% | {ps:8.2f} {(ps / S - 1) * 100:6.2f} {(ps - S) / psd:5.1f} | "
              f"{ss:8.2f} {(ss / S - 1) * 100:6.2f} {(ss - S) / ssd:5.1f} | {be:8.3f} {be / bsd:5.1f}")
    a = np.array([(r[3] / r[1] - 1, r[4] / r[1], r[5] / r[1] - 1, r[6] / r[1]) for r in rows])
    print(f"pose-to-pose: mean error {a[:, 0].mean() * 100:+.2f} % (rms {np.sqrt(np.mean(a[:, 0]**2)) * 100:.2f} %), "
          f"mean reported std {a[:, 1].mean() * 100:.2f} %")
    print(f"step search : mean error {a[:, 2].mean() * 100:+.2f} % (rms {np.sqrt(np.mean(a[:, 2]**2)) * 100:.2f} %), "
          f"mean reported std {a[:, 3].mean() * 100:.2f} %")
    print(f"time per calibration: pose-to-pose {t_pose / n_seeds * 1e3:.0f} ms (20 poses), "
          f"step search {t_step / n_seeds * 1e3:.0f} ms (10 placements)")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 10)
