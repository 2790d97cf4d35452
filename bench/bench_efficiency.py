"""Estimator efficiency against the Cramér–Rao bound, misaligned sensor (docs/twelve-parameters.md).

    python bench/bench_efficiency.py [--seeds 300] [--json PATH]

Window level (points on the ellipsoid raw = K a + o with per-window noise of N samples of
5 mg rms): for each scenario, N seeds, the in-use full identifiable model ("9"), the batch
estimator (LottersBatch, eq. 11a iterated), the recursion itself (LottersRecursive fed one window at a
time: relinearising sliding-window filter, core/estimators/recursive.py), the plain EKF
(LottersRecursive relinearise=False, for reference) and gravcald's online path (OnlineCalibrator: the
recursion on the observable order, re-seeded by batch fits of its window store). Start = truth
perturbed by the drift since the last calibration (1 %), then a sweep of the start error up to the
datasheet spread (sensitivities 6.7 %, offsets 0.67 g, a diagonal start stating that spread).
Efficiency = tr(CRLB) / tr(MSE) (goal: batch and recursion >= 0.9) and its whitened form
mean(e^T F e)/P (1 for an efficient estimator). Then one time-series run through the sensor
model, detector and model-order selection (H-model's simulate, when present).
"""
from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np
from scipy.spatial.transform import Rotation

from gravcal.core.calibration import Calibration
from gravcal.core.crlb import cap_directions, crlb, daily_living_directions, windows_on_ellipsoid
from gravcal.core.estimators.lotters import LottersBatch
from gravcal.core.estimators.recursive import LottersRecursive
from gravcal.core.estimators.parameterization import PARAMETERIZATIONS

NOISE_G, N_SAMPLES, M_WINDOWS = 0.005, 300, 120
D = np.diag([0.125, 0.131, 0.118])
O = np.array([0.502, 0.493, 0.508])
K_MIS = D @ np.array([[1, 0.004, 0.0], [-0.003, 1, 0.0], [0.018, -0.015, 1]]) @ \
    Rotation.from_rotvec([0.02, -0.03, 0.01]).as_matrix()  # second chip tilted (+-2 %) and a frame rotation
TRUTH = Calibration("truth", O, K_MIS)
MOUNT2 = Rotation.align_vectors([[1, 1, 1]], [[0, 0, 1.0]])[0].as_matrix()

SCENARIOS = {
    "loetters or1 theta=180": lambda rng: cap_directions((0, 0, 1), 180, M_WINDOWS, rng),
    "loetters or2 theta=120": lambda rng: cap_directions((1, 1, 1), 120, M_WINDOWS, rng),
    "daily_living (or2 mount)": lambda rng: daily_living_directions(M_WINDOWS, rng, MOUNT2),
}


DATASHEET = "datasheet"  # start_err value: a diagonal start drawn from the datasheet spread, stating it


def perturbed_start(rng: np.random.Generator, start_err: float | str) -> Calibration:
    """The truth after a drift of start_err (fraction of 1 g) in offsets and sensitivities, or (DATASHEET) a
    diagonal nominal start off by the ADXL210 datasheet spread (6.7 % sensitivities, 0.67 g offsets) that
    states that spread (datasheet_held_uncertainty): the farthest start a fresh sensor gives."""
    if start_err == DATASHEET:
        from gravcal.core.estimators.consider import datasheet_held_uncertainty  # noqa: PLC0415

        s = np.diag(K_MIS)
        return datasheet_held_uncertainty(Calibration("datasheet", O + rng.normal(0, 0.67, 3) * s,
                                                      np.diag(s * (1 + rng.normal(0, 0.067, 3)))))
    return Calibration("s", O + rng.normal(0, start_err, 3) * 0.125,
                       K_MIS @ (np.eye(3) + np.diag(rng.normal(0, start_err, 3))))


