"""A whole study: every recording of a directory (or a list) calibrated, one results row per file.

Rows are appended and flushed as files finish, so an interrupted run (Ctrl-C) leaves a valid results
file holding the files done so far, and a re-run skips them (resume). Rows are keyed by the file's
resolved path, so a re-run from another folder finds them; an error row is not done: a re-run
replaces it with a new attempt. The work runs on a
dask.distributed cluster: a local one (``workers``) or an existing one (``scheduler``); with
``workers=0`` in this process. Dask and tqdm are imported here only (the ``study`` extra).
"""
from __future__ import annotations

import csv
import logging
import os
import sys
from pathlib import Path
from typing import Any, Iterable, Iterator

from ..errors import InputError
from .offline import Options

log = logging.getLogger(__name__)

SUFFIXES = (".csv", ".csv.gz", ".gz", ".npy", ".parquet", ".gt3x", ".agdc", ".cwa", ".bin")
AXES = ("x", "y", "z")
PARAMETERS = ([f"offset_{a}" for a in AXES] + [f"sensitivity_{a}{b}" for a in AXES for b in AXES])
FIELDS = ("file", "status", "model", *PARAMETERS, "heldout_rms_mg", "n_windows", "n_excluded_filler", "units", "message",
          "uncalibrated_rms_mg", "calibrated_file")
"""Results columns: offset [raw], sensitivity [raw per g] (a [g] = sensitivity^-1 (raw - offset)); errors
[mg] of |a| - 1 g: held-out, and uncalibrated (the start scored on every window; empty when the start came
from these data); calibrated_file: where --write-dir wrote the calibrated samples."""


def discover(paths: Iterable[Path]) -> list[Path]:
    """The recordings named: files as given, directories searched (recursively) for known suffixes."""
    found: list[Path] = []
    for p in paths:
        if p.is_dir():
            inside = sorted(f for f in p.rglob("*") if f.is_file() and f.name.lower().endswith(SUFFIXES)
                            and ".calibrated." not in f.name.lower())  # a study's own --write-dir output
            if not inside:
                raise InputError(f"{p}: no recordings in this directory (looked for {', '.join(SUFFIXES)})")
            found += inside
        elif p.exists():
            found.append(p)
        else:
            raise InputError(f"{p}: no such file or directory")
    return list(dict.fromkeys(f.resolve() for f in found))


def done_files(out: Path) -> set[str]:
    """Files already in the results (resolved paths). A torn last line, from a kill, is dropped and an
    error row is removed (the results file rewritten without them): those files are calibrated again."""
    if not out.exists() or out.stat().st_size == 0:
        return set()
    with open(out, newline="", encoding="utf-8") as f:
        text = f.read()
    lines = text.splitlines(keepends=True)
    if lines and not lines[-1].endswith("\n"):
        lines = lines[:-1]  # an unfinished row: that file is calibrated again
        with open(out, "w", newline="", encoding="utf-8") as f:
            f.writelines(lines)
    rows = list(csv.DictReader(lines))
    if lines and rows and "file" not in rows[0]:
        raise InputError(f"{out}: exists but is not a gravcal results file (no 'file' column); choose another --out")
    if any(r.get("status") == "error" for r in rows):
        kept = [r for r in rows if r.get("status") != "error"]
        tmp = out.with_name(out.name + ".partial")
        with open(tmp, "w", newline="", encoding="utf-8") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0].keys()), extrasaction="ignore")
            writer.writeheader()
            writer.writerows(kept)
        tmp.replace(out)
        rows = kept
    return {str(Path(r["file"]).resolve()) for r in rows}


def calibrate_file(path: str, opts: Options, write_to: str | None = None) -> dict[str, Any]:
    """One results row; never raises (a broken file is a row with its error). ``write_to``: where its
    calibrated samples go (io.calibrated; only for status ok or partial)."""
    row: dict[str, Any] = {"file": path}
    quiet = logging.getLogger("gravcal")
    level, quiet.level = quiet.level, logging.ERROR  # the row carries the warnings; no interleaved log lines
    try:
        return _calibrate_file(path, opts, row, write_to)
    finally:
        quiet.setLevel(level)


