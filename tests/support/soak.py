"""The soak campaign: a drifting sensor on a simulated wearer, window by window through gravcald's
Processor (bench/bench_soak.py runs it for a week; tests/system/test_soak.py for a day)."""
from __future__ import annotations

import gc
import math
import os
import time
from typing import Any

import numpy as np

from .temperature_sessions import EXT, previous_calibration, run, session

PARAMS = ("s_x", "s_y", "s_z", "o_x", "o_y", "o_z")
FS = 200.0


def rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def processor(process_noise: float):
    from gravcal.daemon.config import load_config
    from gravcal.daemon.persistence import CalibrationState
    from gravcal.daemon.processing import Processor, nominal_calibration

    cfg = load_config(None, {"device.fs_hz": FS, "estimator.process_noise": float(process_noise)})
    return Processor(cfg, CalibrationState(nominal_calibration(), 0, None, False, {}), resumed=False)


def as_window(ws, i):
    from gravcal.core.windows import Window

    n = int(round(ws.n[i]))
    start = int(round((ws.t[i] - 0.5 * n / FS) * FS))
    return Window(start, start + n, start / FS, (start + n - 1) / FS, ws.mean[i], ws.cov[i], ws.aux[i])


def drifting_model(seed: int):
    from gravcal.core.model.defaults import default_model

    return default_model(seed, offset_drift=True, sensitivity_drift=True)


def run_soak(days: float, seed: int = 0, *, process_noise: float = 5e-12, check_every_s: float = 3600.0,
             warmup_s: float = 86400.0, day_start_h: float = 8.0, progress: bool = False,
             max_window_s: float = 10.0, adapt_walk: bool = False,
             adapt_floor: bool = False) -> dict[str, Any]:
    """The soak (module docstring); returns the figures. ``max_window_s``: the longest quasi-static window
    (longer: fewer windows per day, the same information, a faster run). ``adapt_walk``: each parameter's walk
    adapted from ``process_noise`` (OnlineCalibrator.adapt_walk; not the service's default). ``adapt_floor``: the
    recursion's floor from its residuals (OnlineCalibrator.adapt_floor)."""
    from gravcal.core.estimators.remount import session_windows

    t0 = time.perf_counter()
    ws, info = session_windows("daily_living", seed=seed, duration=days * 86400.0, model=drifting_model(seed),
                               day_start_h=day_start_h, max_window_s=max_window_s)
    t_gen = time.perf_counter() - t0
    gc.collect()
    p = processor(process_noise)
    if adapt_walk:
        p.online.adapt_walk()
    if adapt_floor:
        p.online.adapt_floor()
    z: list[list[float]] = []
    checks_t: list[float] = []
    mem: list[tuple[float, float, int, int]] = []  # (t [h], RSS [MB], live objects, stored windows)
    hourly: list[dict[str, Any]] = []  # every check: the published order and whether it was accepted (and why not)
    next_check = check_every_s
    t1 = time.perf_counter()
    for i in range(len(ws)):
        p._window(as_window(ws, i))
        t = float(ws.t[i])
        if t < next_check:
            continue
        next_check += check_every_s
        st = p.state
        hourly.append({"t_h": round(t / 3600.0, 2), "model": st.model, "accepted": bool(st.accepted),
                       **({} if st.accepted else {"why": _why_not(st.calibration, p)})})
        if st.accepted and set(PARAMS) <= set(st.calibration.std):
            tr = info["truth"](float(ws.aux[i, 0]) if ws.aux.shape[1] else 25.0, t)
            cal = st.calibration
            est = {"s_x": cal.sensitivity[0, 0], "s_y": cal.sensitivity[1, 1], "s_z": cal.sensitivity[2, 2],
                   "o_x": cal.offset[0], "o_y": cal.offset[1], "o_z": cal.offset[2]}
            ref = {"s_x": tr.sensitivity[0, 0], "s_y": tr.sensitivity[1, 1], "s_z": tr.sensitivity[2, 2],
                   "o_x": tr.offset[0], "o_y": tr.offset[1], "o_z": tr.offset[2]}
            z.append([(est[k] - ref[k]) / cal.std[k] for k in PARAMS])
            checks_t.append(t)
            if len(checks_t) == 1:
                first_ref = ref
            last_ref, last_std = ref, dict(cal.std)
        if t >= warmup_s:
            gc.collect()
            mem.append((t / 3600.0, rss_mb(), len(gc.get_objects()), len(p.online.store)))
        if progress:
            print(f"  {t / 3600:.0f} h: {p.state.model} accepted={p.state.accepted} windows={i + 1}", flush=True)
    t_run = time.perf_counter() - t1
    za = np.abs(np.array(z)) if z else np.zeros((0, len(PARAMS)))
    out: dict[str, Any] = {
        "days": days, "seed": seed, "process_noise": process_noise, "adapt_walk": adapt_walk, "adapt_floor": adapt_floor,
        "floor_mg": None if p.online.floor is None else round(p.online.floor.floor_g * 1e3, 4), "windows": len(ws),
        "generate_s": round(t_gen, 2), "run_s": round(t_run, 2),
        "windows_per_s": round(len(ws) / max(t_run, 1e-9), 1),
        "checks": int(za.shape[0]), "check_values": int(za.size), "hourly_checks": len(hourly),
        "accepted_share": sum(h["accepted"] for h in hourly) / max(len(hourly), 1),
        # after the first acceptance (a datasheet start needs the first lying postures to determine order 6)
        "accepted_share_after_first": _share_after_first(hourly),
        "checks_after_first": len(hourly) - next((k for k, h in enumerate(hourly) if h["accepted"]), len(hourly)),
        "not_accepted": [h for h in hourly if not h["accepted"]],
        "within_1sigma": float(np.mean(za <= 1)) if za.size else None,
        "within_2sigma": float(np.mean(za <= 2)) if za.size else None,
        "within_3sigma": float(np.mean(za <= 3)) if za.size else None,
        "max_abs_z": float(za.max()) if za.size else None,
        "rms_z": float(np.sqrt(np.mean(za * za))) if za.size else None,  # ~1 for an honest std
        "per_param_rms_z": dict(zip(PARAMS, np.sqrt(np.mean(za * za, axis=0)).round(3).tolist())) if za.size else {},
        "beyond_3sigma": ([{"t_h": round(checks_t[i] / 3600.0, 1), "param": PARAMS[j], "z": round(float(z[i][j]), 2)}
                           for i, j in zip(*np.nonzero(za > 3))] if za.size else []),
        "per_param_within_1sigma": dict(zip(PARAMS, np.mean(za <= 1, axis=0).round(3).tolist())) if za.size else {},
        "final": {"model": p.state.model, "accepted": p.state.accepted, "reseeds": p.online.n_reseeds,
                  "rejected_windows": p.policy.windows_rejected, "remount_events": len(p.remount_events)},
        # how far the truth moved between the first and the last check, in the last stated std
        "truth_moved_max_sigma": (round(max(abs(last_ref[k] - first_ref[k]) / last_std[k] for k in PARAMS), 2)
                                  if checks_t else None),
        "stored_windows_max": max((m[3] for m in mem), default=len(p.online.store)),
        "store_capacity": p.online.store.capacity,
    }
    if len(mem) >= 3:
        h = np.array([m[0] for m in mem])
        for k, name in ((1, "rss_mb"), (2, "objects")):
            y = np.array([m[k] for m in mem], dtype=float)
            slope = float(np.polyfit(h, y, 1)[0]) * 24.0
            out[f"{name}_first"], out[f"{name}_last"] = float(y[0]), float(y[-1])
            out[f"{name}_slope_per_day"] = round(slope, 3)
        out["memory_samples"] = len(mem)
    out["_processor"] = p  # for tests (bounded structures); main() drops it
    return out


