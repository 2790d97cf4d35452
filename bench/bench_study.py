"""Benchmark: a study of N one-day recordings, files per second, for several N in one run.

    python bench/bench_study.py [--files 8 20] [--hours 24] [--fs 100] [--workers 0 2] [--forced]
                                [--processes] [--repeat 3] [--cache DIR] [--json PATH]

Compares, on the same files (the first N of one cached set): a sequential loop over the Python API in
this process (``gravcal.calibrate(gravcal.read(f))``, imports already paid: the in-process rate), and
the whole ``gravcal calibrate FILES --out results.csv --workers W`` process for each W (0: in that
process; 2: the study's plan, io/study_plan.py: Dask's local scheduler with 2 worker processes forked
from that one, started while the next file calibrates there when the timed first file shows idle cores),
interpreter start, imports and the workers' start and close included. With ``--forced`` also
``--workers 2`` with the plan's Dask workers started whatever its timing says. With ``--processes``
also ``run_study`` on a dask.distributed LocalCluster of two spawned worker processes started and
closed in this process (what ``--scheduler`` gives; dask.distributed already imported here). The runs take turns (``--repeat``
rounds, in the same order each round) and each row reports its fastest: on a shared machine other
load only ever slows a run down. Each row also gives the CPU time it used (this process's for the API
loop, the child's user + sys for a command), which load inflates far less than wall time.

Printed: the load average before and after, *x* = a row's files/s over the in-process rate (the
issue's criterion: ``--workers 2`` >= 0.9x) and *x w0* = over ``gravcal calibrate --workers 0`` (the
same command in one process: what choosing 2 workers gains or loses). On a machine with no idle core
(load average >= the cores) two workers cannot gain and the plan stays in one process; read *x* from
a quiet machine.

The gravcal package's bytecode is compiled first (bench_calibrate.compile_gravcal_bytecode, as ``pip
install`` leaves it): with PYTHONDONTWRITEBYTECODE set and an editable install every command would
otherwise compile its modules from source (~0.1 s of a core each start), a cost the in-process loop
pays before its clock.

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

from bench_calibrate import compile_gravcal_bytecode

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

    t0, c0 = time.perf_counter(), time.process_time()
    ok = 0
    for p in paths:
        try:
            cal = gravcal.calibrate(gravcal.read(p))
            ok += cal.status == "ok"  # the verdict, as the study's rows count it
        except ValueError:
            pass
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {"how": "sequential Python API loop", "wall_s": wall, "cpu_s": cpu, "files_per_s": len(paths) / wall,
            "ok": ok}


def _children_cpu() -> float:
    """User + system CPU [s] of this process's finished children."""
    import resource

    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


FORCED = ("import sys; import gravcal.io.study_plan as plan; plan.DASK_START_S = -1.0; "
          "sys.argv = ['gravcal', *sys.argv[1:]]; from gravcal.cli.main import console; console()")


def cli_study(paths: list[Path], workers: int, forced: bool = False) -> dict:
    """The whole ``gravcal calibrate FILES --out R --workers W`` process, as a user runs it; ``forced``: the
    plan's Dask workers started whatever the timed file says (io/study_plan.py DASK_START_S below 0)."""
    import subprocess

    script = Path(sys.executable).parent / "gravcal"
    cmd = [str(script)] if script.is_file() else [sys.executable, "-m", "gravcal.cli.main"]
    if forced:
        cmd = [sys.executable, "-c", FORCED]
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "results.csv"
        before = _children_cpu()  # the children run one at a time: the difference is this one's
        t0 = time.perf_counter()
        r = subprocess.run([*cmd, "calibrate", *map(str, paths), "--out", str(out), "--workers", str(workers)],
                           capture_output=True, text=True, timeout=3600)
        wall, cpu = time.perf_counter() - t0, _children_cpu() - before
        ok = out.read_text().count(",ok,")
    plan = r.stderr.strip().splitlines()[-1] if r.stderr.strip() else ""
    return {"how": f"gravcal calibrate --workers {workers}" + (", Dask workers forced" if forced else ""),
            "workers": workers, "wall_s": wall, "cpu_s": cpu,
            "files_per_s": len(paths) / wall, "ok": ok, "status": r.returncode, "summary": plan}


