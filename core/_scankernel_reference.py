"""numpy reference of core/_scankernel.c (the reading scan of one chunk, core/datapass.py scan_columns):
the extremes and their counts, the smallest time step, finiteness and the runs of exactly repeated rows
(core.repeats.repeated_steps and chunk_runs) of t and three channel fields, folded into the scan state."""
from __future__ import annotations

import numpy as np

from .repeats import chunk_runs

S_LO, S_HI, S_NLO, S_NHI, S_MINDT, S_FINITE = 0, 3, 6, 9, 12, 13


def scan_chunk(t: np.ndarray, x0: np.ndarray, x1: np.ndarray, x2: np.ndarray, prev: np.ndarray | None,
               state: np.ndarray, runs: np.ndarray | None, min_run: int = 1) -> tuple[int, int]:
    """The scan of one chunk folded into ``state`` (14 float64: min[3], max[3], count at min[3], count
    at max[3], smallest step, all finite); ``runs`` (cap, 2) int64 or None: (first step, steps) of the runs
    of rows equal to the row before (``prev``: t, x0, x1, x2 of the row before the chunk, or None) of
    >= min_run steps or at the chunk's ends. Returns (runs written, repeated steps)."""
    if min_run < 1:
        raise ValueError(f"min_run must be >= 1, got {min_run}")
    t = np.asarray(t, dtype=np.float64)
    xs = [np.asarray(x) for x in (x0, x1, x2)]
    m = t.shape[0]
    if any(x.shape != (m,) for x in xs) or len({x.dtype for x in xs}) > 1:
        raise ValueError(f"t and the three channels must have one length ({m}) and the channels one float type")
    with np.errstate(invalid="ignore"):
        before = np.nan if prev is None else float(prev[0])
        dt = np.diff(t, prepend=before)
        dt = dt[dt == dt]  # NaN steps (the first without prev, a NaN time) are never the smallest
        if dt.size:  # `dt < min_dt ? dt : min_dt` row by row: the first of equal minima (-0.0 or 0.0)
            first_min = dt[np.flatnonzero(dt == dt.min())[0]]
            if first_min < state[S_MINDT]:
                state[S_MINDT] = first_min
    n_runs = n_repeats = 0
    if runs is not None:
        rows = np.column_stack([x.astype(np.float64) for x in xs])
        if prev is not None:
            rows = np.vstack([np.asarray(prev, dtype=np.float64)[1:4], rows])
        same = np.ones(max(rows.shape[0] - 1, 0), dtype=bool)
        for c in range(3):
            same &= rows[1:, c] == rows[:-1, c]
        starts, lengths, n_repeats = chunk_runs(same, min_run)
        cap = runs.shape[0] if runs.ndim == 2 else runs.size // 2
        if starts.shape[0] > cap:
            raise ValueError(f"runs holds room for {cap} runs, the chunk has more: give it m // min_run + 2")
        n_runs = int(starts.shape[0])
        out = runs.reshape(-1, 2)
        out[:n_runs, 0], out[:n_runs, 1] = starts, lengths
    finite = bool(np.isfinite(t).all() and all(np.isfinite(x).all() for x in xs))
    if not finite:
        state[S_FINITE] = 0.0  # extremes of non-finite data mean nothing: the scan stops here
    elif m:
        for c, x in enumerate(xs):
            # the chunk's extremes as `v < lo ? v : lo` finds them: the first of equal ones (-0.0 or 0.0)
            lo = float(x[np.flatnonzero(x == x.min())[0]])
            hi = float(x[np.flatnonzero(x == x.max())[0]])
            if lo <= state[S_LO + c]:
                n = float(np.count_nonzero(x == lo))
                state[S_NLO + c] = n if lo < state[S_LO + c] else state[S_NLO + c] + n
                state[S_LO + c] = lo
            if hi >= state[S_HI + c]:
                n = float(np.count_nonzero(x == hi))
                state[S_NHI + c] = n if hi > state[S_HI + c] else state[S_NHI + c] + n
                state[S_HI + c] = hi
    return n_runs, int(n_repeats)
