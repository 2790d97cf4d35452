"""Recordings on disk: read one for ``gravcal calibrate``, write one from ``gravcal simulate``.

The format is recognised by content (daemon.formats.sniff), never by the name alone:

- CSV, plain or gzip-compressed: a header row, then one sample per line. Columns ``t`` [s], ``ax``,
  ``ay``, ``az`` (raw units of any scale: counts, volts, duty cycle or g); optional ``gx``, ``gy``,
  ``gz`` (gyro, any unit), ``temp`` [°C] and ``vsupply`` [V]; any other column is ignored; other
  header names are mapped with ``columns`` (``--columns t=t_unix,ax=x_counts,...``). Delimiter ``,``
  (``;`` or tab are recognised from the header), ``#`` starts a comment line.
- ``.npy``: a structured array with the same field names, opened memory-mapped so a week at
  100 Hz (60 M samples) is not copied; ``t``, ``ax``, ``ay``, ``az`` come back as views.
- ActiGraph .gt3x / .agdc, Axivity .cwa, GENEActiv .bin through their readers (the ``formats``
  extra, daemon.formats.wearables); temperature comes through as ``temp``.

Reading validates and says precisely what is wrong (:class:`~gravcal.errors.InputError`):
missing file, empty file, binary or unknown content, no header, missing columns, text in numbers
(line and column), NaN/inf (dropped with a warning when few, an error when most), clipped/saturated
samples, time going backwards or repeated, too few samples. Messages quote the file only as a short
printable excerpt. Validation runs in chunks so its temporaries stay small next to a memory-mapped week.
"""
from __future__ import annotations

import gzip
import json
import logging
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from gravcal.core.calibration import jsonable  # noqa: F401  (re-exported for the cmd_* modules)
from gravcal.core.samples import CHANNELS, FLAG_SATURATED, duty_ratios, raw_triad
from gravcal.core.datapass import ScanStats, fs_from, scan_columns
from gravcal.core.fastdetect import BlockStats, release_mapped
from gravcal.core.repeats import MIN_RUN, FlatStretches, RunCollector, repeated_steps

from . import prestart
from ..errors import InputError
from .formats.csvtext import OPTIONAL, REQUIRED, Where, load_csv, missing_columns_error, parse_columns, shown_names
from .formats.sniff import FORMATS, excerpt, sniff

log = logging.getLogger(__name__)

VSUPPLY_RANGE_V = (0.5, 60.0)  # a supply-voltage reading outside this is not a supply [V]: handled like NaN
MIN_SAMPLES = 50
"""Fewer samples than this cannot hold even one quasi-static window at any usual rate."""
MAX_NONFINITE_FRACTION = 0.5
"""NaN/inf rows are dropped with a warning up to this fraction; beyond it the file is refused."""
MAX_SATURATED_FRACTION = 0.05
"""Saturated rows are dropped with a warning up to this fraction. Beyond it the sensor sat at
its rail for whole postures, and any calibration from the rest would be biased: refused."""
SATURATION_MIN_COUNT = 20
SATURATION_MIN_FRACTION = 0.005
"""A channel is clipped when at least this many / this fraction of its samples sit exactly on
its extreme value. Continuous data almost never repeats its extreme exactly ..."""
SATURATION_MIN_DISTINCT = 200
"""... unless it is coarsely quantised: the heuristic only applies when a subsample holds at
least this many distinct values (otherwise only a ``flags`` column can mark saturation)."""
CHUNK = 1 << 20  # rows per chunk of the slow paths (bounded temporaries)
SCAN_CHUNK = 1 << 16  # rows per chunk of the validation scan: small enough to stay in the CPU cache
FLAG_FILLER = 1 << 8
"""A row of exactly repeated filler (idle sleep, frozen output): in ``Recording.quality`` beside the
samples' own flags (core.samples.FLAG_*, FLAG_SATURATED for a clipped row)."""


