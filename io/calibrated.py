"""Calibrated data out: a recording's samples through its calibration, written as .npy, .csv / .csv.gz
or .parquet (by the name's ending), with the calibration beside them.

Columns: ``t`` [s] as read, ``ax``, ``ay``, ``az`` [g] = the Calibration's ``apply`` (every term it
carries, at each sample's temperature, supply voltage and time), ``flags``: the file's own flags
with core.samples.FLAG_SATURATED on clipped rows and io.recordings.FLAG_FILLER on exactly repeated
filler (both excluded from the fit; their values are calibrated all the same). Rows holding NaN/inf
have nothing to calibrate and are left out. Metadata: the calibration (``calibrate --save`` format,
with its report) and the column units, in a JSON sidecar ``OUT.json`` (.npy, CSV) or the parquet
file's own key-value metadata (key ``gravcal``). Every written file reads back with ``gravcal.read``
(a ``flags`` column marks saturation for the reader as for any recording).

Samples go through in chunks, so writing a week holds one chunk of temporaries beside the recording.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from .recordings import FLAG_FILLER, Recording

FORMATS = ("npy", "csv", "csv.gz", "parquet")
CHUNK = 1 << 20  # rows calibrated and written at a time
CSV_DECIMALS = 7  # a [g] in CSV: 0.1 µg steps, far below any accelerometer's noise
DTYPE = np.dtype([("t", "<f8"), ("ax", "<f8"), ("ay", "<f8"), ("az", "<f8"), ("flags", "<u2")])
META_KEY = "gravcal"


def format_of(path: str | Path) -> str:
    """The output format named by ``path``'s ending; an unknown one is refused with the known ones."""
    name = Path(path).name.lower()
    for kind in ("csv.gz", "npy", "csv", "parquet"):
        if name.endswith("." + kind):
            if kind == "parquet":
                try:
                    import pyarrow.parquet  # noqa: F401
                except ImportError:
                    raise InputError(f"{path}: writing parquet needs pyarrow (pip install pyarrow)") from None
            return kind
    raise InputError(f"{path}: name the calibrated output .npy, .csv, .csv.gz or .parquet "
                     f"(the ending chooses the format)")


def sidecar(path: str | Path) -> Path:
    """Where the metadata of a .npy or CSV output goes: OUT.json beside OUT."""
    path = Path(path)
    return path.with_name(path.name + ".json")


def metadata(rec: Recording, cal: Any, report: dict[str, Any] | None = None) -> dict[str, Any]:
    """What a written file says about itself: its columns, its source, the calibration that made it and
    (``report``) the ``calibrate --json`` object of that calibration."""
    from gravcal.core.calibration import jsonable

    return jsonable({
        "schema": "gravcal.calibrated/1",
        "columns": {"t": "s", "ax": "g", "ay": "g", "az": "g",
                    "flags": f"bits: the file's own, {_flag_names()}"},
        "source": {"file": str(rec.source), "format": rec.metadata.get("format"), "units": rec.units,
                   "n_samples": rec.n_samples, "fs_hz": rec.fs},
        "calibration": cal.to_dict(),
        **({"report": report} if report is not None else {}),
    })


def _flag_names() -> str:
    from gravcal.core.samples import FLAG_SATURATED

    return f"{FLAG_SATURATED} saturated, {FLAG_FILLER} filler (exactly repeated; excluded from the fit)"


def _chunks(rec: Recording, cal: Any):
    """(t, a [g] (k, 3), flags) per chunk of rows."""
    n, quality = rec.n_samples, rec.quality
    for i in range(0, n, CHUNK):
        s = slice(i, min(n, i + CHUNK))
        pick = (lambda v: None if v is None else np.asarray(v[s], dtype=np.float64))
        a = cal.apply(np.asarray(rec.raw[s], dtype=np.float64), temp=pick(rec.temp), vsupply=pick(rec.vsupply),
                      t=pick(rec.t))
        flags = quality[s] if quality is not None else np.zeros(s.stop - s.start, dtype=np.uint16)
        yield np.asarray(rec.t[s], dtype=np.float64), a, flags


