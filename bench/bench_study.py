"""Benchmark: a study of N one-day recordings, files per second.

    python bench/bench_study.py [--files 4] [--hours 24] [--fs 100] [--workers 1 2] [--repeat 2] [--cache DIR]
                                [--json PATH]

Compares, on the same files: a sequential loop over the Python API in this process
(``gravcal.calibrate(gravcal.read(f))``, imports already paid), and ``run_study`` (what
``gravcal calibrate DIR --out results.csv --workers N`` runs) on a local dask.distributed
cluster with 1 and 2 workers, whole run including the cluster's start and stop. On this 2-core
machine 2 workers can at most double the rate; the cluster's start-up is a fixed cost that a
longer study amortises. The three runs are repeated in turn (``--repeat``) and each reports its
fastest: on a shared machine other load only ever slows a run down. The load average is printed.

Input: N consecutive days of one simulated daily-living recording (core.simulate.simulate_blocks,
seed 0, default sensor), one structured .npy per day (t float64, ax/ay/az float32 duty cycles),
generated once block by block and cached OUTSIDE the repository ($GRAVCAL_CACHE, else
~/.cache/gravcal).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SEED = 0
DTYPE = np.dtype([("t", "<f8"), ("ax", "<f4"), ("ay", "<f4"), ("az", "<f4")])
BLOCK = 1 << 18


def cache_dir(arg: str | None) -> Path:
    d = Path(arg or os.environ.get("GRAVCAL_CACHE") or Path.home() / ".cache" / "gravcal")
    d.mkdir(parents=True, exist_ok=True)
    return d


def generate(folder: Path, n_files: int, hours: float, fs: float) -> list[Path]:
    """n_files consecutive pieces of `hours` each of one simulation (cached)."""
    from gravcal.core.samples import raw_triad
    from gravcal.core.simulate import simulate_blocks
    from gravcal.cli.cmd_simulate import build_model

    paths = [folder / f"day{i:02d}.npy" for i in range(n_files)]
    if all(p.exists() for p in paths):
        return paths
    per = int(round(hours * 3600 * fs))
    mms = [np.lib.format.open_memmap(p.with_suffix(".partial.npy"), mode="w+", dtype=DTYPE, shape=(per,))
           for p in paths]
    i = 0
    t0 = time.perf_counter()
    for block in simulate_blocks("daily_living", build_model(SEED), seed=SEED, duration=n_files * hours * 3600.0,
                                 fs=fs, block=BLOCK):
        raw = raw_triad(block)
        j = 0  # split the block at file borders
        while j < len(block):
            f, off = divmod(i, per)
            if f >= n_files:
                break
            take = min(len(block) - j, per - off)
            mm = mms[f]
            mm["t"][off:off + take] = block["t"][j:j + take]
            for c, name in enumerate(("ax", "ay", "az")):
                mm[name][off:off + take] = raw[j:j + take, c]
            i, j = i + take, j + take
        print(f"  generating: {100 * i / (per * n_files):5.1f} % ({time.perf_counter() - t0:.0f} s)", end="\r",
              file=sys.stderr)
    print(file=sys.stderr)
    for mm, p in zip(mms, paths):
        mm.flush()
        del mm
        p.with_suffix(".partial.npy").rename(p)
    return paths


def sequential_api(paths: list[Path]) -> dict:
    import gravcal

    gravcal.calibrate  # noqa: B018 - imports paid before the clock starts
    import gravcal.api  # noqa: F401

    t0 = time.perf_counter()
    ok = 0
    for p in paths:
        try:
            cal = gravcal.calibrate(gravcal.read(p))
            ok += cal.status == "ok"  # the verdict, as the study's rows count it
        except ValueError:
            pass
    wall = time.perf_counter() - t0
    return {"how": "sequential Python API", "wall_s": wall, "files_per_s": len(paths) / wall, "ok": ok}


def dask_study(paths: list[Path], workers: int) -> dict:
    from gravcal.io.offline import Options
    from gravcal.io.study import run_study

    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "results.csv"
        t0 = time.perf_counter()
        run_study(paths, out, Options(), workers=workers, quiet=True)
        wall = time.perf_counter() - t0
        ok = out.read_text().count(",ok,")
    return {"how": f"run_study, dask LocalCluster, {workers} worker(s)", "workers": workers, "wall_s": wall,
            "files_per_s": len(paths) / wall, "ok": ok}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", type=int, default=4)
    ap.add_argument("--hours", type=float, default=24.0, help="length of each file [h] (default 24: one day)")
    ap.add_argument("--fs", type=float, default=100.0)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--cache")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    folder = cache_dir(a.cache) / f"bench_study_{a.files}x{a.hours:g}h_{a.fs:g}hz_seed{SEED}"
    folder.mkdir(parents=True, exist_ok=True)
    paths = generate(folder, a.files, a.hours, a.fs)
    runs = [lambda: sequential_api(paths)] + [lambda w=w: dask_study(paths, w) for w in a.workers]
    best: list[dict] = [{}] * len(runs)
    for _ in range(a.repeat):
        for i, run in enumerate(runs):
            r = run()
            if not best[i] or r["wall_s"] < best[i]["wall_s"]:
                best[i] = r
    rows = best
    n = a.files
    print(f"{n} files of {a.hours:g} h at {a.fs:g} Hz ({os.cpu_count()} CPUs, load average "
          f"{', '.join(f'{x:.1f}' for x in os.getloadavg())}), fastest of {a.repeat}")
    for r in rows:
        print(f"  {r['how']:<45} {r['wall_s']:7.1f} s  {r['files_per_s']:.3f} files/s  ({r['ok']} of {n} ok)")
    if a.json:
        a.json.write_text(json.dumps({"files": n, "hours": a.hours, "fs": a.fs, "runs": rows}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
