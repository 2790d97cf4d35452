"""Exactly repeated samples: runs far longer than a recording's own repeat rate allows.

An idle-sleeping logger (ActiGraph idle sleep) or a frozen bus repeats its last sample exactly;
real stillness does not (noise moves at least one axis by a step now and then). numpy only, so
`calibrate` can exclude filler without loading diagnose's SciPy.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

MIN_RUN = 10  # repeated steps below which a run is never filler


@dataclass
class FlatStretches:
    """Runs of exactly repeated triads that real stillness would not produce."""

    runs: list[tuple[int, int]] = field(default_factory=list)  # (start, end) sample ranges
    repeat_prob: float = 0.0  # per-step probability of an exact triad repeat in ordinary data
    max_expected_run: float = 0.0

    @property
    def n_samples(self) -> int:
        return int(sum(b - a for a, b in self.runs))


def repeated_steps(raw: np.ndarray, out: np.ndarray | None = None, scratch: np.ndarray | None = None) -> np.ndarray:
    """(N-1,) bool: row i+1 equals row i in every column (compared column by column: a reduction
    along rows of 3 is slow). ``out`` / ``scratch``: reusable (>= N-1,) bool buffers."""
    m = raw.shape[0] - 1
    same = np.empty(m, dtype=bool) if out is None else out[:m]
    np.equal(raw[1:, 0], raw[:-1, 0], out=same)
    tmp = np.empty(m, dtype=bool) if scratch is None else scratch[:m]
    for c in range(1, raw.shape[1]):
        np.equal(raw[1:, c], raw[:-1, c], out=tmp)
        same &= tmp
    return same


def true_runs(same: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(starts, lengths) of the runs of True, from the True positions (few in ordinary data)."""
    idx = np.flatnonzero(same)
    if not idx.size:
        return idx, idx
    breaks = np.flatnonzero(np.diff(idx) != 1)
    starts = idx[np.concatenate([[0], breaks + 1])]
    ends = idx[np.concatenate([breaks, [idx.size - 1]])] + 1
    return starts, ends - starts


def select_flat(n: int, n_repeats: int, starts: np.ndarray, lengths: np.ndarray, min_run: int = MIN_RUN) -> FlatStretches:
    """The decision on a recording of n samples with n_repeats repeated steps in all, given (at
    least) every run of >= min_run repeated steps (start sample, steps).

    q = fraction of consecutive samples with an identical triad outside long runs; the longest run
    expected by chance in N steps is ~ log(N) / log(1/q); runs longer than 3x that (and >= min_run
    steps) are flagged."""
    if n < 3 or n_repeats == 0:
        return FlatStretches()
    long_ = lengths >= min_run
    n_long = int(lengths[long_].sum())
    q = float(n_repeats - n_long) / max(n - 1 - n_long, 1)
    expected = math.log(n) / math.log(1.0 / q) if 0 < q < 1 else (0.0 if q == 0 else math.inf)
    limit = max(min_run, 3.0 * expected)
    sel = lengths >= limit
    runs = list(zip(starts[sel].tolist(), (starts[sel] + lengths[sel] + 1).tolist()))
    return FlatStretches(runs, q, expected)


def flat_stretches(raw: np.ndarray, min_run: int = MIN_RUN) -> FlatStretches:
    """Exact repeats of the whole triad (N, k) whose runs are much longer than chance allows
    (``select_flat``)."""
    raw = np.asarray(raw)
    if raw.ndim == 1:
        raw = raw[:, None]
    n = raw.shape[0]
    if n < 3:
        return FlatStretches()
    starts, lengths = true_runs(repeated_steps(raw))
    return select_flat(n, int(lengths.sum()), starts, lengths, min_run)


def chunk_runs(same: np.ndarray, min_run: int = MIN_RUN) -> tuple[np.ndarray, np.ndarray, int]:
    """(starts, lengths, repeated steps) of one chunk's ``same``: the runs :class:`RunCollector`
    needs (every run of >= min_run steps, and the runs at the chunk's ends, which may join its
    neighbours'); shorter runs inside the chunk only count."""
    starts, lengths = true_runs(same)
    n_repeats = int(lengths.sum())
    keep = lengths >= min_run
    if keep.size:
        keep[0] |= starts[0] == 0
        keep[-1] |= starts[-1] + lengths[-1] == same.shape[0]
    return starts[keep], lengths[keep], n_repeats


class RunCollector:
    """Builds ``select_flat``'s input chunk by chunk: ``add(same, first_step)`` with consecutive
    chunks of ``repeated_steps``; runs across chunk borders are joined, short ones only counted."""

    def __init__(self, min_run: int = MIN_RUN) -> None:
        self.min_run = min_run
        self.n_repeats = 0
        self._starts: list[np.ndarray] = []
        self._lengths: list[np.ndarray] = []
        self._open = (0, 0)  # (start, steps) of a run reaching the last chunk's end

    def add(self, same: np.ndarray, first_step: int) -> None:
        self.add_runs(*chunk_runs(same, self.min_run), first_step, same.shape[0])

    def add_runs(self, starts: np.ndarray, lengths: np.ndarray, n_repeats: int, first_step: int,
                 n_steps: int) -> None:
        """``add`` from what :func:`chunk_runs` kept of a chunk of ``n_steps`` steps (run starts
        relative to the chunk): chunks summarised in any order, e.g. by several threads, are added
        in order."""
        starts = starts + first_step
        self.n_repeats += n_repeats
        o_start, o_len = self._open
        if o_len and starts.size and starts[0] == first_step:
            starts[0], lengths[0] = o_start, lengths[0] + o_len
        elif o_len:
            self._keep(np.array([o_start]), np.array([o_len]))
        end = first_step + n_steps
        if starts.size and starts[-1] + lengths[-1] == end:
            self._open = (int(starts[-1]), int(lengths[-1]))
            starts, lengths = starts[:-1], lengths[:-1]
        else:
            self._open = (0, 0)
        self._keep(starts, lengths)

    def _keep(self, starts: np.ndarray, lengths: np.ndarray) -> None:
        long_ = lengths >= self.min_run
        if long_.any():
            self._starts.append(starts[long_])
            self._lengths.append(lengths[long_])

    def result(self, n: int) -> FlatStretches:
        if self._open[1]:
            self._keep(np.array([self._open[0]]), np.array([self._open[1]]))
            self._open = (0, 0)
        empty = np.zeros(0, dtype=np.int64)
        starts = np.concatenate(self._starts) if self._starts else empty
        lengths = np.concatenate(self._lengths) if self._lengths else empty
        return select_flat(n, self.n_repeats, starts, lengths, self.min_run)