def write_calibrated(path: str | Path, rec: Recording, cal: Any, report: dict[str, Any] | None = None) -> Path:
    """Write ``rec`` calibrated by ``cal`` to ``path`` (format by its ending, see the module doc); returns
    the path. ``rec`` should be read with ``flag_only=True`` so that every finite row is written."""
    path = Path(path)
    kind = format_of(path)
    meta = metadata(rec, cal, report)
    tmp = path.with_name(path.name + ".partial")  # a killed write leaves no file that looks finished
    try:
        if kind == "npy":
            out = np.lib.format.open_memmap(tmp, mode="w+", dtype=DTYPE, shape=(rec.n_samples,))
            i = 0
            for t, a, flags in _chunks(rec, cal):
                k = len(t)
                out["t"][i:i + k], out["flags"][i:i + k] = t, flags
                out["ax"][i:i + k], out["ay"][i:i + k], out["az"][i:i + k] = a[:, 0], a[:, 1], a[:, 2]
                i += k
            out.flush()
            del out
        elif kind == "parquet":
            _write_parquet(tmp, rec, cal, meta)
        else:
            _write_csv(tmp, rec, cal, gz=kind == "csv.gz")
        if kind != "parquet":
            sidecar(path).write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_for(path: str | Path, rec: Recording, cal: Any, *, columns: Any = None, check_saturation: bool = True,
              report: dict[str, Any] | None = None) -> Path:
    """Write the calibrated samples of the file ``rec`` was read from: when reading it dropped saturated
    or filler rows, the file is read again with them kept and flagged (a recording made from arrays is
    written as it is)."""
    from .recordings import read_recording

    full = rec
    if (rec.n_saturated or rec.n_filler) and rec.quality is None and Path(rec.source).is_file():
        full = read_recording(rec.source, columns=columns, check_saturation=check_saturation, flag_only=True)
    return write_calibrated(path, full, cal, report)


def _table(t: np.ndarray, a: np.ndarray, flags: np.ndarray, decimals: int | None = None):
    import pyarrow as pa

    if decimals is not None:  # the shortest decimal of a rounded double is short: a compact CSV
        a = np.round(a, decimals)
    return pa.table({"t": t, "ax": a[:, 0], "ay": a[:, 1], "az": a[:, 2], "flags": flags})


def _write_parquet(path: Path, rec: Recording, cal: Any, meta: dict[str, Any]) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    schema = pa.schema([("t", pa.float64()), ("ax", pa.float64()), ("ay", pa.float64()), ("az", pa.float64()),
                        ("flags", pa.uint16())], metadata={META_KEY: json.dumps(meta)})
    with pq.ParquetWriter(str(path), schema) as w:
        for t, a, flags in _chunks(rec, cal):
            w.write_table(_table(t, a, flags).cast(schema))


def _write_csv(path: Path, rec: Recording, cal: Any, gz: bool) -> None:
    import pyarrow as pa
    import pyarrow.csv as pacsv

    schema = pa.schema([("t", pa.float64()), ("ax", pa.float64()), ("ay", pa.float64()), ("az", pa.float64()),
                        ("flags", pa.uint16())])
    sink = pa.CompressedOutputStream(str(path), "gzip") if gz else pa.OSFile(str(path), "wb")
    with sink:
        sink.write(f"# gravcal calibrated: t [s], a [g]; flags {_flag_names()}; calibration in "
                   f"{sidecar(path.name.removesuffix('.partial')).name}\n".encode())
        with pacsv.CSVWriter(sink, schema, write_options=pacsv.WriteOptions(quoting_style="none")) as w:
            for t, a, flags in _chunks(rec, cal):
                w.write_table(_table(t, a, flags, CSV_DECIMALS).cast(schema))


def read_parquet_metadata(path: str | Path) -> dict[str, Any]:
    """The metadata a parquet output carries (``metadata()``'s dict)."""
    import pyarrow.parquet as pq

    return json.loads(pq.read_schema(str(path)).metadata[META_KEY.encode()])