@dataclass
class Recording:
    """A validated recording in memory (or memory-mapped).

    ``raw`` (also ``acc``) is (N, 3) in the file's raw units (``units``); ``t`` (N,) [s]; ``temp``
    (N,) [°C] or None; ``gyro`` (N, 3) in the file's gyro units or None; ``fs`` [Hz] estimated from
    ``t``; ``vsupply`` (N,) [V] or None; ``metadata``: format, reader and device notes.
    """

    t: np.ndarray
    raw: np.ndarray
    temp: np.ndarray | None
    gyro: np.ndarray | None
    fs: float
    source: Path
    vsupply: np.ndarray | None = None
    n_dropped: int = 0  # rows dropped for NaN/inf
    n_saturated: int = 0  # rows dropped as saturated
    columns: tuple[str, ...] = ()  # every column/field name found in the file
    warnings: list[str] = field(default_factory=list)
    units: str = "raw"
    metadata: dict[str, Any] = field(default_factory=dict)
    n_filler: int = 0  # rows excluded as exactly repeated filler (exclude_filler)
    blocks: BlockStats | None = None  # block statistics of exactly these rows at fs (read with blocks=True)
    quality: np.ndarray | None = None  # read with flag_only: per row the file's flags | FLAG_SATURATED | FLAG_FILLER

    @property
    def acc(self) -> np.ndarray:
        return self.raw

    @property
    def n_samples(self) -> int:
        return int(self.t.shape[0])

    @property
    def duration_s(self) -> float:
        return float(self.t[-1] - self.t[0]) if self.n_samples else 0.0


# ---------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------
def read_recording(path: str | Path, *, min_samples: int = MIN_SAMPLES, check_saturation: bool = True,
                   columns: str | dict[str, str] | None = None, exclude_filler: bool = False,
                   progress: Callable[[int, int], None] | None = None, blocks: bool = False,
                   flag_only: bool = False) -> Recording:
    """Read and validate a recording of any format in ``FORMATS`` (recognised by content).

    ``columns``: other CSV header names, ``"t=t_unix,ax=x_counts"`` or a dict. ``exclude_filler``:
    drop runs of exactly repeated samples (idle-sleep filler, a frozen bus) and say so in ``warnings``.
    ``progress(done, total)``: chunks of the validation pass done, as it goes. ``blocks``: the
    validation pass also computes the block detector's statistics (``Recording.blocks``, for
    core.pipeline.calibrate_recording), kept when no row is dropped (else None: calibrating
    computes them on the rows it gets). ``flag_only``: saturated and filler rows stay and are marked in
    ``Recording.quality`` instead (rows with NaN/inf are still dropped): the rows calibrated data is written for.
    """
    path = Path(path)
    mapping = parse_columns(columns)
    if not path.exists():
        raise InputError(f"{path}: no such file")
    if path.is_dir():
        raise InputError(f"{path}: is a directory, expected a recording ({', '.join(FORMATS)})")
    if path.stat().st_size == 0:
        raise InputError(f"{path}: empty file (expected a header row t,ax,ay,az and samples)")
    found = sniff(path)
    named = path.suffix.lower().lstrip(".")
    if named in ("npy", "parquet", "gt3x", "agdc", "cwa", "bin") and found.kind != named:
        raise InputError(f"{path}: not a readable .{named} file: its content is {found.what}")
    units, meta = "raw", {"format": found.kind}
    if found.kind == "npy":
        cols, where, names = _load_npy(path, mapping)
    elif found.kind in ("csv", "csv.gz"):
        try:
            cols, where, names = load_csv(path, gz=found.kind == "csv.gz", mapping=mapping)
        except (EOFError, zlib.error, gzip.BadGzipFile) as exc:
            raise InputError(f"{path}: damaged gzip data ({type(exc).__name__}: {excerpt(str(exc), 60)})") from None
    elif found.kind == "parquet":
        from .formats.parquet import load_parquet

        cols, where, names = load_parquet(path, mapping)
    elif found.kind in ("gt3x", "agdc", "cwa", "bin"):
        from .formats.wearables import read_wearable

        cols, meta = read_wearable(path, found)
        units = meta.pop("units")
        where, names = Where(path=path), tuple(cols)
    else:
        raise InputError(f"{path}: {found.what}; not a recording gravcal reads ({', '.join(FORMATS)})")
    # the block statistics' memory, when `gravcal calibrate` prepared it for this file (io/prestart.py)
    allocate = prestart.claim(path) if blocks else None
    rec = _validate(path, cols, where, names, min_samples=min_samples, check_saturation=check_saturation,
                    progress=progress, exclude_filler=exclude_filler or flag_only, blocks=blocks, allocate=allocate,
                    flag_only=flag_only)
    rec.units, rec.metadata = units, meta
    return rec


