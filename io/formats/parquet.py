"""Apache Parquet recordings (what ``gravcal calibrate --write OUT.parquet`` writes, and what other
tools export): the same column names as a CSV's (t, ax, ay, az, optional gx, gy, gz, temp, vsupply,
flags), any other column ignored, other names mapped with ``columns``. Read through pyarrow, only
the columns used, as float64 (the triad as one (N, 3) array).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import InputError
from .csvtext import OPTIONAL, REQUIRED, Where, apply_mapping, missing_columns_error
from .sniff import excerpt


def load_parquet(path: Path, mapping: dict[str, str]) -> tuple[dict[str, np.ndarray], Where, tuple[str, ...]]:
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        raise InputError(f"{path}: reading parquet needs pyarrow (pip install pyarrow)") from None
    try:
        pf = pq.ParquetFile(str(path))
    except (pa.ArrowException, OSError) as exc:
        raise InputError(f"{path}: not a readable parquet file ({excerpt(str(exc), 80)})") from None
    theirs = list(pf.schema_arrow.names)
    names = apply_mapping(path, [n.lower() for n in theirs], mapping)
    if any(c not in names for c in REQUIRED):
        raise missing_columns_error(path, names)
    wanted = [c for c in REQUIRED + OPTIONAL + ("flags",) if c in names]
    for c in wanted:
        kind = pf.schema_arrow.field(theirs[names.index(c)]).type
        if not (pa.types.is_floating(kind) or pa.types.is_integer(kind)):
            raise InputError(f"{path}: column {c!r} holds {kind}; expected a number per sample")
    n = pf.metadata.num_rows
    if n == 0:
        raise InputError(f"{path}: empty input: the file holds no samples")
    cols = {c: np.empty(n) for c in wanted if c not in ("ax", "ay", "az")}
    triad = np.empty((n, 3))
    i = 0
    try:
        for batch in pf.iter_batches(columns=[theirs[names.index(c)] for c in wanted]):
            k = batch.num_rows
            for j, c in enumerate(wanted):
                v = batch.column(j).cast(pa.float64()).to_numpy(zero_copy_only=False)
                if c in ("ax", "ay", "az"):
                    triad[i:i + k, "xyz".index(c[1])] = v
                else:
                    cols[c][i:i + k] = v
            i += k
    except (pa.ArrowException, OSError) as exc:
        raise InputError(f"{path}: damaged parquet data ({excerpt(str(exc), 80)})") from None
    cols.update(_triad=triad, ax=triad[:, 0], ay=triad[:, 1], az=triad[:, 2])
    return cols, Where(path=path), tuple(names)