def run(dirs_fn, seeds: int, model: str = "9", start_err: float | str = 0.01, online: bool = True) -> dict[str, float]:
    par = PARAMETERIZATIONS[model](K_MIS, O)
    p_true = par.pack(K_MIS, O)
    errs: dict[str, list] = {"batch": [], "recursive": [], "ekf": [], "ordered": []}
    F_all = []
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        ws = windows_on_ellipsoid(TRUTH, dirs_fn(rng), noise_g=NOISE_G, n=N_SAMPLES, rng=rng)
        F_all.append(crlb(ws, TRUTH, model).fisher)
        start = perturbed_start(rng, start_err)
        cals = {"batch": LottersBatch(model, sigma_floor_g=0.0).fit(ws, start),
                "recursive": LottersRecursive(start, model, sigma_floor_g=0.0).update(ws),
                "ekf": LottersRecursive(start, model, sigma_floor_g=0.0, relinearise=False).update(ws)}
        if online:
            cals["ordered"] = recursive_with_order(ws, start)
        for name, c in cals.items():
            errs[name].append(par.pack(c.sensitivity, c.offset) - p_true)
    F = np.array(F_all)
    tr_crlb = float(np.mean([np.trace(np.linalg.inv(f)) for f in F]))
    out = {"crlb_accel_rms_mg": float(np.sqrt(np.mean([crlb_accel(f) for f in F[:20]])) * 1e3)}
    for name, e in ((k, np.array(v)) for k, v in errs.items() if v):
        sq = np.sum(e * e, axis=1)
        out[f"{name}_eff"] = tr_crlb / sq.mean()
        out[f"{name}_eff_se"] = out[f"{name}_eff"] * sq.std(ddof=1) / math.sqrt(seeds) / sq.mean()
        out[f"{name}_whitened"] = float(np.mean(np.einsum("ki,kij,kj->k", e, F, e)) / par.n_params)
    return out


SWITCH_FRACTION: list[float] = []  # where the ordered recursion reached the full set (fraction of the windows)


def recursive_with_order(ws, start: Calibration, systematic_g: float = 0.0) -> Calibration:
    """The daemon's online path: OnlineCalibrator (core/estimators/online.py) fed one window at a time: it
    updates only the order the windows so far determine and re-seeds the recursion with a batch fit of
    its (bounded) window store when the order grows or the store has doubled. systematic_g = 0: the
    window-level simulation has no per-window model error (see docs/twelve-parameters.md)."""
    from gravcal.core.estimators.online import OnlineCalibrator  # noqa: PLC0415

    oc = OnlineCalibrator(start, systematic_g=systematic_g)
    reached = None
    for i in range(len(ws)):
        oc.update(ws.subset(np.arange(i, i + 1)))
        if reached is None and oc.model == "9":
            reached = (i + 1) / len(ws)
    SWITCH_FRACTION.append(1.0 if reached is None else reached)
    FINAL_ORDERS.append(oc.model)
    return oc.calibration


FINAL_ORDERS: list[str] = []