def recording_from_arrays(t: Any, acc: Any, *, temp: Any = None, vsupply: Any = None, min_samples: int = MIN_SAMPLES,
                          check_saturation: bool = True, exclude_filler: bool = True) -> Recording:
    """Validate arrays as a file's columns are: t (N,) [s], acc (N, 3) raw, optional temp/vsupply (N,)."""
    t = np.asarray(t, dtype=np.float64)
    acc = np.asarray(acc, dtype=np.float64)
    if t.ndim != 1 or acc.shape != (t.shape[0], 3):
        raise InputError(f"need t of shape (N,) and acc of shape (N, 3); got {t.shape} and {acc.shape}")
    cols = {"t": t, "ax": acc[:, 0], "ay": acc[:, 1], "az": acc[:, 2], "_triad": acc}
    for name, v in (("temp", temp), ("vsupply", vsupply)):
        if v is not None:
            v = np.asarray(v, dtype=np.float64)
            if v.shape != t.shape:
                raise InputError(f"{name} has shape {v.shape}; need one value per sample, shape {t.shape}")
            cols[name] = v
    rec = _validate(Path("<arrays>"), cols, Where(path=Path("<arrays>")), tuple(c for c in cols if c != "_triad"),
                    min_samples=min_samples, check_saturation=check_saturation, exclude_filler=exclude_filler)
    rec.metadata = {"format": "arrays"}
    return rec


def _filler_stretches(raw: np.ndarray, min_run: int = MIN_RUN) -> FlatStretches:
    """core.repeats.flat_stretches of the triad, in cache-sized chunks with reused buffers (a
    mapped input is released as the scan releases it)."""
    n = raw.shape[0]
    runs = RunCollector(min_run)
    size = min(n, SCAN_CHUNK)
    same, scratch = np.empty(size, dtype=bool), np.empty(size, dtype=bool)
    for s in _chunks(max(n - 1, 0), SCAN_CHUNK):  # steps s: row i + 1 against row i
        runs.add(repeated_steps(raw[s.start:s.stop + 1], same, scratch), s.start)
        release_mapped(raw, s.start, s.stop)
    return runs.result(n)


def _without_filler(rec: Recording, min_samples: int, flats: FlatStretches | None = None) -> Recording:
    """Drop runs of exactly repeated triads (core.repeats.select_flat decides; ``flats``: already
    found by the validation scan); the first sample of each run is a real one and stays."""
    if flats is None:
        flats = _filler_stretches(rec.raw)
    if not flats.runs:
        return rec
    keep = np.ones(rec.n_samples, dtype=bool)
    for a, b in flats.runs:
        keep[a + 1:b] = False
    n_out = int(rec.n_samples - keep.sum())
    if keep.sum() < max(min_samples, 2):
        raise InputError(f"{rec.source}: {n_out} of {rec.n_samples} samples are exactly repeated filler "
                         f"(idle sleep or frozen output): too few real samples left")
    note = (f"excluded {n_out} of {rec.n_samples} samples ({100.0 * n_out / rec.n_samples:.1f} %) as exactly repeated "
            f"filler in {len(flats.runs)} run(s), longest {max(b - a for a, b in flats.runs)} samples "
            f"(idle sleep / frozen output, not stillness)")
    log.warning("%s: %s", rec.source, note)
    sub = (lambda x: None if x is None else x[keep])
    return Recording(t=rec.t[keep], raw=rec.raw[keep], temp=sub(rec.temp), gyro=sub(rec.gyro), fs=rec.fs,
                     source=rec.source, vsupply=sub(rec.vsupply), n_dropped=rec.n_dropped, n_saturated=rec.n_saturated,
                     columns=rec.columns, warnings=[*rec.warnings, note], units=rec.units, metadata=rec.metadata,
                     n_filler=n_out)