def process_cluster_study(paths: list[Path]) -> dict:
    """run_study on a LocalCluster of two worker processes (spawned, one thread each), started and closed
    inside the clock."""
    import dask
    from dask.distributed import LocalCluster

    from gravcal.io.offline import Options
    from gravcal.io.study import run_study

    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "results.csv"
        t0, c0 = time.perf_counter(), time.process_time() + _children_cpu()
        environ = {k: v for k, v in dask.config.get("distributed.nanny.pre-spawn-environ", default={}).items()
                   if k != "MALLOC_TRIM_THRESHOLD_"}  # with it every large numpy temporary is a fresh mmap
        with dask.config.set({"distributed.nanny.pre-spawn-environ": environ}):
            cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
        try:
            run_study(paths, out, Options(), scheduler=cluster.scheduler_address, quiet=True)
        finally:
            cluster.close()
        wall, cpu = time.perf_counter() - t0, time.process_time() + _children_cpu() - c0
        ok = out.read_text().count(",ok,")
    return {"how": "run_study, LocalCluster of 2 worker processes", "workers": 2, "wall_s": wall, "cpu_s": cpu,
            "files_per_s": len(paths) / wall, "ok": ok}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", type=int, nargs="+", default=[8, 20], help="study sizes (the first N of one set)")
    ap.add_argument("--hours", type=float, default=24.0, help="length of each file [h] (default 24: one day)")
    ap.add_argument("--fs", type=float, default=100.0)
    ap.add_argument("--workers", type=int, nargs="+", default=[0, 2], help="gravcal calibrate --workers W runs")
    ap.add_argument("--processes", action="store_true", help="also a LocalCluster of two worker processes")
    ap.add_argument("--forced", action="store_true",
                    help="also --workers 2 with the Dask workers started whatever the plan's timing says")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--cache")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    most = max(a.files)
    folder = cache_dir(a.cache) / f"bench_study_{most}x{a.hours:g}h_{a.fs:g}hz_seed{SEED}"
    folder.mkdir(parents=True, exist_ok=True)
    every = generate(folder, most, a.hours, a.fs)
    compile_gravcal_bytecode()
    load = [os.getloadavg()]
    results = []
    for n in sorted(a.files):
        paths = every[:n]
        runs = [lambda: sequential_api(paths)] + [lambda w=w: cli_study(paths, w) for w in a.workers]
        if a.forced:
            runs.append(lambda: cli_study(paths, 2, forced=True))
        if a.processes:
            runs.append(lambda: process_cluster_study(paths))
        rounds: list[list[dict]] = []
        for _ in range(a.repeat):
            rounds.append([run() for run in runs])
        best = [min((rnd[i] for rnd in rounds), key=lambda r: r["wall_s"]) for i in range(len(runs))]
        for i, r in enumerate(best):  # each round's ratio to the loop of the same round: load shared alike
            r["round_x"] = [rnd[0]["wall_s"] / rnd[i]["wall_s"] for rnd in rounds]
            r["round_wall_s"] = [rnd[i]["wall_s"] for rnd in rounds]
        results.append({"files": n, "runs": best})
        load.append(os.getloadavg())
    print(f"{a.hours:g} h files at {a.fs:g} Hz, {os.cpu_count()} CPUs, load average (1, 5, 15 min) "
          f"{' -> '.join(', '.join(f'{x:.1f}' for x in l) for l in (load[0], load[-1]))}; "
          f"every row the fastest of {a.repeat} rounds")
    print("x: files/s over the API loop's (the in-process rate); x w0: over `--workers 0`'s; "
          "rounds: x of each round against the loop of the same round")
    for res in results:
        base = res["runs"][0]["files_per_s"]
        w0 = next((r["files_per_s"] for r in res["runs"] if r.get("workers") == 0 and "forced" not in r["how"]),
                  None)
        print(f"{res['files']} files {'':<42} {'wall s':>8} {'CPU s':>6} {'files/s':>8} {'x':>6} {'x w0':>6}  rounds")
        for r in res["runs"]:
            xw0 = f"{r['files_per_s'] / w0:6.2f}" if w0 else f"{'':6}"
            print(f"  {r['how']:<50} {r['wall_s']:8.2f} {r['cpu_s']:6.2f} {r['files_per_s']:8.3f} "
                  f"{r['files_per_s'] / base:6.2f} {xw0}  {' '.join(f'{x:.2f}' for x in r['round_x'])}"
                  f"  ({r['ok']} of {res['files']} ok)")
            if r.get("summary"):
                print(f"      {r['summary']}")
    if a.json:
        a.json.write_text(json.dumps({"hours": a.hours, "fs": a.fs, "load": load, "studies": results}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
