"""Accuracy side by side: gravcal and the peer calibrators on the SAME held-out quasi-static windows.

    python bench/bench_accuracy.py [--quick] [--json PATH] [--recordings NAME ...] [--folds 5]
                                   [--peer-input samples|windows]

Evaluation windows. gravcal's detector (the `gravcal calibrate` pipeline: bootstrap start,
Lötters detector, per-axis screening, re-detection) defines the quasi-static windows of each
recording ONCE; every method is scored on the same windows. Error of a window: | |a| - 1 g |
of its calibrated mean (Lötters eq. 4), in mg; a figure is the RMS over the held-out windows.

Held-out splits, by TIME (never odd/even):
  blocks    the recording's time span cut into k equal contiguous blocks; each block in turn is the test part
  halves    fit on the first half, test on the second, and the reverse
  insample  fit on everything, score on every window (NOT held out: a reference, and the only score a
            calibration-session method like imucal's Ferraris gets, since it needs all its sections)
The fit part is everything outside the test block (raw samples for the peers, each running its own
still detection on them; for gravcal the evaluation windows lying wholly in the fit part). Test windows
lie wholly inside the test block; a window straddling a boundary is used by nobody in that fold.

Methods. gravcal "6", "auto" (order selection: offsets / 6 / 9 where the windows determine it), and
"6+temperature_offset", "9+temperature_offset" (+ temperature_sensitivity) where the recording has a
temperature; the peers
through bench/peers.py (skdh, actipy, imucal), fed the acceleration in nominal g (the recording's raw
units through its datasheet scale). With ``--peer-input windows`` the peers instead get the same windows
as gravcal (the fit part's evaluation windows, in nominal g, with their temperatures) and their own full
model is fitted on them and applied (bench/peers_windows.py): skdh's closest-point fit (GGIR's
g.calibrate as skdh ports it) and actipy's calibrate_gravity. A method that declines a fold (too few still points, sphere not
populated, too little data, an order the windows cannot determine) is counted as declined with its reason,
and scored "as used" with the data it hands back unchanged (nominal g) — both are reported.

Recordings. The measured ones in $GRAVCAL_DATA (gravcal.io.datasets) and simulated wrist-worn daily
living with known truth (core.simulate), given to everybody in two forms: the ADXL210's duty cycles through
the datasheet scale (50 %, 4 %/g: zero-g offsets up to ±1 g in nominal g), and a "factory-g" output (the
same sensor after an imperfect factory calibration: ±30 mg offsets, ±2 % sensitivities, what the peers are
designed for). For the simulated ones the parameter errors of every method's full-recording fit are reported
against the truth at the recording's median still temperature: offsets [mg], sensitivities [%], and the
norm error over the whole sphere [mg].
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peers  # noqa: E402

from gravcal.core.calibration import Calibration, jsonable  # noqa: E402
from gravcal.core.windows import WindowSet  # noqa: E402

SCHEMES = ("blocks", "halves", "insample")  # insample: fit on everything, score on every window (a reference only)
MEASURED = ("imu_tk_xsens", "actigraph_cpw_thermal_chamber", "imucal_ferraris", "mpu6050_tomisuarez")
# zero [raw] of each measured recording's nominal scale (acc_per_g comes from the loader's meta)
NOMINAL_ZERO = {"imu_tk_xsens": 32768.0}
GYRO_DPS_PER_UNIT = {"imucal_ferraris": 1.0}  # imucal wants deg/s; only the Ferraris session has its sections
ADXL_ZERO, ADXL_PER_G = 0.5, 0.04  # ADXL210 datasheet: 50 % duty at 0 g, 4 %/g (core/model/defaults.SENS_TYP)


@dataclass
class Rec:
    """A recording as the bench uses it: raw (N, 3) in its own units and the map y = A (raw - zero) to nominal g."""

    name: str
    kind: str  # "measured" | "simulated"
    t: np.ndarray
    raw: np.ndarray
    fs: float
    A: np.ndarray  # (3, 3) nominal g per raw unit
    zero: np.ndarray  # (3,) raw at nominal 0 g
    temp: np.ndarray | None = None
    sections: dict[str, tuple[int, int]] = field(default_factory=dict)
    gyro_dps: np.ndarray | None = None
    truth: Calibration | None = None  # raw = K a + o (raw units) at truth_temp_c
    truth_temp_c: float | None = None
    note: str = ""

    def to_g(self, raw: np.ndarray) -> np.ndarray:
        return (np.asarray(raw, dtype=float) - self.zero) @ self.A.T

    def to_raw(self, y: np.ndarray) -> np.ndarray:
        return np.asarray(y, dtype=float) @ np.linalg.inv(self.A).T + self.zero


# -- recordings -------------------------------------------------------------------------------------
def measured(name: str) -> Rec:
    from gravcal.io.datasets import load

    r = load(name)
    per_g = float(r.meta["acc_per_g"])
    gyro = None
    if r.gyro is not None and name in GYRO_DPS_PER_UNIT:
        gyro = r.gyro * GYRO_DPS_PER_UNIT[name]
    return Rec(r.name, "measured", np.asarray(r.t, float), np.asarray(r.acc, float), float(r.fs), np.eye(3) / per_g,
               np.full(3, NOMINAL_ZERO.get(name, 0.0)), r.temp, dict(r.sections), gyro,
               note=f"{r.acc_units}; nominal {per_g:g} per g")


def simulated(hours: float, seed: int = 1, fs: float = 25.0) -> list[Rec]:
    """Wrist daily living, ADXL210 pair with temperature terms and misalignment; two forms (see module doc)."""
    from gravcal.core.model.defaults import default_model
    from gravcal.core.samples import raw_triad
    from gravcal.core.simulate import simulate

    model = default_model(np.random.default_rng(seed), temperature=True, misalignment=True)
    sim = simulate("daily_living", model, seed=seed, duration=hours * 3600.0, fs=fs, placement="wrist")
    s = sim.samples
    t, raw, temp = np.asarray(s["t"], float), raw_triad(s), np.asarray(s["temp"], float)
    truth = Calibration.from_dict(sim.truth["calibration"])
    temp_c = float(sim.truth["conditions"]["temp_c"])
    tag = f"sim_wrist_{hours:g}h"
    adxl = Rec(f"{tag}_adxl210", "simulated", t, raw, fs, np.eye(3) / ADXL_PER_G, np.full(3, ADXL_ZERO), temp,
               truth=truth, truth_temp_c=temp_c,
               note=f"daily_living wrist {hours:g} h at {fs:g} Hz, seed {seed}; duty cycles through the datasheet scale")
    rng = np.random.default_rng(seed + 1000)
    # factory calibration: the truth at 25 °C, off by N(0, 30 mg) offsets and N(0, 2 %) sensitivities
    from gravcal.core.model.defaults import triad_truth

    t25 = triad_truth(model, temp_c=25.0)
    K_fac = np.diag(np.diag(t25.sensitivity) * (1 + rng.normal(0, 0.02, 3)))
    o_fac = t25.offset + np.diag(t25.sensitivity) * rng.normal(0, 0.030, 3)
    A = np.linalg.inv(K_fac)
    y = (raw - o_fac) @ A.T  # the device's output in g; gravcal gets the same numbers (its raw units = g)
    fac = Rec(f"{tag}_factory_g", "simulated", t, y, fs, np.eye(3), np.zeros(3), temp,
              truth=Calibration("truth", A @ (truth.offset - o_fac), A @ truth.sensitivity), truth_temp_c=temp_c,
              note="same sensor after an imperfect factory calibration (±30 mg, ±2 %): output in g")
    return [adxl, fac]


# -- evaluation windows and splits ------------------------------------------------------------------
def evaluation_windows(rec: Rec) -> tuple[WindowSet, str]:
    """gravcal's quasi-static windows of the whole recording (the calibrate pipeline's detection)."""
    from gravcal.core.pipeline import calibrate_recording

    try:
        rep = calibrate_recording(rec.t, rec.raw, temp=rec.temp, model="auto", fs=rec.fs)
        return rep.windows, f"{rep.n_windows} windows (pipeline order {rep.calibration.model})"
    except ValueError as exc:  # order not determined: the windows are still the detector's
        from gravcal.core.pipeline import MAX_WINDOW_STD_G, _Columns, _detect, data_start, screen_windows

        start = data_start(rec.t, rec.raw, rec.fs)
        ws, _ = screen_windows(_detect(rec.t, _Columns(rec.raw), rec.fs, "lotters", start, rec.temp, {}), start,
                               MAX_WINDOW_STD_G)
        return ws, f"{len(ws)} windows (pipeline: {exc})"


@dataclass
class Fold:
    lo: int  # test block = samples [lo, hi)
    hi: int
    test: np.ndarray  # indices of the evaluation windows wholly inside [lo, hi)
    fit: np.ndarray  # indices of the evaluation windows wholly outside


def time_folds(t: np.ndarray, ws: WindowSet, scheme: str, k: int = 5) -> list[Fold]:
    """Test blocks contiguous in TIME: ``blocks`` = k equal spans of the recording's duration, ``halves`` = 2."""
    if scheme not in SCHEMES:
        raise ValueError(f"unknown scheme {scheme!r}; known: {', '.join(SCHEMES)}")
    if scheme == "insample":
        return [Fold(0, 0, np.arange(len(ws)), np.arange(len(ws)))]
    n = 2 if scheme == "halves" else int(k)
    if n < 2:
        raise ValueError(f"need at least 2 blocks, got {n}")
    edges_t = np.linspace(t[0], t[-1], n + 1)
    edges = np.searchsorted(t, edges_t, side="left")
    edges[-1] = t.shape[0]
    out = []
    for i in range(n):
        lo, hi = int(edges[i]), int(edges[i + 1])
        test = np.flatnonzero((ws.start >= lo) & (ws.end <= hi))
        fit = np.flatnonzero((ws.end <= lo) | (ws.start >= hi))
        out.append(Fold(lo, hi, test, fit))
    return out


