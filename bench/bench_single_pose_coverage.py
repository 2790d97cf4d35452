"""Coverage of the one-pose temperature slopes' std, on chamber sessions gravcal's simulator did not make: not a test.

    OPENBLAS_NUM_THREADS=1 python bench/bench_single_pose_coverage.py [--seeds 200] [--first 1000]

Sessions from tests/support/single_pose_sessions.py (its own streams): a chamber stepping the temperature with
a lag, each channel's zero-g level (and in "offset_and_gain" its gain) following it, a slow wander (AR(1),
10 min) of ``--wander`` mg, handling windows in other postures; the device's own calibration of the gains held
exact or off by its stated 3 %. Each is given to core.estimators.single_pose (what `gravcal calibrate` does when
the norm determines nothing). Prints per case: sessions with a partial calibration, RMS of z = (estimate -
truth) / stated std per axis and pooled, and the share beyond 2σ (4.55 % for an honest Gaussian std).
``--first``: the first seed (tests/core/test_single_pose.py uses 0-79; the default here starts at 1000).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from gravcal.core.estimators.single_pose import HELD_KEY, single_pose  # noqa: E402
from gravcal.core.estimators.start import device_calibration_start  # noqa: E402
from support.single_pose_sessions import window_session  # noqa: E402

CASES = (("offset", 0.0), ("offset", 0.03), ("offset_and_gain", 0.03))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=200)
    ap.add_argument("--first", type=int, default=1000)
    ap.add_argument("--wander", type=float, nargs="+", default=[0.0, 0.3, 1.0], help="wander std [mg]")
    args = ap.parse_args()
    print("| kind | held gains | wander [mg] | partial | RMS z x, y, z | RMS z pooled | beyond 2σ |")
    print("|---|---|---|---|---|---|---|")
    for wander in args.wander:
        for kind, rel in CASES:
            z, partial = [], 0
            for seed in range(args.first, args.first + args.seeds):
                S = window_session(seed, kind=kind, held_rel_std=rel, wander_g=wander * 1e-3)
                start = device_calibration_start(S.held_K, S.held_o, "bench logger", "its own calibration")
                if rel == 0:
                    start.metadata.pop(HELD_KEY)
                sp = single_pose(S.windows, start)
                if sp is None or sp.status != "partial":
                    continue
                partial += 1
                mag = sp.determined["temperature_slopes"]
                z.append([(mag["value"][a] - S.truth_mg_per_c[i]) / mag["std"][a] for i, a in enumerate("xyz")])
            z = np.asarray(z)
            per_axis = ", ".join(f"{v:.3f}" for v in np.sqrt(np.mean(z ** 2, axis=0)))
            held = "exact" if rel == 0 else f"±{100 * rel:g} %"
            print(f"| {kind} | {held} | {wander:g} | {partial}/{args.seeds} | {per_axis} | "
                  f"{np.sqrt(np.mean(z ** 2)):.3f} | {100 * np.mean(np.abs(z) > 2):.1f} % |", flush=True)


if __name__ == "__main__":
    main()