def _load_npy(path: Path, mapping: dict[str, str]) -> tuple[dict[str, np.ndarray], Where, tuple[str, ...]]:
    layout = "a structured array with fields t, ax, ay, az (optional gx, gy, gz, temp)"
    try:
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - numpy's header parser raises ValueError, SyntaxError, TokenError...
        raise InputError(f"{path}: not a readable .npy file ({excerpt(str(exc), 80)}); expected {layout}") from None
    if isinstance(arr, np.lib.npyio.NpzFile):  # pragma: no cover - np.load only returns this for .npz content
        raise InputError(f"{path}: is an .npz archive; expected a .npy file holding {layout}")
    names = arr.dtype.names
    if names is None:
        raise InputError(
            f"{path}: holds a plain {arr.dtype} array of shape {arr.shape}; expected {layout} "
            f"(e.g. np.save(path, np.rec.fromarrays([t, ax, ay, az], names='t,ax,ay,az')))"
        )
    if arr.ndim != 1:
        raise InputError(f"{path}: structured array has shape {arr.shape}; expected one dimension (one row per sample)")
    if len(arr) == 0:
        raise InputError(f"{path}: empty input: the array holds no samples")
    lower = {n.lower(): n for n in names}
    for ours, theirs in mapping.items():
        if theirs.lower() not in lower:
            raise InputError(f"{path}: --columns {ours}={excerpt(theirs, 24)}: no such field; found: {shown_names(list(names))}")
        lower[ours] = lower.pop(theirs.lower())
    if any(c not in lower for c in REQUIRED):
        raise missing_columns_error(path, list(lower), what="field")
    for c in REQUIRED + OPTIONAL:
        if c in lower and (arr.dtype[lower[c]].kind not in "fiu" or arr.dtype[lower[c]].shape != ()):
            raise InputError(f"{path}: field {c!r} has type {arr.dtype[lower[c]]}; expected a scalar number per sample")
    cols = {c: arr[lower[c]] for c in REQUIRED + OPTIONAL if c in lower}
    if "flags" in lower:
        cols["flags"] = arr[lower["flags"]]
    triad = _triad_view(arr, [lower[c] for c in ("ax", "ay", "az")])
    if triad is not None:
        cols["_triad"] = triad
    return cols, Where(path=path), tuple(names)


def _triad_view(arr: np.ndarray, fields: list[str]) -> np.ndarray | None:
    """An (N, 3) view (no copy) of three adjacent fields of one float type, else None."""
    dts = [arr.dtype.fields[f][0] for f in fields]
    offs = [arr.dtype.fields[f][1] for f in fields]
    if len({d.str for d in dts}) != 1 or dts[0].kind != "f":
        return None
    size = dts[0].itemsize
    if offs != [offs[0], offs[0] + size, offs[0] + 2 * size]:
        return None
    return np.ndarray(shape=(arr.shape[0], 3), dtype=dts[0], buffer=arr, offset=offs[0], strides=(arr.strides[0], size))


def _chunks(n: int, size: int = CHUNK) -> Iterator[slice]:
    for i in range(0, n, size):
        yield slice(i, min(n, i + size))


def _scan(t: np.ndarray, raw: np.ndarray, extra: list[np.ndarray], flags: np.ndarray | None,
          progress: Callable[[int, int], None] | None = None, repeats: bool = False, blocks: bool = False,
          aux: np.ndarray | None = None, allocate: Callable[..., np.ndarray] | None = None) -> ScanStats:
    """core.datapass.scan_columns in chunks of SCAN_CHUNK rows (of block_stats' grid with ``blocks``)."""
    return scan_columns(t, raw, extra, flags, chunk=SCAN_CHUNK, progress=progress, repeats=repeats, blocks=blocks,
                        aux=aux, allocate=allocate)