def fit_samples(n: int, fold: Fold) -> np.ndarray:
    """Sample indices of the fit part (everything outside the test block), in time order."""
    return np.r_[np.arange(0, fold.lo), np.arange(fold.hi, n)]


# -- methods ----------------------------------------------------------------------------------------
@dataclass
class Fitted:
    ok: bool
    message: str
    seconds: float
    f: Callable[[np.ndarray, np.ndarray | None], np.ndarray] | None = None  # (y (M,3) nominal g, T (M,)) -> a [g]
    model: str = ""


def gravcal_methods(rec: Rec) -> list[str]:
    m = ["6", "auto"]
    if rec.temp is not None:
        m += ["6+temperature_offset", "9+temperature_offset", "9+temperature_offset+temperature_sensitivity"]
    return m


def fit_gravcal(rec: Rec, model: str, idx: np.ndarray, ws_fit: WindowSet) -> Fitted:
    """gravcal on the fit part: its own data-derived start from the fit part's raw samples, then the order fit."""
    from gravcal.core.estimators.extended import apply_extended
    from gravcal.core.pipeline import _fit_order, data_start

    t0 = time.perf_counter()
    try:
        start = data_start(rec.t[idx], rec.raw[idx], rec.fs)
        fitted = _fit_order(ws_fit, model.split("+")[0], start, None, None, 5)
        cal = fitted.calibration
        if "+" in model:
            # the extended fit from the base fit, as `gravcal diagnose` does (iterated eq. 11a with the
            # data-derived floor); its calibration carries the terms for apply_extended
            from gravcal.core.estimators.order import fit_extended_floor

            ext, _floor = fit_extended_floor(model, ws_fit, cal)
            cal = ext.calibration(len(ws_fit))
            cal.converged = bool(ext.converged)
            fitted.model = model
    except (ValueError, np.linalg.LinAlgError) as exc:
        return Fitted(False, str(exc), time.perf_counter() - t0)
    dt = time.perf_counter() - t0
    if not cal.converged:
        return Fitted(False, f"did not converge: {cal.message}", dt)

    def f(y, T, cal=cal):
        return apply_extended(cal, rec.to_raw(y), temp=T)

    return Fitted(True, cal.message or "ok", dt, f, fitted.model)