def _calibrate_file(path: str, opts: Options, row: dict[str, Any], write_to: str | None = None) -> dict[str, Any]:
    from . import offline

    try:
        rec, t_read, c_read = offline.read(path, opts)
    except InputError as exc:
        return {**row, "status": "error", "message": _one_line(exc)}
    except Exception as exc:  # noqa: BLE001 - an unreadable file must not end the study
        return {**row, "status": "error", "message": _one_line(f"{type(exc).__name__}: {exc}")}
    row.update(units=rec.units, n_excluded_filler=rec.n_filler)
    try:
        report, out = offline.calibrate(rec, opts, (t_read, c_read))
    except ValueError as exc:  # no usable stillness, too few windows, nothing determined
        return {**row, "status": "refused", "message": _one_line(exc)}
    except Exception as exc:  # noqa: BLE001
        return {**row, "status": "error", "message": _one_line(f"{type(exc).__name__}: {exc}")}
    cal = report.calibration
    # the verdict of `calibrate --json` (gravcal.core.verdict.STATUSES): ok, partial, not_improved, unreliable, refused
    row.update(status=out["status"], model=cal.model, n_windows=int(cal.n_windows),
               heldout_rms_mg=out.get("heldout_rms_mg"),
               message=_one_line("; ".join(filter(None, [out.get("reason"), *rec.warnings]))))
    row["uncalibrated_rms_mg"] = (out.get("verdict") or {}).get("uncalibrated_rms_mg")
    for i, a in enumerate(AXES):
        row[f"offset_{a}"] = float(cal.offset[i])
        for j, b in enumerate(AXES):
            row[f"sensitivity_{a}{b}"] = float(cal.sensitivity[i, j])
    from gravcal.core.verdict import TRUSTED

    if write_to and out["status"] in TRUSTED:
        from .calibrated import write_for

        try:
            row["calibrated_file"] = str(write_for(write_to, rec, cal, columns=opts.columns,
                                                   check_saturation=opts.check_saturation, report=out))
        except (InputError, OSError) as exc:
            return {**row, "status": "error", "message": _one_line(f"writing {write_to}: {exc}")}
    return row