def _validate(path: Path, cols: dict[str, np.ndarray], where: Where, columns: tuple[str, ...], *,
              min_samples: int, check_saturation: bool, progress: Callable[[int, int], None] | None = None,
              exclude_filler: bool = False, blocks: bool = False,
              allocate: Callable[..., np.ndarray] | None = None, flag_only: bool = False) -> Recording:
    t = cols["t"]
    raw = cols.pop("_triad", None)
    if raw is None:
        raw = np.column_stack([cols["ax"], cols["ay"], cols["az"]]).astype(np.float64, copy=False)
    temp = cols.get("temp")
    vsupply = cols.get("vsupply")
    if vsupply is not None:  # an out-of-range reading is no supply value: counted and dropped like NaN
        v = np.asarray(vsupply, dtype=np.float64)
        vsupply = np.where((v >= VSUPPLY_RANGE_V[0]) & (v <= VSUPPLY_RANGE_V[1]), v, np.nan)
    gyro = np.column_stack([cols[c] for c in ("gx", "gy", "gz")]) if all(c in cols for c in ("gx", "gy", "gz")) else None
    flags = cols.get("flags")
    n = int(t.shape[0])
    notes: list[str] = []
    extra = ([v for v in (temp, vsupply) if v is not None]
             + ([gyro[:, i] for i in range(3)] if gyro is not None else []))
    # the block statistics' aux channel is temp alone (calibrate_recording's covariate columns
    # without a supply voltage); with one, calibrating computes them
    blocks = blocks and vsupply is None
    scan = _scan(t, raw, extra, flags, progress, repeats=exclude_filler, blocks=blocks, aux=temp, allocate=allocate)

    # 1. NaN / inf in any column we use: drop the rows (a copy; only when there are any).
    keep: np.ndarray | None = None
    n_dropped = 0
    if not scan.finite:
        used = {"t": t, "ax": raw[:, 0], "ay": raw[:, 1], "az": raw[:, 2]}
        if temp is not None:
            used["temp"] = temp
        if vsupply is not None:
            used["vsupply"] = vsupply
        if gyro is not None:
            used.update(gx=gyro[:, 0], gy=gyro[:, 1], gz=gyro[:, 2])
        bad = _nonfinite_rows(used, n)
        n_dropped = int(bad.sum())
        first = int(np.argmax(bad))
        which = [name for name, v in used.items() if not np.isfinite(v[first])]
        what = "NaN/inf or empty values" + (f" (or a supply voltage outside {VSUPPLY_RANGE_V[0]:g}-"
                                             f"{VSUPPLY_RANGE_V[1]:g} V)" if vsupply is not None else "")
        msg = (f"{n_dropped} of {n} samples ({100.0 * n_dropped / n:.1f} %) hold {what} "
               f"(first at {where(first)}, column {', '.join(which)})")
        if n_dropped > MAX_NONFINITE_FRACTION * n:
            raise InputError(f"{path}: {msg}: too many to drop")
        notes.append(f"dropped {msg}")
        keep = ~bad
        sub_flags = flags[keep] if flags is not None else None
        scan = _scan(t[keep], raw[keep], [], sub_flags, repeats=exclude_filler)

    # 2. Saturated (clipped) samples: a flags column says so exactly; else the pile-up heuristic.
    n_saturated = 0
    sat_rows = None
    if check_saturation:
        sat, detail = _saturated_rows(raw, flags, keep, scan)
        if sat is not None:
            n_saturated = int(sat.sum())
            n_valid = n - n_dropped
            first = int(np.argmax(sat))
            msg = (f"{n_saturated} of {n_valid} samples ({100.0 * n_saturated / n_valid:.1f} %) are saturated "
                   f"(sensor at the end of its range: {detail}; first at {where(first)})")
            if flag_only:
                sat_rows = sat
            elif n_saturated > MAX_SATURATED_FRACTION * n_valid:
                raise InputError(
                    f"{path}: {msg}: too many to drop, a calibration from the rest would be biased "
                    f"(use a wider range or --no-saturation-check if the data is merely quantised)"
                )
            if not flag_only:
                notes.append(f"dropped {msg}")
                keep = ~sat if keep is None else keep & ~sat
                scan.repeats = None  # found on rows that are no longer all there

    if keep is not None:
        t, raw = t[keep], raw[keep]
        temp = temp[keep] if temp is not None else None
        vsupply = vsupply[keep] if vsupply is not None else None
        gyro = gyro[keep] if gyro is not None else None
        orig_index = np.flatnonzero(keep)
    else:
        orig_index = None
    n_kept = int(t.shape[0])
    if n_kept < max(min_samples, 2):
        extra_msg = f" after dropping {n - n_kept} bad ones" if n_kept != n else ""
        raise InputError(f"{path}: too few samples: {n_kept}{extra_msg}; need at least {max(min_samples, 2)}")

    # 3. Time strictly increasing (the scan's smallest step; locate the culprit only when needed).
    if not scan.min_dt > 0:
        _check_time(path, t, where, orig_index)  # raises with the line
    fs = fs_from(scan.dt_medians)
    for note in notes:
        log.warning("%s: %s", path, note)
    rec = Recording(t=t, raw=raw, temp=temp, vsupply=vsupply, gyro=gyro, fs=fs, source=path, n_dropped=n_dropped,
                    n_saturated=n_saturated, columns=columns, warnings=notes,
                    blocks=scan.blocks if keep is None else None)
    if flag_only:
        rec.quality = _quality(n_kept, flags, sat_rows, keep,
                               scan.repeats.result(n_kept) if scan.repeats is not None else _filler_stretches(raw))
        return rec
    if not exclude_filler:
        return rec
    return _without_filler(rec, min_samples, scan.repeats.result(n_kept) if scan.repeats is not None else None)


