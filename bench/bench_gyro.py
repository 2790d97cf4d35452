"""Gyro in use: pose-to-pose vs Scapellato's step-height search vs the truth, across seeds.

Part 1 (foot instep, Scapellato et al. 2005): for each seed one ENC-03J board is drawn
(datasheet spreads: scale factor +-20 %), worn on the foot instep for (a) 20 everyday sagittal
foot poses and (b) 10 foot placements onto 17 cm steps. Pose-to-pose runs on (a), the step
search on (b); both estimate the sensitivity [counts per rad/s] of the same board.

Part 2 (motion scenarios, core/scenarios.py): each scenario simulated for ``--duration`` s per
seed (board, wearer and noise drawn from the seed, as ``gravcald --emulate`` does), the
accelerometer's quasi-static windows detected with the true accelerometer calibration (this
isolates the gyro method), then the gyro calibrated (i) offline (``calibrate_gyro``,
bootstrapped start) and (ii) online as the daemon feeds it (``OnlineGyroCalibrator`` from the
nominal 357.36 counts per rad/s, blocks of 50 samples). The step search needs steps of known
height: not applicable to these scenarios. A scenario without rotations about the gyro's axis
(board y) must be declined, with the reason counted.

Both parts report the error against the truth in % and in units of the method's own reported
std (z), and the time per calibration.

    python bench/bench_gyro.py [n_seeds] [--duration S] [--scenarios a,b,c] [--json PATH]
"""
from __future__ import annotations

import argparse
import json
import re
import sys
import time
from collections import Counter
from typing import Any

import numpy as np

from gravcal.core.calibration import Calibration
from gravcal.core.detectors import QuasiStaticDetector, detect
from gravcal.core.gyro import OnlineGyroCalibrator, calibrate_gyro
from gravcal.core.gyro.footmotion import foot_poses, simulate_foot, stair_climb
from gravcal.core.gyro.scapellato import placements, step_height_search
from gravcal.core.model.enc03j import gyro_truth
from gravcal.core.samples import raw_triad
from gravcal.core.simulate import simulate

FS = 100.0
NOMINAL = 357.36  # counts per rad/s: 0.67 mV/(°/s) x 7.5 x 4096 / 3.3 V (the daemon's start)
SCENARIOS = ("sagittal_postures", "six_position", "loetters")
ONLINE_BLOCK = 50


def _summary(errors: list[float], stds: list[float], claims: int, n: int, seconds: float) -> dict[str, Any]:
    """errors, stds relative to the truth (fractions) of the claimed estimates."""
    e, s = np.asarray(errors, float), np.asarray(stds, float)
    z = e / s if e.size else e
    return {"seeds": n, "claimed": claims,
            "mean_error_pct": float(e.mean() * 100) if e.size else None,
            "rms_error_pct": float(np.sqrt(np.mean(e**2)) * 100) if e.size else None,
            "mean_reported_std_pct": float(s.mean() * 100) if s.size else None,
            "rms_z": float(np.sqrt(np.mean(z**2))) if z.size else None,
            "max_abs_z": float(np.abs(z).max()) if z.size else None,
            "seconds_per_calibration": seconds / max(n, 1)}


# -- part 1: foot instep ----------------------------------------------------------------
def foot(n_seeds: int) -> dict[str, Any]:
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
        rows.append({"seed": seed, "truth": S, "truth_vs_nominal": S / NOMINAL - 1,
                     "pose_to_pose": float(pose.sensitivity[0, 0]), "pose_to_pose_std": float(pose.std["S"]),
                     "step_search": float(step.sensitivity), "step_search_std": float(step.std),
                     "bias_error_counts": float(pose.bias[0] - tr["bias_counts"]), "bias_std": float(pose.bias_std[0])})
    print("Part 1: foot instep, 20 poses (pose-to-pose) and 10 placements onto 17 cm steps (step search)")
    print(f"{'seed':>4} {'S true':>8} {'vs nom':>7} | {'pose S':>8} {'err %':>6} {'z':>5} | {'step S':>8} {'err %':>6} "
          f"{'z':>5} | {'bias err':>8} {'z':>5}")
    for r in rows:
        S = r["truth"]
        print(f"{r['seed']:4d} {S:8.2f} {r['truth_vs_nominal'] * 100:6.1f}% | {r['pose_to_pose']:8.2f} "
              f"{(r['pose_to_pose'] / S - 1) * 100:6.2f} {(r['pose_to_pose'] - S) / r['pose_to_pose_std']:5.1f} | "
              f"{r['step_search']:8.2f} {(r['step_search'] / S - 1) * 100:6.2f} "
              f"{(r['step_search'] - S) / r['step_search_std']:5.1f} | {r['bias_error_counts']:8.3f} "
              f"{r['bias_error_counts'] / r['bias_std']:5.1f}")
    out = {"rows": rows}
    for key, t in (("pose_to_pose", t_pose), ("step_search", t_step)):
        out[key] = _summary([r[key] / r["truth"] - 1 for r in rows], [r[key + "_std"] / r["truth"] for r in rows],
                            len(rows), n_seeds, t)
        m = out[key]
        print(f"{key:>12}: mean error {m['mean_error_pct']:+.2f} % (rms {m['rms_error_pct']:.2f} %), mean reported std "
              f"{m['mean_reported_std_pct']:.2f} %, rms z {m['rms_z']:.2f}, max |z| {m['max_abs_z']:.1f}, "
              f"{m['seconds_per_calibration'] * 1e3:.0f} ms per calibration")
    return out