def _one_line(msg: Any, limit: int = 300) -> str:
    text = " ".join(str(msg).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _results(files: list[str], opts: Options, workers: int | None, scheduler: str | None,
             targets: list[str | None]) -> Iterator[dict[str, Any]]:
    if workers == 0 and not scheduler:
        for f, w in zip(files, targets):
            yield calibrate_file(f, opts, w) if w else calibrate_file(f, opts)
        return
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise InputError("a study on Dask needs dask.distributed: pip install 'gravcal[study]' "
                         "(or --workers 0 to run in this process)") from None
    if logging.getLogger().level > logging.INFO:  # the cluster's start/stop chatter only with -v
        logging.getLogger("distributed").setLevel(logging.WARNING)
    cluster = None
    if scheduler:
        try:
            client = Client(scheduler, timeout="15s")
        except (OSError, TimeoutError, ValueError) as exc:
            raise InputError(f"--scheduler {scheduler}: cannot reach a dask scheduler there "
                             f"({type(exc).__name__}: {_one_line(exc, 120)})") from None
    else:
        import dask

        n = min(workers or os.cpu_count() or 1, len(files))  # no worker started for no file
        # Dask's default MALLOC_TRIM_THRESHOLD_ fixes glibc's mmap threshold, so each large numpy
        # temporary becomes a fresh mmap with its page faults: measured 2x the CPU per recording
        environ = {k: v for k, v in dask.config.get("distributed.nanny.pre-spawn-environ", default={}).items()
                   if k != "MALLOC_TRIM_THRESHOLD_"}
        # the nannies set these in this process's environment to pass them on, and leave them: a calibration
        # here afterwards would read OPENBLAS_NUM_THREADS=1 as "BLAS started single-threaded" and not limit it
        kept = {k: os.environ.get(k) for k in environ}
        try:
            with dask.config.set({"distributed.nanny.pre-spawn-environ": environ}):
                cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0")
        finally:
            for k, v in kept.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        client = Client(cluster)
    try:
        futures = (client.map(calibrate_file, files, targets, opts=opts, pure=False) if any(targets)
                   else client.map(calibrate_file, files, opts=opts, pure=False))
        file_of = {fut.key: f for fut, f in zip(futures, files)}
        for fut in as_completed(futures):
            try:
                yield fut.result()
            except Exception as exc:  # noqa: BLE001 - a worker killed (e.g. out of memory) on one file
                yield {"file": file_of[fut.key], "status": "error", "message": _one_line(f"{type(exc).__name__}: {exc}")}
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _progress(total: int, off: bool) -> Any:
    """A tqdm bar on a terminal; without tqdm (or off) a bar that shows nothing."""
    try:
        from tqdm import tqdm
    except ImportError:
        if not off:
            log.info("no progress bar: pip install 'gravcal[study]' for one")
        from contextlib import nullcontext
        from types import SimpleNamespace

        return nullcontext(SimpleNamespace(update=lambda n: None))
    return tqdm(total=total, unit="file", disable=off)


def write_targets(files: list[str], write_dir: Path, fmt: str) -> list[str]:
    """Where each file's calibrated samples go: DIR/NAME.calibrated.FMT, NAME the file's name without its
    recording suffix; names that two files share get a short hash of the path."""
    import hashlib

    def stem(f: str) -> str:
        name = Path(f).name
        low = name.lower()
        return next((name[:-len(s)] for s in SUFFIXES if low.endswith(s)), name)

    stems = [stem(f) for f in files]
    return [str(write_dir / (f"{s}.calibrated.{fmt}" if stems.count(s) == 1 else
                             f"{s}-{hashlib.sha1(f.encode()).hexdigest()[:8]}.calibrated.{fmt}"))
            for s, f in zip(stems, files)]


EXIT_ERROR_ROWS = 2


def run_study(paths: list[Path], out: Path, opts: Options, *, workers: int | None = None,
              scheduler: str | None = None, quiet: bool = False, write_dir: Path | None = None,
              write_format: str = "npy") -> int:
    """Calibrate every recording in ``paths`` into ``out``; returns the exit status: 0 when no row is an
    error (refused rows are results), EXIT_ERROR_ROWS when a file could not be read or calibrated (its
    row says why; a re-run tries it again). ``write_dir``: each file's calibrated samples, as
    ``write_format``, there (io.calibrated)."""
    if workers is not None and workers < 0:
        raise InputError(f"--workers must be 0 (in this process) or more, got {workers}")
    if write_dir is not None and not write_dir.is_dir():
        raise InputError(f"--write-dir {write_dir}: no such directory")
    files = [str(p) for p in discover(paths)]
    done = done_files(out)
    todo = [f for f in files if f not in done]
    targets = write_targets(todo, write_dir, write_format) if write_dir is not None else [None] * len(todo)
    if done:
        log.warning("%s: %d of %d files already done, skipped", out, len(files) - len(todo), len(files))
    new = not out.exists() or out.stat().st_size == 0
    counts: dict[str, int] = {}
    with open(out, "a", newline="", encoding="utf-8") as f, \
            _progress(len(todo), quiet or not sys.stderr.isatty()) as bar:
        writer = csv.DictWriter(f, fieldnames=FIELDS, extrasaction="ignore")
        if new:
            writer.writeheader()
            f.flush()
        for row in (_results(todo, opts, workers, scheduler, targets) if todo else ()):  # no cluster for nothing
            writer.writerow(row)
            f.flush()
            counts[row["status"]] = counts.get(row["status"], 0) + 1
            bar.update(1)
    summary = ", ".join(f"{n} {s}" for s, n in sorted(counts.items())) or "nothing new"
    if not quiet:
        print(f"gravcal: {len(todo)} file(s) calibrated ({summary}); results in {out}", file=sys.stderr)
    if counts.get("error"):
        print(f"gravcal: error: {counts['error']} file(s) could not be calibrated (status error in {out}; "
              f"a re-run tries them again)", file=sys.stderr)
        return EXIT_ERROR_ROWS
    return 0