def fit_peer(rec: Rec, name: str, idx: np.ndarray) -> Fitted:
    sections = None
    if rec.sections:  # sections wholly inside the fit part, re-indexed into it
        pos = np.full(rec.t.shape[0] + 1, -1, dtype=np.int64)
        pos[idx] = np.arange(idx.size)
        sections = {}
        for s, (a, b) in rec.sections.items():
            if b > a and pos[a] >= 0 and pos[b - 1] >= 0 and pos[b - 1] - pos[a] == b - 1 - a:
                sections[s] = (int(pos[a]), int(pos[b - 1]) + 1)
    r = peers.calibrate(name, rec.t[idx], rec.to_g(rec.raw[idx]), rec.fs, None if rec.temp is None else rec.temp[idx],
                        sections=sections, gyro_dps=None if rec.gyro_dps is None else rec.gyro_dps[idx])
    return Fitted(r.ok, r.message, r.seconds, (lambda y, T, r=r: r.apply(y, T)) if r.ok else None)


def fit_peer_windows(rec: Rec, name: str, ws_fit: WindowSet) -> Fitted:
    """The peer's own model fitted on the fit part's evaluation windows (bench/peers_windows.py)."""
    import peers_windows

    T = ws_fit.aux[:, 0] if (rec.temp is not None and ws_fit.aux.shape[1]) else None
    r = peers_windows.fit(name, rec.to_g(ws_fit.mean), T)
    return Fitted(r.ok, r.message, r.seconds, (lambda y, T, r=r: r.apply(y, T)) if r.ok else None)