# -- part 2: motion scenarios -----------------------------------------------------------
def _online(gyro: np.ndarray, seq: np.ndarray, raw: np.ndarray, acc: Calibration):
    det = QuasiStaticDetector(FS, to_g=acc)
    online = OnlineGyroCalibrator(FS, k=1, axis=(0.0, 1.0, 0.0), hp_hz=0.3, start_sensitivity=NOMINAL,
                                  range_rad_s=np.radians(300.0), rails=(0, 4095))
    for i in range(0, gyro.shape[0], ONLINE_BLOCK):
        online.push(gyro[i:i + ONLINE_BLOCK])
        for w in det.update(seq[i:i + ONLINE_BLOCK] / FS, raw[i:i + ONLINE_BLOCK]):
            online.window(w, acc)
    return online.calibration


def _reason(message: str) -> str:
    """The reason a calibration declined, its numbers replaced by # (so that seeds group)."""
    why = message.split(";")[0].removeprefix("no sensitivity: ")
    return re.sub(r"(?<![A-Za-z])\d+(\.\d+)?", "#", why)


def scenario(name: str, n_seeds: int, duration: float) -> dict[str, Any]:
    res: dict[str, dict[str, Any]] = {"offline": {"err": [], "std": [], "t": 0.0, "declined": Counter(), "pairs": []},
                                      "online": {"err": [], "std": [], "t": 0.0, "declined": Counter(), "pairs": []}}
    for seed in range(n_seeds):
        sim = simulate(name, seed=seed, duration=duration, fs=FS)
        smp = sim.samples
        acc = Calibration.from_dict(sim.truth["calibration"])
        truth = gyro_truth(sim.model, vsupply=float(np.median(smp["vsupply"])))
        S = truth["sensitivity_counts_per_rad_s"]
        t, raw, gyro = smp["t"].astype(float), raw_triad(smp), smp["gyro"].astype(float)
        t0 = time.perf_counter()
        ws = detect(t, raw, fs=FS, to_g=acc)
        off = calibrate_gyro(t, gyro, ws, acc, fs=FS, hp_hz=truth["hp_hz"], axis=truth["axis"],
                             range_rad_s=truth["range_rad_s"], rails=(0, 4095), folds=0)
        res["offline"]["t"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        on = _online(gyro, smp["seq"].astype(float), raw, acc)
        res["online"]["t"] += time.perf_counter() - t0
        for key, cal in (("offline", off), ("online", on)):
            r = res[key]
            r["pairs"].append(cal.n_pairs)
            if cal.sensitivity is None:
                r["declined"][_reason(cal.message)] += 1
            else:
                r["err"].append(cal.sensitivity[0, 0] / S - 1)
                r["std"].append(cal.std["S"] / S)
    out = {}
    for key, r in res.items():
        out[key] = _summary(r["err"], r["std"], len(r["err"]), n_seeds, r["t"])
        out[key]["mean_pairs_used"] = float(np.mean(r["pairs"]))
        out[key]["declined"] = dict(r["declined"])
    return out


def scenarios(names: list[str], n_seeds: int, duration: float) -> dict[str, Any]:
    print(f"\nPart 2: scenarios, {duration:g} s each, {n_seeds} seeds; true accelerometer calibration; "
          "step search: n/a (no steps of known height)")
    print(f"{'scenario':>18} {'mode':>7} | {'claimed':>7} {'pairs':>5} {'mean err %':>10} {'rms err %':>9} "
          f"{'std %':>6} {'rms z':>5} {'max|z|':>6} {'s/cal':>5} | declined (reason)")
    out = {}
    for name in names:
        out[name] = scenario(name, n_seeds, duration)
        for key, m in out[name].items():
            f = (lambda v, fmt: "-" if v is None else format(v, fmt))
            why = "; ".join(f"{n} x {w}" for w, n in m["declined"].items())
            print(f"{name:>18} {key:>7} | {m['claimed']:>3}/{m['seeds']:<3} {m['mean_pairs_used']:5.1f} "
                  f"{f(m['mean_error_pct'], '+10.2f')} {f(m['rms_error_pct'], '9.2f')} "
                  f"{f(m['mean_reported_std_pct'], '6.2f')} {f(m['rms_z'], '5.2f')} {f(m['max_abs_z'], '6.1f')} "
                  f"{m['seconds_per_calibration']:5.2f} | {why}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("n_seeds", nargs="?", type=int, default=10, help="seeds per part (default 10)")
    ap.add_argument("--duration", type=float, default=600.0, help="scenario length [s] in part 2 (default 600)")
    ap.add_argument("--scenarios", default=",".join(SCENARIOS), help=f"part 2 scenarios (default {','.join(SCENARIOS)})")
    ap.add_argument("--json", metavar="PATH", help="also write the figures as a JSON object to PATH")
    args = ap.parse_args(argv)
    if args.n_seeds < 1 or not args.duration > 0:
        print("bench_gyro: error: n_seeds must be >= 1 and --duration > 0", file=sys.stderr)
        return 2
    names = [s for s in args.scenarios.split(",") if s]
    t0 = time.perf_counter()
    result = {"bench": "gyro", "command": "python bench/bench_gyro.py " + " ".join(sys.argv[1:] if argv is None else argv),
              "n_seeds": args.n_seeds, "duration_s": args.duration,
              "foot": foot(args.n_seeds), "scenarios": scenarios(names, args.n_seeds, args.duration)}
    result["wall_s"] = time.perf_counter() - t0
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