def _share_after_first(hourly: list[dict[str, Any]]) -> float | None:
    first = next((k for k, h in enumerate(hourly) if h["accepted"]), None)
    if first is None:
        return None
    rest = hourly[first:]
    return sum(h["accepted"] for h in rest) / len(rest)


def _why_not(cal, p) -> str:
    """Why a published calibration is not accepted (the policy's criteria, in its order)."""
    if not cal.converged:
        return "not converged"
    if not cal.observable:
        return "not observable" + (" (provisional)" if p.online.provisional else "")
    if p.policy.suspect():
        return f"suspect ({sum(p.policy.recent_rejections)} of the last {len(p.policy.recent_rejections)} rejected)"
    if p.policy.refitting:
        return "refitting"
    return "other: " + (cal.message or "")[:120]


def run_controls(n: int) -> dict[str, Any]:
    """How often the online estimator selects the temperature term on sensors without it (the controls of
    tests/core/test_online_extended.py, more seeds)."""
    chosen, observable = 0, 0
    for seed in range(100, 100 + n):
        ws, info = session(seed, False)
        oc = run(ws, previous_calibration(info))
        chosen += oc.model == EXT
        observable += oc.extended_status[EXT]["status"] in ("chosen", "not warranted")
    # one-sided 95 % upper bound on the rate with 0 selections: 1 - 0.05^(1/n)
    return {"controls": n, "selected": chosen, "tested": observable,
            "rate_upper_95": round(1 - 0.05 ** (1 / max(observable, 1)), 3) if chosen == 0 else None}


def run_remount(n: int, days: float = 3.0, angle_deg: float = 40.0) -> dict[str, Any]:
    from gravcal.core.estimators.remount import RemountDetector, session_windows
    from scipy.spatial.transform import Rotation

    at = 30 * 3600.0
    detected, delays, angle_err, false_alarms = 0, [], [], 0
    for seed in range(n):
        ax = np.random.default_rng(seed + 100).normal(size=3)
        rv = ax / np.linalg.norm(ax) * math.radians(angle_deg)
        R = Rotation.from_rotvec(rv).as_matrix()
        for remount in (True, False):
            ws, info = session_windows("daily_living", seed=seed, duration=days * 86400, remount_at=at if remount else None,
                                       remount_rotvec=rv if remount else None)
            d = RemountDetector()
            for i in range(len(ws)):
                d.update(ws.t[i], info["f"][i], ws.n[i] / 200.0)
            ev = list(d.events)
            if not remount:
                false_alarms += len(ev)
                continue
            false_alarms += sum(e.t < at for e in ev)
            after = [e for e in ev if e.t >= at]
            if after:
                detected += 1
                delays.append((after[0].t - at) / 3600.0)
                old = np.array(after[0].old_direction)
                turned = math.degrees(math.acos(np.clip(old @ (R.T @ old), -1, 1)))
                angle_err.append(abs(after[0].angle_deg - turned))
    return {"seeds": n, "days": days, "angle_deg": angle_deg, "detected": detected,
            "delay_h_median": float(np.median(delays)) if delays else None,
            "delay_h_max": float(np.max(delays)) if delays else None,
            "within_2h": int(sum(d <= 2 for d in delays)),
            "angle_error_deg_max": float(np.max(angle_err)) if angle_err else None,
            "false_alarms": false_alarms, "sensor_days_without_remount": n * days + n * at / 86400.0}