def window_errors_mg(rec: Rec, fitted: Fitted | None, ws: WindowSet) -> np.ndarray:
    y = rec.to_g(ws.mean)
    T = ws.aux[:, 0] if (rec.temp is not None and ws.aux.shape[1]) else None
    a = y if fitted is None or not fitted.ok else fitted.f(y, T)
    return (np.linalg.norm(a, axis=1) - 1.0) * 1e3


def _rms(e: list[np.ndarray]) -> float | None:
    x = np.concatenate(e) if e else np.zeros(0)
    return float(np.sqrt(np.mean(x * x))) if x.size else None


PEER_INPUT = ["samples"]  # "windows": the peers fitted on the evaluation windows (--peer-input)


def methods_for(rec: Rec, peer_names: list[str]) -> list[tuple[str, Callable[[np.ndarray, WindowSet], Fitted]]]:
    out: list[tuple[str, Callable[[np.ndarray, WindowSet], Fitted]]] = [
        ("nominal (no calibration)", lambda idx, wsf: Fitted(True, "identity", 0.0, lambda y, T: y))]
    for m in gravcal_methods(rec):
        out.append((f"gravcal {m}", lambda idx, wsf, m=m: fit_gravcal(rec, m, idx, wsf)))
    for p in peer_names:
        if PEER_INPUT[0] == "windows":
            import peers_windows

            if p in peers_windows.WINDOWS_PEERS:
                out.append((f"{p} (same windows)", lambda idx, wsf, p=p: fit_peer_windows(rec, p, wsf)))
            continue
        out.append((p, lambda idx, wsf, p=p: fit_peer(rec, p, idx)))
    return out


