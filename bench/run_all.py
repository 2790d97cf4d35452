"""Every benchmark in one command: writes docs/benchmarks.md (a table per part) and docs/benchmarks.json.

    python bench/run_all.py [--quick] [--skip PART ...] [--only PART ...] [--out DIR] [--timeout S] [--merge]
    python bench/run_all.py --render [--out DIR]      (re-write benchmarks.md from benchmarks.json, nothing run)

Parts (each a script of its own, run as a child process with --json, so one failing part is reported
in the page with its error and the others still run):

    accuracy    bench_accuracy.py     held-out static-window error, gravcal vs the peers, measured + simulated:
                                      the peers on the raw samples as their users run them, and (--peer-input
                                      windows) their own models fitted on the same windows as gravcal
    speed       bench_calibrate.py    `gravcal calibrate` on 1..7 simulated days at 100 Hz vs the peers
    daemon      bench_daemon.py       latency frame-in -> socket-out and CPU at 200 Hz (1 and 32 clients),
                                      RSS over >= 2e7 samples extrapolated to 1e8;
                bench_server.py       replay throughput (1 and 32 clients)
    efficiency  bench_efficiency.py   estimator efficiency against the Cramér–Rao bound
    codec       bench_codec.py        frame decoding, driver CPU at 200 Hz
    estimator   bench_estimator.py    cost per window / per batch fit
    detector    bench_detector.py     detector throughput (text output)
    faults      bench_faults.py       fault campaign (--long)
    soak        bench_soak.py         accelerated week-long soak
    gyro        bench_gyro.py         gyro calibration

--quick shrinks every part (seconds instead of tens of minutes); the page says which mode ran.
Peers (scikit-digital-health, actipy, imucal) are optional: the page and the console say which
are missing and how to install them (pip install -e .[bench]); the rest still runs.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

from report_page import render_page  # bench/ is the script's folder: on sys.path when it runs

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
sys.path.insert(0, str(BENCH))


# -- the parts: name -> list of (label, argv builder(quick, json_path) -> argv after the script) ----------
def _script_accepts(script: Path, flag: str) -> bool:
    """Does the script's --help mention ``flag`` (other helpers' scripts grow options over time)?"""
    try:
        out = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return flag in out.stdout


Step = tuple[str, str, Callable[[bool, str], list[str]]]  # (label, script, argv builder)

PARTS: dict[str, list[Step]] = {
    "accuracy": [("accuracy", "bench_accuracy.py", lambda q, j: (["--quick"] if q else []) + ["--json", j]),
                 ("accuracy, the peers' models on the same windows", "bench_accuracy.py",
                  lambda q, j: (["--quick"] if q else []) + ["--peer-input", "windows", "--json", j])],
    "speed": [("speed", "bench_calibrate.py", lambda q, j: (["--days", "1"] if q else []) + ["--json", j])],
    "daemon": [
        ("latency, 1 client", "bench_daemon.py",
         lambda q, j: ["latency", "--clients", "1", "--seconds", "5" if q else "30", "--json", j]),
        ("latency, 32 clients", "bench_daemon.py",
         lambda q, j: ["latency", "--clients", "32", "--seconds", "5" if q else "30", "--json", j]),
        ("CPU, 1 client at 10 Hz", "bench_daemon.py",
         lambda q, j: ["latency", "--clients", "1", "--watch-rate", "10", "--seconds", "5" if q else "30", "--json", j]),
        ("CPU, 32 clients at 10 Hz", "bench_daemon.py",
         lambda q, j: ["latency", "--clients", "32", "--watch-rate", "10", "--seconds", "5" if q else "30", "--json", j]),
        ("replay throughput, 1 client", "bench_server.py",
         lambda q, j: ["--clients", "1", "--samples", "200000" if q else "2000000", "--json", j]),
        ("replay throughput, 32 clients", "bench_server.py",
         lambda q, j: ["--clients", "32", "--samples", "200000" if q else "2000000", "--json", j]),
        ("memory", "bench_daemon.py", lambda q, j: ["memory", "--samples", "2000000" if q else "100000000", "--json", j]),
    ],
    "efficiency": [("efficiency", "bench_efficiency.py",
                    lambda q, j: (["--seeds", "30", "--no-time-series"] if q else ["--seeds", "300"]) + ["--json", j])],
    "codec": [("codec", "bench_codec.py", lambda q, j: (["--skip-drivers"] if q else ["--seconds", "10"]) + ["--json", j])],
    "estimator": [("estimator", "bench_estimator.py", lambda q, j: ["--json", j])],
    "detector": [("detector", "bench_detector.py", lambda q, j: ["--samples", "1000000" if q else "10000000"])],
    "faults": [("faults", "bench_faults.py", lambda q, j: ([] if q else ["--long"]) + ["--json", j])],
    "soak": [("soak", "bench_soak.py", lambda q, j: ["--json", j])],
    "gyro": [("gyro", "bench_gyro.py", lambda q, j: ["--json", j])],
    "engine": [("CPU per sample by calibration model", "bench_engine_terms.py",
                lambda q, j: ["--seconds", "5" if q else "20", "--repeats", "1" if q else "5", "--json", j])],
}
QUICK_FLAG_PARTS = ("soak", "gyro", "faults")  # other helpers' scripts: pass --quick when they accept it


def run_step(label: str, script: str, argv: list[str], timeout: float, log: Callable[[str], None]) -> dict[str, Any]:
    path = BENCH / script
    cmd = [sys.executable, str(path), *argv]
    shown = "python " + " ".join(shlex.quote(str(Path("bench") / script) if a == str(path) else a)
                                 for a in cmd[1:])
    res: dict[str, Any] = {"label": label, "script": script, "command": shown}
    if not path.is_file():
        res.update(status="missing", error=f"bench/{script} does not exist (yet)")
        log(f"  {label}: MISSING bench/{script}")
        return res
    log(f"  {label}: {shown}")
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=REPO)
    except subprocess.TimeoutExpired as exc:
        res.update(status="failed", seconds=time.perf_counter() - t0, error=f"timed out after {timeout:.0f} s",
                   stdout_tail=_tail(exc.stdout), stderr_tail=_tail(exc.stderr))
        log(f"    timed out after {timeout:.0f} s")
        return res
    res["seconds"] = time.perf_counter() - t0
    res["stdout"] = p.stdout[-20000:]
    res["stderr_tail"] = _tail(p.stderr)
    if p.returncode != 0:
        err = _last_error(p.stderr) or f"exit status {p.returncode}"
        res.update(status="failed", error=err)
        log(f"    FAILED ({err})")
        return res
    res["status"] = "ok"
    log(f"    ok ({res['seconds']:.0f} s)")
    return res


def _tail(text: Any, n: int = 3000) -> str:
    if text is None:
        return ""
    if isinstance(text, bytes):
        text = text.decode("utf-8", "replace")
    return text[-n:]


def _last_error(stderr: str) -> str:
    lines = [ln for ln in stderr.strip().splitlines() if ln.strip()]
    if not lines:
        return ""
    if "--json" in stderr and "unrecognized arguments" in stderr:
        return "the script does not accept --json yet: " + lines[-1]
    return lines[-1][:500]


def run_part(name: str, quick: bool, timeout: float, log: Callable[[str], None]) -> dict[str, Any]:
    steps = []
    for label, script, build in PARTS[name]:
        with tempfile.NamedTemporaryFile(suffix=".json", delete=False) as fh:
            jpath = fh.name
        argv = build(quick, jpath)
        if quick and name in QUICK_FLAG_PARTS and (BENCH / script).is_file() and _script_accepts(BENCH / script, "--quick"):
            argv = ["--quick", *argv]
        r = run_step(label, script, argv, timeout, log)
        r["command"] = r["command"].replace(jpath, "OUT.json")
        if r.get("status") == "ok" and "--json" in argv:
            try:
                r["json"] = json.loads(Path(jpath).read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                r.update(status="failed", error=f"ran, but wrote no readable JSON ({exc})")
        try:
            os.unlink(jpath)
        except OSError:
            pass
        steps.append(r)
    status = "ok" if all(s["status"] == "ok" for s in steps) else (
        "missing" if all(s["status"] == "missing" for s in steps) else "failed" if all(
            s["status"] != "ok" for s in steps) else "partial")
    return {"status": status, "steps": steps}


# -- environment ----------------------------------------------------------------------------------------
def machine() -> dict[str, Any]:
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    ram_gb = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                ram_gb = int(line.split()[1]) / 1024 / 1024
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "ram_gb": ram_gb, "os": platform.platform(),
            "python": sys.version.split()[0], "load_avg_at_start": os.getloadavg() if hasattr(os, "getloadavg") else None}


def package_versions() -> dict[str, str | None]:
    from importlib.metadata import PackageNotFoundError, version

    out: dict[str, str | None] = {}
    for name in ("gravcal", "numpy", "scipy", "pyserial", "python-can", "smbus2", "pandas", "matplotlib",
                 "scikit-digital-health", "actipy", "imucal"):
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = None
    return out


def java_version() -> str | None:
    try:
        p = subprocess.run(["java", "-version"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return (p.stderr or p.stdout).strip().splitlines()[0] if (p.stderr or p.stdout).strip() else None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="every part in seconds-to-minutes size")
    ap.add_argument("--skip", action="append", default=[], metavar="PART",
                    help=f"skip a part (repeatable, or comma-separated): {', '.join(PARTS)}")
    ap.add_argument("--only", action="append", default=[], metavar="PART", help="run only these parts")
    ap.add_argument("--out", default=str(REPO / "docs"), help="folder for benchmarks.md and benchmarks.json (default docs/)")
    ap.add_argument("--timeout", type=float, default=7200.0, help="per script [s] (default 7200)")
    ap.add_argument("--merge", action="store_true",
                    help="keep the parts not run now from the existing OUT/benchmarks.json (re-run a few parts)")
    ap.add_argument("--render", action="store_true", help="only re-write benchmarks.md from OUT/benchmarks.json")
    args = ap.parse_args(argv)
    if args.render:
        src = Path(args.out) / "benchmarks.json"
        try:
            report = json.loads(src.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            ap.error(f"--render needs a readable {src}: {exc}")
        (Path(args.out) / "benchmarks.md").write_text(render_page(report), encoding="utf-8")
        print(f"re-rendered {Path(args.out) / 'benchmarks.md'} from {src}")
        return 0
    skip = {x for s in args.skip for x in s.split(",") if x}
    only = {x for s in args.only for x in s.split(",") if x}
    unknown = sorted((skip | only) - set(PARTS))
    if unknown:
        ap.error(f"unknown part(s) {', '.join(unknown)}; parts: {', '.join(PARTS)}")
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)

    def log(msg: str) -> None:
        print(msg, flush=True)

    import peers

    avail = peers.available()
    missing = {k: why for k, why in avail.items() if why is not None}
    if missing:
        log("peers missing (their rows are left out; everything else runs):")
        for k, why in missing.items():
            log(f"  {k}: {why}")
    cmdline = "python bench/run_all.py" + "".join(" " + shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    report: dict[str, Any] = {"command": cmdline, "date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
                              "quick": args.quick, "machine": machine(), "versions": package_versions(),
                              "java": java_version(), "peers": avail, "parts": {}}
    previous: dict[str, Any] = {}
    if args.merge and (out_dir / "benchmarks.json").is_file():
        try:
            old = json.loads((out_dir / "benchmarks.json").read_text(encoding="utf-8"))
            previous = old.get("parts", {})
            report["merged_from"] = old.get("command"), old.get("date")
        except ValueError:
            log(f"--merge: {out_dir / 'benchmarks.json'} is not readable JSON; starting afresh")
    t0 = time.perf_counter()
    for name in PARTS:
        if name in skip or (only and name not in only):
            report["parts"][name] = previous.get(name, {"status": "skipped", "steps": []})
            continue
        log(f"[{name}]")
        try:
            report["parts"][name] = run_part(name, args.quick, args.timeout, log)
        except Exception as exc:  # the runner itself must not die on one part
            report["parts"][name] = {"status": "failed", "steps": [{"label": name, "script": "", "command": "",
                                                                    "status": "failed", "error": f"{type(exc).__name__}: {exc}"}]}
        report["seconds"] = time.perf_counter() - t0
        _write(out_dir, report)  # after every part: a long run leaves a page even if interrupted
    report["seconds"] = time.perf_counter() - t0
    md = _write(out_dir, report)
    log(f"wrote {md} and {out_dir / 'benchmarks.json'}")
    bad = [n for n, p in report["parts"].items() if p["status"] not in ("ok", "skipped")]
    if bad:
        log(f"parts not fully ok: {', '.join(bad)} (see the page)")
    return 0


def _write(out_dir: Path, report: dict[str, Any]) -> Path:
    from gravcal.core.calibration import jsonable

    data = jsonable(report)
    for p in data["parts"].values():  # stdout is in the page when needed; keep the JSON to the figures
        for s in p["steps"]:
            if "json" in s:
                s.pop("stdout", None)
    (out_dir / "benchmarks.json").write_text(json.dumps(data, indent=1), encoding="utf-8")
    md = out_dir / "benchmarks.md"
    md.write_text(render_page(report), encoding="utf-8")
    return md


if __name__ == "__main__":
    sys.exit(main())