def _quality(n: int, flags: np.ndarray | None, sat: np.ndarray | None, keep: np.ndarray | None,
             flats: FlatStretches) -> np.ndarray:
    """Per kept row: the file's own flags, FLAG_SATURATED where clipped, FLAG_FILLER inside a filler run."""
    pick = (lambda v: v if keep is None else v[keep])
    quality = np.zeros(n, dtype=np.uint16) if flags is None else pick(np.asarray(flags)).astype(np.uint16)
    if sat is not None:
        quality[pick(sat)] |= FLAG_SATURATED
    for a, b in flats.runs:
        quality[a + 1:b] |= FLAG_FILLER  # the first sample of a run is a real one
    return quality


def _nonfinite_rows(used: dict[str, np.ndarray], n: int) -> np.ndarray:
    """Boolean mask of rows with a non-finite value in any of ``used``."""
    bad = np.zeros(n, dtype=bool)
    for v in used.values():
        for s in _chunks(n):
            bad[s] |= ~np.isfinite(v[s])
    return bad


def _saturated_rows(raw: np.ndarray, flags: np.ndarray | None, keep: np.ndarray | None,
                    scan: ScanStats) -> tuple[np.ndarray | None, str]:
    """Mask of saturated rows (None when there are none) and what marked them.

    Uses the scan's per-channel extremes and their counts; builds a mask only when needed.
    """
    n = raw.shape[0]
    n_valid = n if keep is None else int(keep.sum())
    piles = []  # (channel, label, edge) with an exact pile-up at the extreme
    step = max(1, n // 100_000)
    for c, name in enumerate(("ax", "ay", "az")):
        for label, edge, count in (("minimum", scan.lo[c], scan.n_lo[c]), ("maximum", scan.hi[c], scan.n_hi[c])):
            if count >= max(SATURATION_MIN_COUNT, SATURATION_MIN_FRACTION * n_valid):
                sub = np.asarray(raw[::step, c], dtype=np.float64)
                if np.unique(sub[np.isfinite(sub)]).size >= SATURATION_MIN_DISTINCT:  # else merely quantised
                    piles.append((c, name, label, float(edge)))
    if not piles and scan.n_flagged == 0:
        return None, ""
    sat = np.zeros(n, dtype=bool)
    details = []
    if scan.n_flagged:
        for s in _chunks(n):
            sat[s] |= (np.asarray(flags[s]).astype(np.int64) & FLAG_SATURATED) != 0
        details.append("flagged saturated by the logger")
    for c, name, label, edge in piles:
        hit = np.zeros(n, dtype=bool)
        for s in _chunks(n):
            hit[s] = raw[s, c] == edge
        sat |= hit
        details.append(f"{name} sits at its {label} {edge:.6g} in {int(hit.sum())} samples")
    if keep is not None:
        sat &= keep
    return sat, "; ".join(details)


def _check_time(path: Path, t: np.ndarray, where: Where, orig_index: np.ndarray | None) -> None:
    """Raise, naming the place, if time does not increase strictly."""
    n = int(t.shape[0])
    for s in _chunks(n):
        lo = max(0, s.start - 1)  # overlap one sample so the step across chunk borders is checked too
        dt = np.diff(np.asarray(t[lo:s.stop], dtype=np.float64))
        bad = dt <= 0
        if bad.any():
            k = lo + int(np.argmax(bad)) + 1  # index of the offending sample
            orig = int(orig_index[k]) if orig_index is not None else k
            prev = int(orig_index[k - 1]) if orig_index is not None else k - 1
            if t[k] == t[k - 1]:
                raise InputError(f"{path}: duplicated time t={float(t[k]):.9g} s at {where(prev)} and {where(orig)}")
            raise InputError(
                f"{path}: time goes backwards at {where(orig)}: t={float(t[k]):.9g} s after t={float(t[k - 1]):.9g} s "
                f"(time must increase strictly)"
            )


# ---------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------
def recording_columns(samples: np.ndarray) -> dict[str, np.ndarray]:
    """The calibrate-format columns of SAMPLE_DTYPE rows.

    ``ax``, ``ay``, ``az``: the triad's duty cycles T1/T2 (core.samples.raw_triad), the raw
    units the estimators work in; ``ax2``: the redundant channel's duty cycle; ``gyro`` [ADC
    counts], ``temp`` [°C], ``vsupply`` [V], ``seq``, ``flags``; ``t1_<channel>`` and
    ``t2_a``/``t2_b`` [timer counts] so nothing of the sample is lost.
    """
    tri = raw_triad(samples)
    duty = duty_ratios(samples)
    out: dict[str, np.ndarray] = {
        "t": samples["t"], "ax": tri[:, 0], "ay": tri[:, 1], "az": tri[:, 2], "ax2": duty[:, 3],
        "gyro": samples["gyro"], "temp": samples["temp"], "vsupply": samples["vsupply"],
        "seq": samples["seq"], "flags": samples["flags"],
    }
    for i, ch in enumerate(CHANNELS):
        out[f"t1_{ch}"] = samples["t1"][:, i]
    out["t2_a"] = samples["t2"][:, 0]
    out["t2_b"] = samples["t2"][:, 1]
    return out


RECORDING_DTYPE = np.dtype([
    ("t", "<f8"), ("ax", "<f8"), ("ay", "<f8"), ("az", "<f8"), ("ax2", "<f8"),
    ("gyro", "<u2"), ("temp", "<f4"), ("vsupply", "<f4"), ("seq", "<i8"), ("flags", "<u2"),
    ("t1_ax", "<u4"), ("t1_ay", "<u4"), ("t1_az", "<u4"), ("t1_ax2", "<u4"), ("t2_a", "<u4"), ("t2_b", "<u4"),
])
"""The .npy layout ``gravcal simulate`` writes (ax, ay, az adjacent float64: read as one (N, 3) view)."""

_CSV_FORMATS = {"t": "%.6f", "ax": "%.10g", "ay": "%.10g", "az": "%.10g", "ax2": "%.10g", "temp": "%.3f", "vsupply": "%.4f"}


def to_recording_array(samples: np.ndarray) -> np.ndarray:
    """SAMPLE_DTYPE rows -> RECORDING_DTYPE rows."""
    cols = recording_columns(samples)
    out = np.empty(samples.shape[0], dtype=RECORDING_DTYPE)
    for name in RECORDING_DTYPE.names:
        out[name] = cols[name]
    return out


def write_recording(path: str | Path, blocks: np.ndarray | Iterable[np.ndarray], n_total: int | None = None) -> int:
    """Write SAMPLE_DTYPE rows (one array or an iterable of blocks) as CSV or .npy (by extension).

    For .npy from an iterable, ``n_total`` (rows) lets the file be written block by block
    through a memory map; without it the blocks are collected first. Returns rows written.
    """
    path = Path(path)
    if isinstance(blocks, np.ndarray):
        blocks = [blocks]
        n_total = len(blocks[0])
    if path.suffix.lower() == ".npy":
        return _write_npy(path, blocks, n_total)
    return _write_csv(path, blocks)


def _write_csv(path: Path, blocks: Iterable[np.ndarray]) -> int:
    names = RECORDING_DTYPE.names
    fmt = [_CSV_FORMATS.get(n, "%d") for n in names]
    n = 0
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(",".join(names) + "\n")
        for block in blocks:
            cols = recording_columns(block)
            np.savetxt(f, np.column_stack([np.asarray(cols[c], dtype=np.float64) for c in names]), fmt=fmt, delimiter=",")
            n += len(block)
    return n


def _write_npy(path: Path, blocks: Iterable[np.ndarray], n_total: int | None) -> int:
    if n_total is None:
        arr = np.concatenate([to_recording_array(b) for b in blocks]) if blocks else np.empty(0, RECORDING_DTYPE)
        np.save(path, arr)
        return len(arr)
    mm = np.lib.format.open_memmap(path, mode="w+", dtype=RECORDING_DTYPE, shape=(n_total,))
    i = 0
    for block in blocks:
        k = min(len(block), n_total - i)
        mm[i:i + k] = to_recording_array(block[:k])
        i += k
    mm.flush()
    del mm
    if i != n_total:
        raise ValueError(f"{path}: expected {n_total} samples, the source gave {i}")
    return i


def truth_path(path: str | Path) -> Path:
    """Where the true parameters of a simulated recording go: FILE.csv -> FILE.truth.json."""
    path = Path(path)
    return path.with_name(path.stem + ".truth.json")


def write_truth(path: str | Path, truth: dict[str, Any]) -> Path:
    """Write the simulator's truth dict as JSON beside the recording ``path``; returns its path."""
    out = truth_path(path)
    out.write_text(json.dumps(jsonable(truth), indent=2) + "\n", encoding="utf-8")
    return out