def heldout(rec: Rec, ws: WindowSet, peer_names: list[str], k: int) -> dict[str, Any]:
    """Per scheme and method: pooled held-out RMS (calibrated folds only, and as used), folds declined and why."""
    n = rec.t.shape[0]
    out: dict[str, Any] = {}
    meths = methods_for(rec, peer_names)
    for scheme in SCHEMES:
        folds = time_folds(rec.t, ws, scheme, k)
        res: dict[str, Any] = {}
        for name, fit in meths:
            cal_err, used_err, declined, seconds, models = [], [], [], 0.0, []
            per_fold: list[float | None] = []  # each fold's held-out RMS; None: declined or nothing to test
            for i, fold in enumerate(folds):
                per_fold.append(None)
                if fold.test.size == 0:
                    continue
                ft = fit(fit_samples(n, fold), ws.subset(fold.fit))
                seconds += ft.seconds
                e = window_errors_mg(rec, ft, ws.subset(fold.test))
                used_err.append(e)
                if ft.ok:
                    cal_err.append(e)
                    per_fold[i] = _rms([e])
                    if ft.model:
                        models.append(ft.model)
                else:
                    declined.append(f"fold {i}: {ft.message}")
            res[name] = {"heldout_rms_mg": _rms(cal_err), "as_used_rms_mg": _rms(used_err),
                         "folds_fitted": len(cal_err), "folds": len(used_err), "declined": declined,
                         "fold_rms_mg": per_fold, "models": models, "fit_seconds": seconds}
        out[scheme] = {"folds": len(folds), "test_windows": [int(f.test.size) for f in folds],
                       "fit_windows": [int(f.fit.size) for f in folds], "methods": res}
    return out


def effective(f: Callable, T: float | None) -> tuple[np.ndarray, np.ndarray]:
    """(S, o) in nominal g of an affine calibration a = f(y, T) at temperature T: y = S a + o."""
    Tv = None if T is None else np.full(4, T)
    a = f(np.vstack([np.zeros(3), np.eye(3)]), Tv)
    M = (a[1:] - a[0]).T
    S = np.linalg.inv(M)
    return S, -S @ a[0]