def timing() -> dict:
    """Cost per window: plain LottersRecursive.step (6 and 9), and the OnlineCalibrator amortised over a
    long daily-living stream (order checks, 6-vs-9 comparisons, re-seeding batch fits included)."""
    from gravcal.core.estimators.online import OnlineCalibrator  # noqa: PLC0415

    rng = np.random.default_rng(0)
    m = 6000
    ws = windows_on_ellipsoid(TRUTH, daily_living_directions(m, rng, MOUNT2), noise_g=NOISE_G, n=N_SAMPLES, rng=rng)
    cm = ws.cov_of_mean
    out: dict = {}
    for model in ("6", "9"):
        r = LottersRecursive(TRUTH, model, sigma_floor_g=0.0)
        t0 = time.perf_counter()
        for i in range(m):
            r.step(ws.mean[i], cm[i], float(ws.t[i]))
        out[f"recursive_step_model{model}_us"] = (time.perf_counter() - t0) / m * 1e6
        print(f"  LottersRecursive.step model {model}: {(time.perf_counter() - t0) / m * 1e6:6.1f} µs/window")
    rows = [ws.subset(np.arange(i, i + 1)) for i in range(m)]
    oc = OnlineCalibrator(Calibration("s", O + 0.001, K_MIS * 1.01), capacity=4000)
    t0 = time.perf_counter()
    for row in rows:
        oc.update(row)
    dt = time.perf_counter() - t0
    st = oc.stats()
    print(f"  OnlineCalibrator.update (store 4000, {m} windows): {dt / m * 1e6:6.0f} µs/window amortised "
          f"({st['n_checks']} order checks, {st['n_compares']} comparisons, {st['n_reseeds']} re-seeds, "
          f"{st['evicted']} evicted; final order {st['model']})")
    r = oc.recursive
    t0 = time.perf_counter()
    for i in range(m):
        r.step(ws.mean[i], cm[i], float(ws.t[i]))
    out["online_update_amortised_us"] = dt / m * 1e6
    out["online_final_order"] = st["model"]
    out["online_plain_step_us"] = (time.perf_counter() - t0) / m * 1e6
    print(f"  its plain per-window update (LottersRecursive.step, order {st['model']}): "
          f"{out['online_plain_step_us']:6.1f} µs/window")
    return out


def crlb_accel(F: np.ndarray) -> float:
    from gravcal.core.crlb import sphere_metric  # noqa: PLC0415

    G = sphere_metric(PARAMETERIZATIONS["9"](K_MIS, O), TRUTH)
    return float(np.trace(G @ np.linalg.inv(F)))


