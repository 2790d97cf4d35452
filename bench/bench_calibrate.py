"""Benchmark: `gravcal calibrate` on a week at 100 Hz (60 M samples, structured .npy).

    python bench/bench_calibrate.py [--days 1 2 4 7] [--repeat 1] [--cache DIR] [--json PATH] [--csv]
                                    [--peers | --no-peers] [--peer-forms nominal factory] [--peer-timeout 1800]
                                    [--peer-gate G]

Targets (issue 8, item 3): calibration (not counting reading the file) <= 1 s for 7 days, peak
memory <= 1.2x the input array; issue 2's 7 days in <= 5 s wall is reported too. ``--json
PATH`` writes the figures (per size: wall, read, calibrate, start-up, peak RSS and its ratio to
the input, windows, held-out error, and the growth from the smallest to the largest size).
``--csv`` also times `gravcal calibrate` on a 1-day CSV (written once into the cache).

Input. A simulated daily-living week (core.simulate.simulate_blocks, seed 0, default sensor),
generated once and cached OUTSIDE the repository ($GRAVCAL_CACHE, else ~/.cache/gravcal):
written block by block through np.lib.format.open_memmap, so generating it needs no more
memory than one block. The 1-, 2- and 4-day inputs are prefixes of the week. Layout:

    t  float64   [s]: float32 cannot hold a week at 100 Hz (its step at 6e5 s is 0.06 s > 0.01 s)
    ax, ay, az   float32 duty cycles T1/T2: float32 resolves 3e-8 at 0.5, ~1000x finer than the
                 timer quantum (1/20000 counts) and the sensor noise, so it loses nothing and
                 makes the input 20 bytes/sample (1.2 GB for the week) instead of 32 (1.9 GB).

Bytecode. Before measuring, gravcal's sources are compiled to bytecode (compileall), as pip does
when it installs a package and as the peers' installed packages are: an editable install under
PYTHONDONTWRITEBYTECODE=1 (this machine's environment) would otherwise compile every gravcal module
in every run (~0.15 s of start-up that no installed copy pays).

Same conditions for every method. Before a size's first timed run its file is read once whole, so every
method (gravcal first or last) finds it in the page cache. Each round runs every method once (gravcal,
the numpy reference, each peer and form), the order rotated by one from size to size and from round to
round (``--repeat N``: N rounds), so no method always runs first or after the same neighbour; each
method's fastest round (wall time) is shown, and all its wall times are in the JSON (``walls_s``).

Measurement. Each run is a child process `gravcal calibrate FILE --json` (what a user runs),
waited for with os.wait4 to get that child's own peak RSS (ru_maxrss, KiB on Linux). A child's
ru_maxrss starts at its parent's peak at the exec, so this process keeps its own small: it never
imports the peers (their availability is asked in a child). RSS
includes the memory-mapped input pages the child touched, so the ratio is honest about
memory-mapping. Wall time is split into read+validate and calibrate as reported by the command
(timing_s in its JSON); the rest is interpreter start-up and imports.

Peers, side by side (issue 8, item 3; on by default when installed, ``--no-peers`` to skip; a
missing peer is listed with its install hint). For each size each peer that
calibrates from free-living data runs in its own child (bench/peer_child.py) on the same file, in the
same rounds as gravcal:
skdh (CalibrateAccelerometer on numpy arrays) and actipy (calibrate_gravity on a DataFrame with a
DatetimeIndex). The child reads the file block by block into exactly what the peer's users hand
it, timed apart from the peer's call; the parent takes the child's peak RSS with os.wait4 and
kills it after ``--peer-timeout`` seconds (reported). imucal is "n/a": a Ferraris calibration needs
an annotated lab session (six faces and three turns), not free-living data. Two forms of the input:
    nominal  the duty cycles through the ADXL210 datasheet scale, (duty - 0.5) / 0.04 g: zero-g
             offsets up to 1 g (this sensor's x reads -1.0 g at 0 g), beyond what the peers accept;
    factory  the same sensor after an imperfect factory calibration (the truth, off by N(0, 30 mg)
             offsets and N(0, 2 %) sensitivities, seed 1000, as bench_accuracy's "factory_g"):
             what the peers are built for, so their full fit runs and is timed.
Error: against the simulation's truth (the .truth.json next to the week), the RMS over gravity
directions on the whole sphere of |a_estimated - a_true| [mg], for gravcal and every peer that
calibrated (cheap, needs no second fit; a held-out error would need one more run per peer).
``--peer-gate G`` (diagnostic, labelled in the output): the peers' sphere/cube gate (0.3 g) set to G,
so their fit runs on this wrist recording, whose z axis seldom points below -0.2 g when still and
which they therefore decline at every size.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

FS = 100.0
SEED = 0
DTYPE = np.dtype([("t", "<f8"), ("ax", "<f4"), ("ay", "<f4"), ("az", "<f4")])
BLOCK = 1 << 18
TARGET_WALL_S = 5.0  # issue 2
TARGET_CALIBRATE_S = 1.0  # issue 8: calibration time for 7 days, reading excluded
TARGET_RATIO = 1.2  # issue 8: peak RSS / input bytes
TARGET_WALL_7D_S = 1.5  # whole process (interpreter, imports, reading, calibration) for 7 days
TARGET_PEER_X = 5.0  # every free-living peer's whole-process wall time / gravcal's, same file, same run


def cache_dir(arg: str | None) -> Path:
    d = Path(arg or os.environ.get("GRAVCAL_CACHE") or Path.home() / ".cache" / "gravcal")
    d.mkdir(parents=True, exist_ok=True)
    return d


def week_path(cache: Path, days: int) -> Path:
    return cache / f"bench_daily_living_{days}d_{int(FS)}hz_seed{SEED}.npy"


def generate_week(path: Path, days: int = 7) -> None:
    """Simulate `days` of daily living into a structured .npy, block by block (bounded memory)."""
    from gravcal.core.model.defaults import triad_truth
    from gravcal.core.samples import raw_triad
    from gravcal.core.simulate import simulate_blocks
    from gravcal.cli.cmd_simulate import build_model

    n = int(round(days * 86400 * FS))
    model = build_model(SEED)
    tmp = path.with_suffix(".partial.npy")
    mm = np.lib.format.open_memmap(tmp, mode="w+", dtype=DTYPE, shape=(n,))
    i = 0
    t0 = time.perf_counter()
    for block in simulate_blocks("daily_living", model, seed=SEED, duration=days * 86400.0, fs=FS, block=BLOCK):
        k = len(block)
        raw = raw_triad(block)
        mm["t"][i:i + k] = block["t"]
        mm["ax"][i:i + k], mm["ay"][i:i + k], mm["az"][i:i + k] = raw[:, 0], raw[:, 1], raw[:, 2]
        i += k
        if (i // BLOCK) % 40 == 0:
            print(f"  generating: {i / n * 100:5.1f} % ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    mm.flush()
    del mm
    if i != n:
        raise RuntimeError(f"simulator gave {i} samples, expected {n}")
    tmp.rename(path)
    path.with_suffix(".truth.json").write_text(json.dumps({"calibration": triad_truth(model).to_dict(), "seed": SEED}))


def prefix_file(week: Path, path: Path, days: int) -> None:
    src = np.load(week, mmap_mode="r")
    n = int(round(days * 86400 * FS))
    tmp = path.with_suffix(".partial.npy")
    dst = np.lib.format.open_memmap(tmp, mode="w+", dtype=src.dtype, shape=(n,))
    for i in range(0, n, 1 << 22):
        dst[i:i + (1 << 22)] = src[i:min(n, i + (1 << 22))]
    dst.flush()
    del dst
    tmp.rename(path)


def warm_page_cache(path: Path, chunk: int = 1 << 20) -> None:
    """Read the whole file once (and drop the bytes): every timed method then finds it in the page cache,
    as after any earlier run; a readahead hint alone (posix_fadvise) may still be under way when the
    first method starts, which then waits for the disk."""
    buf = bytearray(chunk)
    with open(path, "rb", buffering=0) as f:
        while f.readinto(buf):
            pass


REFERENCE = Path(__file__).resolve().parent / "numpy_reference.py"


def run_calibrate(path: Path, reference: bool = False) -> dict:
    """One `gravcal calibrate --json` child (or the numpy reference's): wall time, its own peak RSS, its JSON."""
    cmd = ([sys.executable, str(REFERENCE), str(path)] if reference
           else [sys.executable, "-m", "gravcal.cli.main", "calibrate", str(path), "--json"])
    with tempfile.TemporaryFile(mode="w+") as out, tempfile.TemporaryFile(mode="w+") as err:
        t0 = time.perf_counter()
        p = subprocess.Popen(cmd, stdout=out, stderr=err)
        _, status, usage = os.wait4(p.pid, 0)
        wall = time.perf_counter() - t0
        p.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        text, errors = out.read(), err.read()
    if p.returncode not in (0, 3):
        raise RuntimeError(f"gravcal calibrate failed ({p.returncode}): {errors.strip()}")
    d = json.loads(text)
    return {"wall": wall, "cpu": usage.ru_utime + usage.ru_stime, "maxrss_bytes": usage.ru_maxrss * 1024, "json": d,
            "exit": p.returncode}


PEER_CHILD = Path(__file__).resolve().parent / "peer_child.py"
FREE_LIVING_PEERS = ("skdh", "actipy")  # imucal: Ferraris lab session only
IMUCAL_NA = "n/a: imucal's Ferraris calibration needs an annotated lab session (6 static faces + 3 turns, with the gyro), " \
            "not free-living data"
ADXL_ZERO, ADXL_PER_G = 0.5, 0.04  # ADXL210 datasheet: 50 % duty at 0 g, 4 %/g


def sphere(n: int = 2000) -> np.ndarray:
    """n near-uniform unit vectors (Fibonacci sphere): the gravity directions the error is averaged over."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (1 + 5 ** 0.5) * k
    r = np.sqrt(1 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def load_truth(cache: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(offset (3,), sensitivity (3, 3)) in duty cycles of the simulated week: duty = offset + S a."""
    p = week_path(cache, 7).with_suffix(".truth.json")
    if not p.exists():
        return None
    c = json.loads(p.read_text())["calibration"]
    return np.asarray(c["offset"], float), np.asarray(c["sensitivity"], float)


def gravcal_truth_error_mg(d: dict, truth) -> float | None:
    """RMS over the sphere of |S_est^-1 (o + S u - o_est) - u| [mg] (gravcal works in duty cycles)."""
    if truth is None or not d.get("offset") or not d.get("sensitivity"):
        return None
    o, S = truth
    u = sphere()
    duty = o + u @ S.T
    a = np.linalg.solve(np.asarray(d["sensitivity"], float), (duty - np.asarray(d["offset"], float)).T).T
    return float(np.sqrt(np.mean(np.sum((a - u) ** 2, axis=1))) * 1e3)


def peer_truth_error_mg(d: dict, zero: np.ndarray, per_g: np.ndarray, truth) -> float | None:
    """The same error for a peer's a = M (y - offset_g), y = (duty - zero) / per_g."""
    if truth is None or not d.get("ok"):
        return None
    o, S = truth
    u = sphere()
    y = (o + u @ S.T - zero) / per_g
    a = (y - np.asarray(d["offset_g"], float)) @ np.asarray(d["matrix"], float).T
    return float(np.sqrt(np.mean(np.sum((a - u) ** 2, axis=1))) * 1e3)


def peer_forms(truth) -> dict[str, tuple[np.ndarray, np.ndarray, str]]:
    """name -> (zero duty, duty per g, description) of each input form the peers are given."""
    forms = {"nominal": (np.full(3, ADXL_ZERO), np.full(3, ADXL_PER_G), "(duty - 0.5) / 0.04: datasheet scale")}
    if truth is not None:
        o, S = truth
        rng = np.random.default_rng(SEED + 1000)
        k = np.diag(S) * (1 + rng.normal(0, 0.02, 3))
        z = o + np.diag(S) * rng.normal(0, 0.030, 3)
        forms["factory"] = (z, k, "imperfect factory calibration: truth off by N(0, 30 mg), N(0, 2 %)")
    return forms


def run_peer(name: str, path: Path, zero: np.ndarray, per_g: np.ndarray, timeout_s: float,
             sphere_crit: float | None = None) -> dict:
    """One peer child: its JSON, wall time, own peak RSS; killed (and reported) past timeout_s."""
    cmd = [sys.executable, str(PEER_CHILD), name, str(path), "--fs", str(FS), "--zero", *map(repr, zero.tolist()),
           "--per-g", *map(repr, per_g.tolist())] + ([] if sphere_crit is None else ["--sphere-crit", repr(sphere_crit)])
    with tempfile.TemporaryFile(mode="w+") as out, tempfile.TemporaryFile(mode="w+") as err:
        t0 = time.perf_counter()
        p = subprocess.Popen(cmd, stdout=out, stderr=err)
        timed_out = False
        while True:
            pid, status, usage = os.wait4(p.pid, os.WNOHANG)
            if pid:
                break
            if time.perf_counter() - t0 > timeout_s:
                p.kill()  # our own child, by its pid
                _, status, usage = os.wait4(p.pid, 0)
                timed_out = True
                break
            time.sleep(0.05)
        wall = time.perf_counter() - t0
        p.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        text, errors = out.read(), err.read()
    r = {"peer": name, "wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime, "peak_rss_bytes": usage.ru_maxrss * 1024,
         "exit": p.returncode, "timed_out": timed_out}
    if timed_out:
        r.update(ok=False, message=f"timeout: killed after {timeout_s:g} s")
    elif p.returncode != 0 or not text.strip():
        tail = errors.strip().splitlines()[-1] if errors.strip() else "no output"
        r.update(ok=False, message=f"child failed (exit {p.returncode}): {tail}")
    else:
        r.update(json.loads(text.strip().splitlines()[-1]))
    return r


def _x(a: float | None, b: float | None) -> float | None:
    return a / b if a is not None and b else None


def _cell(v: float | None, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def side_by_side(npy: list[dict], peer_rows: list[dict], run_peers: list[str], missing: dict, forms: dict,
                 versions: dict, timeout_s: float) -> dict:
    """Print gravcal vs each peer per size (ratios peer/gravcal) and the growth; return the JSON section."""
    by_days = {r["days"]: r for r in npy}
    for p in peer_rows:
        g = by_days[p["days"]]
        p["calibrate_x_gravcal"] = _x(p["calibrate_s"], g["calibrate_s"])
        p["wall_x_gravcal"] = _x(p["wall_s"], g["wall_s"])
        p["peak_rss_x_gravcal"] = _x(p["peak_rss_bytes"], g["peak_rss_bytes"])
    print()
    print("side by side (ratios are peer / gravcal; RSS/input against the same 20 B/sample .npy; "
          "err = RMS over the sphere vs the simulated truth, mg)")
    print(f"{'days':>4} {'method':<16} {'read s':>7} {'calib s':>8} {'wall s':>7} {'calib x':>7} {'wall x':>6} "
          f"{'peak RSS MB':>11} {'RSS/input':>9} {'RSS x':>6} {'err mg':>8} {'load':>9}  result")
    for days in sorted(by_days):
        g = by_days[days]
        print(f"{days:4d} {'gravcal':<16} {g['read_s']:7.2f} {g['calibrate_s']:8.2f} {g['wall_s']:7.2f} {'1':>7} {'1':>6} "
              f"{g['peak_rss_bytes'] / 1e6:11.0f} {g['rss_ratio']:9.2f} {'1':>6} {_cell(g['truth_err_mg'], '8.2f'):>8} "
              f"{g['load_avg_1min']:9.1f}  model {g['model']}, {g['windows']} windows, "
              f"held-out {g['heldout_rms_mg']:.2f} mg")
        for p in (q for q in peer_rows if q["days"] == days):
            res = ("TIMEOUT" if p["timed_out"] else "calibrated" if p["ok"] else "DECLINED") + f": {p['message']}"
            print(f"{days:4d} {p['peer'] + ' (' + p['form'] + ')':<16} {_cell(p['read_s'], '7.2f'):>7} "
                  f"{_cell(p['calibrate_s'], '8.2f'):>8} {p['wall_s']:7.2f} {_cell(p['calibrate_x_gravcal'], '7.1f'):>7} "
                  f"{_cell(p['wall_x_gravcal'], '6.1f'):>6} {p['peak_rss_bytes'] / 1e6:11.0f} {p['rss_ratio']:9.2f} "
                  f"{_cell(p['peak_rss_x_gravcal'], '6.1f'):>6} {_cell(p['truth_err_mg'], '8.2f'):>8} "
                  f"{p['load_avg_1min'][0]:4.1f}-{p['load_avg_1min'][1]:<4.1f}  {res[:110]}")
        print(f"{days:4d} {'imucal':<16} {IMUCAL_NA}")
    for k, v in missing.items():
        print(f"missing peer {k}: {v}")
    growth: dict = {}
    if len(npy) >= 2:
        a, b = npy[0]["days"], npy[-1]["days"]
        print(f"growth {a} -> {b} days (samples x{b / a:.1f}):")

        def grow(label: str, ra: dict | None, rb: dict | None) -> None:
            if not ra or not rb:
                return
            g = {k: _x(rb[k], ra[k]) for k in ("calibrate_s", "read_s", "wall_s", "peak_rss_bytes")}
            growth[label] = g
            print(f"  {label:<18} calibrate x{_cell(g['calibrate_s'], '.1f')}, read x{_cell(g['read_s'], '.1f')}, "
                  f"wall x{_cell(g['wall_s'], '.1f')}, peak RSS x{_cell(g['peak_rss_bytes'], '.1f')}")

        grow("gravcal", npy[0], npy[-1])
        for name in run_peers:
            for form in forms:
                pick = {q["days"]: q for q in peer_rows if q["peer"] == name and q["form"] == form}
                grow(f"{name} ({form})", pick.get(a), pick.get(b))
        pick = {q["days"]: q for q in peer_rows if q["peer"] == "numpy-ref"}
        grow("numpy-ref", pick.get(a), pick.get(b))
    return {"run": run_peers, "missing": missing, "not_applicable": {"imucal": IMUCAL_NA}, "versions": versions,
            "forms": {k: {"zero_duty": v[0].tolist(), "duty_per_g": v[1].tolist(), "what": v[2]} for k, v in forms.items()},
            "timeout_s": timeout_s, "error": "RMS over the sphere of |a_est - a_true| [mg] against the simulated truth",
            "rows": peer_rows, "growth": growth}


def csv_path(cache: Path) -> Path:
    return cache / f"bench_daily_living_1d_{int(FS)}hz_seed{SEED}.csv"


def make_csv(cache: Path) -> Path:
    """The 1-day input as CSV (t, ax, ay, az), written once in blocks."""
    path = csv_path(cache)
    if path.exists():
        return path
    src = np.load(week_path(cache, 1), mmap_mode="r")
    tmp = path.with_suffix(".partial.csv")
    with open(tmp, "w") as f:
        f.write("t,ax,ay,az\n")
        for i in range(0, len(src), 1 << 20):
            b = src[i:i + (1 << 20)]
            np.savetxt(f, np.column_stack([b["t"], b["ax"], b["ay"], b["az"]]), fmt=["%.2f", "%.8g", "%.8g", "%.8g"],
                       delimiter=",")
    tmp.rename(path)
    return path


def peers_available() -> dict[str, str | None]:
    """bench/peers.py's ``available()``, asked in a child process. Importing the peers (pandas, SciPy,
    ...) would raise this process's peak RSS to ~245 MB, and a child started from it (vfork/exec)
    inherits that peak as its own ru_maxrss: every method's peak RSS would read at least that."""
    code = "import json, peers; print(json.dumps(peers.available()))"
    out = subprocess.run([sys.executable, "-c", code], cwd=Path(__file__).resolve().parent, check=True,
                         capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def compile_gravcal_bytecode() -> None:
    """Write the __pycache__ an installed gravcal has (see the module doc, Bytecode)."""
    import compileall  # noqa: PLC0415
    import importlib.util  # noqa: PLC0415

    for name in ("gravcal", "gravcal.core", "gravcal.drivers", "gravcal.daemon"):
        for where in importlib.util.find_spec(name).submodule_search_locations:
            compileall.compile_dir(where, quiet=1)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=int, nargs="+", default=[1, 2, 4, 7])
    ap.add_argument("--repeat", type=int, default=1,
                    help="rounds per size, every method once a round in a rotating order; each method's fastest run "
                         "is shown (default 1)")
    ap.add_argument("--cache", default=None, help="cache directory (default $GRAVCAL_CACHE or ~/.cache/gravcal)")
    ap.add_argument("--json", type=Path, default=None, metavar="PATH", help="also write the figures as JSON here")
    ap.add_argument("--csv", action="store_true", help="also time a 1-day CSV recording")
    ap.add_argument("--peers", action=argparse.BooleanOptionalAction, default=None,
                    help="run the peer calibrators side by side (default: those installed)")
    ap.add_argument("--peer-forms", nargs="+", choices=["nominal", "factory"], default=["nominal", "factory"],
                    help="input forms given to the peers (default both; see the module doc)")
    ap.add_argument("--peer-gate", type=float, default=None, metavar="G",
                    help="diagnostic: override the peers' sphere/cube gate (their default 0.3 g) so that their fit "
                         "runs on data they would decline; NOT as their users run them, labelled as such")
    ap.add_argument("--reference", action=argparse.BooleanOptionalAction, default=True,
                    help="also time bench/numpy_reference.py (10 s windows + least squares) on each .npy (default on)")
    ap.add_argument("--peer-timeout", type=float, default=1800.0, help="seconds per peer run before it is killed")
    ap.add_argument("--make", type=int, default=None, help=argparse.SUPPRESS)  # internal: build one input file
    args = ap.parse_args()
    cache = cache_dir(args.cache)
    week = week_path(cache, 7)
    if args.make is not None:
        if args.make == 7:
            generate_week(week, 7)
        else:
            prefix_file(week, week_path(cache, args.make), args.make)
        return 0
    rows = []
    inputs = []
    for days in ([7] if not week.exists() else []) + list(args.days):
        path = week_path(cache, days)
        if not path.exists():
            # Built in a child process: a child forked from a parent that touched gigabytes would
            # start with the parent's RSS, and ru_maxrss of the calibrate runs would include it.
            print(f"building the {days}-day input once: {path}", file=sys.stderr)
            subprocess.run([sys.executable, __file__, "--make", str(days), "--cache", str(cache)], check=True)
        if days in args.days:
            inputs.append((days, "npy", path))
    if args.csv:
        if not week_path(cache, 1).exists():
            subprocess.run([sys.executable, __file__, "--make", "1", "--cache", str(cache)], check=True)
        inputs.append((1, "csv", make_csv(cache)))
    truth = load_truth(cache)
    compile_gravcal_bytecode()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import peers as peer_lib

    why_missing = peers_available() if args.peers is not False else {}
    missing = {k: v for k, v in why_missing.items() if v is not None}
    run_peers = [k for k in FREE_LIVING_PEERS if k in why_missing and why_missing[k] is None]
    for k, v in missing.items():
        print(f"peer {k} unavailable: {v}", file=sys.stderr)
    if args.peers and not run_peers:
        print(f"--peers: no free-living peer is usable ({peer_lib.INSTALL_HINT})", file=sys.stderr)
    forms = {k: v for k, v in peer_forms(truth).items() if k in args.peer_forms}
    for f in args.peer_forms:
        if f not in forms:
            print(f"peer form {f}: needs the truth file next to the week; skipped", file=sys.stderr)
    peer_rows: list[dict] = []
    for size_index, (days, fmt, path) in enumerate(inputs):
        n = int(round(days * 86400 * FS))
        nbytes = np.load(path, mmap_mode="r").nbytes if fmt == "npy" else path.stat().st_size
        warm_page_cache(path)  # every method then reads it from the page cache, the first timed one too
        methods: list[tuple] = [("gravcal",)]
        if fmt == "npy":
            methods += ([("numpy-ref",)] if args.reference else []) + [(name, form) for name in run_peers for form in forms]
        runs: dict[tuple, list[dict]] = {m: [] for m in methods}
        for r in range(args.repeat):
            # each round in another order: no method always runs first (after the warming read) or after
            # the same neighbour, whose freed memory and cache state the next process finds
            k = (size_index + r) % len(methods)
            for m in methods[k:] + methods[:k]:
                load0 = os.getloadavg()[0]
                if m[0] == "gravcal":
                    res = run_calibrate(path)
                elif m[0] == "numpy-ref":
                    res = run_calibrate(path, reference=True)
                else:
                    print(f"  {days} d: {m[0]} ({m[1]}) ...", file=sys.stderr)
                    zero, per_g, _ = forms[m[1]]
                    res = run_peer(m[0], path, zero, per_g, args.peer_timeout, args.peer_gate)
                res["load"] = [load0, os.getloadavg()[0]]
                runs[m].append(res)
        g = runs[("gravcal",)]
        best = min(g, key=lambda r: r["wall"])
        d = best["json"]
        rows.append({"days": days, "format": fmt, "samples": n, "input_bytes": nbytes, "wall_s": best["wall"],
                     "read_s": d["timing_s"]["read"], "calibrate_s": d["timing_s"]["calibrate"],
                     "cpu_s": best["cpu"], "read_cpu_s": d["timing_s"].get("read_cpu"),
                     "calibrate_cpu_s": d["timing_s"].get("calibrate_cpu"), "load_avg_1min": best["load"][0],
                     "startup_s": best["wall"] - d["timing_s"]["read"] - d["timing_s"]["calibrate"],
                     "peak_rss_bytes": max(r["maxrss_bytes"] for r in g), "windows": d["n_windows"],
                     "rss_ratio": max(r["maxrss_bytes"] for r in g) / nbytes,
                     "heldout_rms_mg": d["heldout_rms_mg"], "model": d["model"], "exit": best["exit"],
                     "runs": len(g), "walls_s": [r["wall"] for r in g], "truth_err_mg": gravcal_truth_error_mg(d, truth)})
        if ("numpy-ref",) in runs:
            ref = min(runs[("numpy-ref",)], key=lambda r: r["wall"])
            d = ref["json"]
            peer_rows.append({"days": days, "peer": "numpy-ref", "form": "10 s", "gate_g": None, "samples": n,
                              "input_bytes": nbytes, "ok": True, "timed_out": False,
                              "message": f"{d['n_windows']} still 10 s windows, least-squares ellipsoid",
                              "wall_s": ref["wall"], "read_s": 0.0, "calibrate_s": d["timing_s"]["calibrate"],
                              "startup_s": ref["wall"] - d["timing_s"]["calibrate"], "read_cpu_s": 0.0,
                              "calibrate_cpu_s": d["timing_s"]["calibrate_cpu"], "cpu_s": ref["cpu"],
                              "peak_rss_bytes": ref["maxrss_bytes"], "rss_ratio": ref["maxrss_bytes"] / nbytes,
                              "truth_err_mg": gravcal_truth_error_mg(d, truth), "load_avg_1min": ref["load"],
                              "runs": len(runs[("numpy-ref",)]), "walls_s": [r["wall"] for r in runs[("numpy-ref",)]]})
        for m in methods:
            if m[0] in ("gravcal", "numpy-ref"):
                continue
            name, form = m
            zero, per_g, _ = forms[form]
            r = min(runs[m], key=lambda q: q["wall_s"])
            ts = r.get("timing_s", {})
            peer_rows.append({"days": days, "peer": name, "form": form, "gate_g": args.peer_gate, "samples": n,
                              "input_bytes": nbytes,
                              "ok": r["ok"], "message": r["message"], "timed_out": r["timed_out"],
                              "wall_s": r["wall_s"], "read_s": ts.get("read"), "calibrate_s": ts.get("calibrate"),
                              "startup_s": ts.get("startup"), "read_cpu_s": ts.get("read_cpu"),
                              "calibrate_cpu_s": ts.get("calibrate_cpu"), "cpu_s": r["cpu_s"],
                              "peak_rss_bytes": r["peak_rss_bytes"], "rss_ratio": r["peak_rss_bytes"] / nbytes,
                              "rss_after_read_bytes": r.get("rss_after_read_bytes"),
                              "truth_err_mg": peer_truth_error_mg(r, zero, per_g, truth),
                              "offset_g": r.get("offset_g"), "matrix": r.get("matrix"), "load_avg_1min": r["load"],
                              "runs": len(runs[m]), "walls_s": [q["wall_s"] for q in runs[m]]})

    print(f"gravcal calibrate on simulated daily living, {FS:g} Hz, fields t f8 + ax/ay/az f4 "
          f"({DTYPE.itemsize} bytes/sample); cache {cache}")
    print(f"{'days':>4} {'fmt':>3} {'samples':>11} {'input MB':>9} {'wall s':>7} {'read s':>7} {'calib s':>8} "
          f"{'startup s':>9} {'calib CPU s':>11} {'peak RSS MB':>11} {'RSS/input':>9} {'windows':>7} {'held-out mg':>11} "
          f"{'exit':>4} {'load':>5}")
    for r in rows:
        ho = r["heldout_rms_mg"]
        print(f"{r['days']:4d} {r['format']:>3} {r['samples']:11d} {r['input_bytes'] / 1e6:9.0f} {r['wall_s']:7.2f} "
              f"{r['read_s']:7.2f} {r['calibrate_s']:8.2f} {r['startup_s']:9.2f} {r['calibrate_cpu_s'] or float('nan'):11.2f} "
              f"{r['peak_rss_bytes'] / 1e6:11.0f} {r['rss_ratio']:9.2f} {r['windows']:7d} "
              f"{ho if ho is None else round(ho, 2)!s:>11} {r['exit']:4d} {r['load_avg_1min']:5.1f}")
    print("(wall times are only meaningful on an idle machine: compare the load column with the number of cores; "
          "CPU seconds count all threads)")
    npy = [r for r in rows if r["format"] == "npy"]
    out: dict = {"bench": "calibrate", "command": " ".join([Path(sys.executable).name] + sys.argv),
                 "fs_hz": FS, "bytes_per_sample": DTYPE.itemsize, "rows": rows,
                 "targets": {"calibrate_s_7d": TARGET_CALIBRATE_S, "rss_ratio": TARGET_RATIO, "wall_s_7d": TARGET_WALL_S}}
    if len(npy) >= 2:
        a, b = npy[0], npy[-1]
        out["growth"] = {"from_days": a["days"], "to_days": b["days"], "samples_x": b["samples"] / a["samples"],
                         "calibrate_s_x": b["calibrate_s"] / a["calibrate_s"], "read_s_x": b["read_s"] / a["read_s"],
                         "peak_rss_x": b["peak_rss_bytes"] / a["peak_rss_bytes"]}
        g = out["growth"]
        print(f"growth {a['days']} -> {b['days']} days: samples x{g['samples_x']:.1f}, calibrate x{g['calibrate_s_x']:.1f}, "
              f"read x{g['read_s_x']:.1f}, peak RSS x{g['peak_rss_x']:.1f}")
    if args.peers is not False or args.reference:
        out["peers"] = side_by_side(npy, peer_rows, run_peers, missing, forms, peer_lib.versions(), args.peer_timeout)
        out["peers"]["gate_g"] = args.peer_gate
        if args.peer_gate is not None:
            print(f"NOTE: the peers ran with their sphere/cube gate overridden to {args.peer_gate:g} g (theirs: 0.3 g): "
                  "a diagnostic of their fit's cost and error, not how their users run them")
    last = npy[-1] if npy else None
    if last is not None and last["days"] == 7:
        met = {"calibrate_s": last["calibrate_s"] <= TARGET_CALIBRATE_S, "rss_ratio": last["rss_ratio"] <= TARGET_RATIO,
               "wall_s": last["wall_s"] <= TARGET_WALL_S}
        out["targets_met"] = met
        print(f"targets for 7 days: calibration <= {TARGET_CALIBRATE_S:g} s: {'met' if met['calibrate_s'] else 'NOT met'} "
              f"({last['calibrate_s']:.2f} s); peak memory <= {TARGET_RATIO:g}x input: "
              f"{'met' if met['rss_ratio'] else 'NOT met'} ({last['rss_ratio']:.2f}x); wall <= {TARGET_WALL_S:g} s: "
              f"{'met' if met['wall_s'] else 'NOT met'} ({last['wall_s']:.2f} s)")
    out["speed_targets"] = speed_targets(npy, peer_rows)
    if args.json:
        args.json.write_text(json.dumps(out, indent=2) + "\n")
    return 0


def speed_targets(npy: list[dict], peer_rows: list[dict]) -> dict:
    """The whole-process targets as ratios within this run (they hold on a loaded machine; the absolute
    times only on an idle one): 7 days in <= 1.5 s and calibrated in <= 1.0 s, peak RSS <= 1.2x the
    input, every peer >= 5x slower, and the numpy reference not faster on one day."""
    by = {r["days"]: r for r in npy}
    res: dict = {}
    if 7 in by:
        g = by[7]
        res["wall_7d_s"] = {"value": g["wall_s"], "target": TARGET_WALL_7D_S, "met": g["wall_s"] <= TARGET_WALL_7D_S}
        res["calibrate_7d_s"] = {"value": g["calibrate_s"], "target": TARGET_CALIBRATE_S,
                                 "met": g["calibrate_s"] <= TARGET_CALIBRATE_S}
        res["rss_ratio_7d"] = {"value": g["rss_ratio"], "target": TARGET_RATIO, "met": g["rss_ratio"] <= TARGET_RATIO}
    for p in peer_rows:
        g = by.get(p["days"])
        if g is None or p["days"] not in (1, 7) or (p["peer"] == "numpy-ref" and p["days"] != 1):
            continue
        x = p["wall_s"] / g["wall_s"]
        need = 1.0 if p["peer"] == "numpy-ref" else TARGET_PEER_X
        res[f"{p['peer']} ({p['form']}) {p['days']}d wall / gravcal"] = {"value": x, "target": need, "met": x >= need}
    for k, v in res.items():
        print(f"target {k}: {v['value']:.2f} (target {'<=' if k.endswith('_s') or 'rss' in k else '>='} "
              f"{v['target']:g}): {'met' if v['met'] else 'NOT met'}")
    return res


if __name__ == "__main__":
    sys.exit(main())