def parameter_errors(rec: Rec, ws: WindowSet, peer_names: list[str]) -> dict[str, Any]:
    """Every method fitted on the whole recording, against the truth at the truth's temperature."""
    n = rec.t.shape[0]
    idx = np.arange(n)
    S_true = rec.A @ rec.truth.sensitivity
    o_true = rec.A @ (rec.truth.offset - rec.zero)
    T = rec.truth_temp_c if rec.temp is not None else None
    u = np.random.default_rng(0).normal(size=(4000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    y_sphere = u @ S_true.T + o_true
    out: dict[str, Any] = {}
    for name, fit in methods_for(rec, peer_names):
        ft = fit(idx, ws)
        if not ft.ok:
            out[name] = {"ok": False, "message": ft.message}
            continue
        S, o = effective(ft.f, T)
        a = ft.f(y_sphere, None if T is None else np.full(len(u), T))
        out[name] = {"ok": True, "model": ft.model, "seconds": ft.seconds,
                     "offset_err_mg": ((o - o_true) * 1e3).tolist(),
                     "sens_err_pct": ((np.diag(S) / np.diag(S_true) - 1) * 100).tolist(),
                     "max_offset_err_mg": float(np.max(np.abs(o - o_true)) * 1e3),
                     "max_sens_err_pct": float(np.max(np.abs(np.diag(S) / np.diag(S_true) - 1)) * 100),
                     "sphere_norm_rms_mg": float(np.sqrt(np.mean((np.linalg.norm(a, axis=1) - 1) ** 2)) * 1e3)}
    return out


def run(quick: bool = False, names: list[str] | None = None, k: int = 5, sim_hours: float | None = None,
        log: Callable[[str], None] = print) -> dict[str, Any]:
    avail = peers.available()
    peer_names = [p for p, why in avail.items() if why is None]
    for p, why in avail.items():
        if why is not None:
            log(f"peer {p} skipped: {why}")
    hours = sim_hours if sim_hours is not None else (6.0 if quick else 26.0)
    result: dict[str, Any] = {"peers_available": avail, "peer_versions": peers.versions(), "schemes": list(SCHEMES),
                              "peer_input": PEER_INPUT[0],
                              "blocks": k, "sim_hours": hours, "recordings": {}}
    todo: list[Callable[[], list[Rec]]] = []
    for name in (names or list(MEASURED) + ["sim"]):
        if name == "sim":
            todo.append(lambda: simulated(hours))
        else:
            todo.append(lambda name=name: [measured(name)])
    for make in todo:
        try:
            recs = make()
        except Exception as exc:  # a missing data folder: say so, go on
            log(f"recording unavailable: {exc}")
            result["recordings"][getattr(make, "__name__", "?")] = {"error": str(exc)}
            continue
        for rec in recs:
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ws, wnote = evaluation_windows(rec)
                entry: dict[str, Any] = {"kind": rec.kind, "samples": int(rec.t.shape[0]), "fs": rec.fs,
                                         "hours": float((rec.t[-1] - rec.t[0]) / 3600), "windows": len(ws),
                                         "windows_note": wnote, "note": rec.note, "temperature": rec.temp is not None}
                if len(ws) < 2:
                    entry["error"] = f"only {len(ws)} evaluation window(s)"
                else:
                    entry["heldout"] = heldout(rec, ws, peer_names, k)
                    if rec.truth is not None:
                        entry["parameters"] = parameter_errors(rec, ws, peer_names)
            entry["seconds"] = time.perf_counter() - t0
            result["recordings"][rec.name] = entry
            log(format_recording(rec.name, entry))
    return result


def _f(x: float | None, fmt: str = "{:.2f}") -> str:
    return "—" if x is None else fmt.format(x)


def method_cell(m: dict[str, Any]) -> str:
    """'1.23' | '1.23 (3/5 folds)' | 'declined (as used 45.6)'."""
    if m["folds_fitted"] == 0:
        return f"declined (as used {_f(m['as_used_rms_mg'], '{:.1f}')})"
    s = _f(m["heldout_rms_mg"])
    if m["folds_fitted"] < m["folds"]:
        s += f" ({m['folds_fitted']}/{m['folds']} folds; as used {_f(m['as_used_rms_mg'], '{:.1f}')})"
    return s


def format_recording(name: str, entry: dict[str, Any]) -> str:
    lines = [f"{name}: {entry.get('hours', 0):.2f} h, {entry.get('windows', 0)} windows ({entry.get('windows_note', '')})"]
    if "error" in entry:
        return lines[0] + f"\n  {entry['error']}"
    for scheme, d in entry["heldout"].items():
        lines.append(f"  held-out by {scheme} (test windows per fold {d['test_windows']}):")
        for m, r in d["methods"].items():
            lines.append(f"    {m:50s} {method_cell(r)}")
            for why in r["declined"][:2]:
                lines.append(f"        {why[:160]}")
    for m, p in entry.get("parameters", {}).items():
        if p["ok"]:
            lines.append(f"  truth: {m:46s} offsets max {p['max_offset_err_mg']:8.2f} mg  sens max {p['max_sens_err_pct']:6.3f} %"
                         f"  sphere {p['sphere_norm_rms_mg']:8.2f} mg")
        else:
            lines.append(f"  truth: {m:46s} declined: {p['message'][:120]}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="6 h simulated recording instead of 26 h")
    ap.add_argument("--json", metavar="PATH", help="write the raw figures here")
    ap.add_argument("--recordings", nargs="*", help=f"subset of {', '.join(MEASURED)}, sim")
    ap.add_argument("--folds", type=int, default=5, help="time blocks for the 'blocks' scheme (default 5)")
    ap.add_argument("--sim-hours", type=float, help="length of the simulated recording [h] (default 26; quick 6)")
    ap.add_argument("--peer-input", choices=("samples", "windows"), default="samples",
                    help="samples: each peer on the fit part's raw samples, its own detection and gates (as its users "
                         "run it); windows: each peer's own model fitted on the same evaluation windows as gravcal "
                         "(bench/peers_windows.py)")
    args = ap.parse_args(argv)
    PEER_INPUT[0] = args.peer_input
    res = run(args.quick, args.recordings, args.folds, args.sim_hours)
    if args.json:
        Path(args.json).write_text(json.dumps(jsonable(res), indent=1), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
