"""A whole study: every recording of a directory (or a list) calibrated, one results row per file.

Rows are appended and flushed as files finish, so an interrupted run (Ctrl-C) leaves a valid results
file holding the files done so far, and a re-run skips them (resume). Rows are keyed by the file's
resolved path, so a re-run from another folder finds them; an error row is not done: a re-run
replaces it with a new attempt. The work runs on an existing dask.distributed cluster (``scheduler``),
on Dask's local scheduler, its workers (forked processes, or threads) started while this process
calibrates the first files (``workers``; io/study_plan.py), or with ``workers=0`` in this process. Dask
and tqdm are imported here and in io/study_plan.py only (the ``study`` extra).
"""
from __future__ import annotations

import csv
import logging
import os
import sys
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterable, Iterator

from ..errors import InputError
from . import study_plan
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
    with _rows_carry_the_warnings():
        return _calibrate_file(path, opts, row, write_to)


_quiet = threading.Lock()
_quiet_state = [0, logging.NOTSET]  # files being calibrated in this process, the gravcal logger's level before


@contextmanager
def _rows_carry_the_warnings() -> Iterator[None]:
    """The gravcal logger at ERROR while any file of the study is being calibrated in this process (worker
    threads overlap): the row carries the warnings; no interleaved log lines."""
    quiet = logging.getLogger("gravcal")
    with _quiet:
        if _quiet_state[0] == 0:
            _quiet_state[1], quiet.level = quiet.level, logging.ERROR
        _quiet_state[0] += 1
    try:
        yield
    finally:
        with _quiet:
            _quiet_state[0] -= 1
            if _quiet_state[0] == 0:
                quiet.setLevel(_quiet_state[1])


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
             targets: list[str | None], plan: study_plan.Plan | None = None) -> Iterator[dict[str, Any]]:
    plan = plan if plan is not None else study_plan.Plan()

    def here(f: str, w: str | None) -> dict[str, Any]:
        return calibrate_file(f, opts, w) if w else calibrate_file(f, opts)

    if scheduler:
        yield from _on_scheduler(scheduler, files, targets, opts, plan)
        return
    if workers == 0:
        plan.reason = "--workers 0"
        for f, w in zip(files, targets):
            yield here(f, w)
            plan.in_process += 1
        return
    yield from study_plan.local_rows(list(zip(files, targets)), here, _error_row, workers or os.cpu_count() or 1, plan)


def _on_scheduler(scheduler: str, files: list[str], targets: list[str | None], opts: Options,
                  plan: study_plan.Plan) -> Iterator[dict[str, Any]]:
    try:
        from dask.distributed import Client
    except ImportError:
        raise InputError("--scheduler needs dask.distributed: pip install 'gravcal[study]'") from None
    if logging.getLogger().level > logging.INFO:  # the client's chatter only with -v
        logging.getLogger("distributed").setLevel(logging.WARNING)
    try:
        client = Client(scheduler, timeout="15s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise InputError(f"--scheduler {scheduler}: cannot reach a dask scheduler there "
                         f"({type(exc).__name__}: {_one_line(exc, 120)})") from None
    plan.reason = f"on the scheduler at {scheduler}"
    try:
        for row in _cluster_rows(client, files, targets, opts):
            plan.on_cluster += 1
            yield row
    finally:
        client.close()


def _cluster_rows(client: Any, files: list[str], targets: list[str | None], opts: Options) -> Iterator[dict[str, Any]]:
    """The rows of ``files`` calibrated on ``client``'s cluster, as they finish; a task that dies (a
    worker killed, e.g. out of memory) is an error row."""
    from dask.distributed import as_completed

    futures = (client.map(calibrate_file, files, targets, opts=opts, pure=False) if any(targets)
               else client.map(calibrate_file, files, opts=opts, pure=False))
    file_of = {fut.key: f for fut, f in zip(futures, files)}
    for fut in as_completed(futures):
        try:
            yield fut.result()
        except Exception as exc:  # noqa: BLE001
            yield _error_row(file_of[fut.key], exc)


def _error_row(path: str, exc: BaseException) -> dict[str, Any]:
    """The row of a file whose task raised (a worker killed, out of memory): the study goes on."""
    return {"file": path, "status": "error", "message": _one_line(f"{type(exc).__name__}: {exc}")}


def _progress(total: int, off: bool) -> Any:
    """A tqdm bar on a terminal; without tqdm (or off) a bar that shows nothing (tqdm not imported: its
    import and monitor thread cost a study written to a file ~0.03-0.07 s for nothing)."""
    from contextlib import nullcontext
    from types import SimpleNamespace

    nothing = nullcontext(SimpleNamespace(update=lambda n: None))
    if off:
        return nothing
    try:
        from tqdm import tqdm
    except ImportError:
        log.info("no progress bar: pip install 'gravcal[study]' for one")
        return nothing
    return tqdm(total=total, unit="file")


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
    plan = study_plan.Plan()
    with open(out, "a", newline="", encoding="utf-8") as f, \
            _progress(len(todo), quiet or not sys.stderr.isatty()) as bar:
        writer = csv.DictWriter(f, fieldnames=FIELDS, extrasaction="ignore")
        if new:
            writer.writeheader()
            f.flush()
        for row in (_results(todo, opts, workers, scheduler, targets, plan) if todo else ()):  # no cluster for nothing
            writer.writerow(row)
            f.flush()
            counts[row["status"]] = counts.get(row["status"], 0) + 1
            bar.update(1)
    summary = ", ".join(f"{n} {s}" for s, n in sorted(counts.items())) or "nothing new"
    where = f"; {plan.summary()}" if todo else ""
    if todo:
        log.info("study plan: %s", plan.summary())
    if not quiet:
        print(f"gravcal: {len(todo)} file(s) calibrated ({summary}{where}); results in {out}", file=sys.stderr)
    if counts.get("error"):
        print(f"gravcal: error: {counts['error']} file(s) could not be calibrated (status error in {out}; "
              f"a re-run tries them again)", file=sys.stderr)
        return EXIT_ERROR_ROWS
    return 0