def time_series_run(seed: int = 3) -> dict:
    try:
        from gravcal.core.simulate import simulate  # noqa: PLC0415
    except ImportError:
        print("time series: gravcal.core.simulate not available, skipped")
        return {}
    from gravcal.core.detectors import detect  # noqa: PLC0415
    from gravcal.core.estimators.order import select_order  # noqa: PLC0415
    from gravcal.core.model.defaults import default_model, triad_truth  # noqa: PLC0415
    from gravcal.core.samples import raw_triad  # noqa: PLC0415

    model = default_model(np.random.default_rng(seed), misalignment=True)
    t0 = time.perf_counter()
    sim = simulate("daily_living", model, seed=seed, duration=2 * 3600.0, fs=100.0)  # < 6 h: one bed episode
    truth = triad_truth(model)
    start = Calibration("start", truth.offset + 0.002, np.diag(np.diag(truth.sensitivity)) * 1.02)
    ws = detect(sim.samples["t"], raw_triad(sim.samples), fs=100.0, to_g=start)
    dec = select_order(ws, start=start)
    print(f"time series: daily_living 2 h, misaligned default_model(seed={seed}): {len(ws)} windows, "
          f"order chosen {dec.model!r} ({time.perf_counter() - t0:.1f} s)\n  reason: {dec.reason}")
    out: dict = {"windows": len(ws), "order_chosen": dec.model, "reason": dec.reason, "models": {}}
    for m in ("6", "9"):
        try:
            cal = LottersBatch(m).fit(ws, dec.calibration or start)
        except ValueError as exc:
            print(f"  model {m}: {exc}")
            out["models"][m] = {"error": str(exc)}
            continue
        par = PARAMETERIZATIONS[m](truth.sensitivity, truth.offset)
        e = par.pack(cal.sensitivity, cal.offset) - par.pack(truth.sensitivity, truth.offset)
        b = crlb(ws, truth, m, sigma_floor_g=cal.metadata.get("sigma_floor_g", 0.0))
        sphere = np.random.default_rng(0).normal(size=(2000, 3))
        sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
        err = np.linalg.norm(cal.apply(sphere @ truth.sensitivity.T + truth.offset) - sphere, axis=1)
        out["models"][m] = {"observable": bool(cal.observable), "whitened": float(e @ b.fisher @ e / len(e)),
                            "crlb_accel_mg": float(b.accel_rms_g * 1e3),
                            "sphere_error_rms_mg": float(math.sqrt(np.mean(err ** 2)) * 1e3)}
        print(f"  model {m} (observable={cal.observable}): e^T F e / P = {e @ b.fisher @ e / len(e):.2f}, CRLB accel {b.accel_rms_g * 1e3:.3f} mg, "
              f"true calibrated-acceleration error over the sphere: rms {math.sqrt(np.mean(err ** 2)) * 1e3:.2f} mg "
              f"(the 6 model's includes the misalignment it cannot represent and the frame)")
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=300)
    ap.add_argument("--no-time-series", action="store_true")
    ap.add_argument("--timing-only", action="store_true")
    ap.add_argument("--json", metavar="PATH", help="write the figures here")
    args = ap.parse_args(argv)
    res: dict = {"seeds": args.seeds, "windows": M_WINDOWS, "samples_per_window": N_SAMPLES, "noise_g": NOISE_G,
                 "model": "9", "scenarios": {}, "drift": {}}
    print("cost per window:")
    res["timing"] = timing()
    if args.timing_only:
        _dump(args.json, res)
        return
    print(f"window level: {M_WINDOWS} windows x {N_SAMPLES} samples, {NOISE_G * 1e3:g} mg/sample, model 9, "
          f"{args.seeds} seeds; recursive start = truth after 1 % drift")
    print("efficiency tr(CRLB)/tr(MSE) ± se (whitened P/mean(e^T F e)); 'recursion' = LottersRecursive over all 9 "
          "from the start, one window at a time (relinearising); 'EKF' = the same without relinearisation; "
          "'online' = OnlineCalibrator: recursion on the observable order only, re-seeded by a batch fit of its "
          "window store when the order grows or the store doubles")
    print(f"{'scenario':26s} {'CRLB mg':>7s} {'batch':>19s} {'recursion':>19s} {'EKF':>19s} {'online':>19s}")
    for name, fn in SCENARIOS.items():
        t0 = time.perf_counter()
        r = run(fn, args.seeds)
        cols = " ".join(f"{r[k + '_eff']:6.3f}±{r[k + '_eff_se']:.3f} ({1 / r[k + '_whitened']:.3f})"
                        for k in ("batch", "recursive", "ekf", "ordered"))
        print(f"{name:26s} {r['crlb_accel_rms_mg']:7.3f} {cols}   ({time.perf_counter() - t0:.1f} s; online reached "
              f"9 after {np.median(SWITCH_FRACTION) * 100:.0f} % of the windows, median; final orders "
              f"{dict(zip(*np.unique(FINAL_ORDERS, return_counts=True)))})")
        res["scenarios"][name] = {**r, "online_reached_9_fraction_median": float(np.median(SWITCH_FRACTION)),
                                  "final_orders": {str(k): int(v) for k, v in
                                                   zip(*np.unique(FINAL_ORDERS, return_counts=True))}}
        SWITCH_FRACTION.clear()
        FINAL_ORDERS.clear()
    print("recursion efficiency vs the start error (daily_living; the recursion alone, no re-seeds):")
    for err in (0.002, 0.005, 0.01, 0.02, 0.05, DATASHEET):
        r = run(SCENARIOS["daily_living (or2 mount)"], max(100, args.seeds // 3), start_err=err, online=False)
        label = "datasheet spread (6.7 %, 0.67 g)" if err == DATASHEET else f"{err * 100:4.1f} % of 1 g"
        print(f"  start error {label}: recursion {r['recursive_eff']:.3f}±{r['recursive_eff_se']:.3f}, "
              f"EKF {r['ekf_eff']:.3f}±{r['ekf_eff_se']:.3f}, batch {r['batch_eff']:.3f}±{r['batch_eff_se']:.3f}")
        res["drift"][str(err)] = r
    SWITCH_FRACTION.clear()
    FINAL_ORDERS.clear()
    if not args.no_time_series:
        res["time_series"] = time_series_run()
    _dump(args.json, res)


def _dump(path: str | None, res: dict) -> None:
    if path:
        with open(path, "w", encoding="utf-8") as fh:
            json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main()
