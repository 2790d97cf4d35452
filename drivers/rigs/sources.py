"""Where the emulator's samples come from: the sensor model, a recording, or a test pattern.

Every source is an iterator of SAMPLE_DTYPE blocks with consecutive ``seq`` from 0, plus its
sample rate ``fs`` [Hz]. The emulator only paces and frames them.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from ...core.samples import CHANNELS, FLAG_REPLAYED, SAMPLE_DTYPE
from ..codec import TICK_HZ

PATTERN = "pattern"
"""Scenario name of the deterministic test pattern (no sensor model involved)."""


@dataclass
class Source:
    blocks: Iterable[np.ndarray]
    fs: float
    name: str


def scenario_source(name: str, *, seed: int = 0, fs: float = 100.0, duration: float = 60.0,
                    block: int = 256, **scenario_kw) -> Source:
    """The sensor model on a scenario, via ``gravcal.core.simulate.simulate_blocks``."""
    if name == PATTERN:
        return Source(pattern_blocks(seed=seed, fs=fs, duration=duration, block=block), fs, name)
    # The sensor model's imports (~0.1 s); the test pattern and replays do without them.
    from ...core.scenarios import SCENARIOS
    from ...core.simulate import simulate_blocks

    if name not in SCENARIOS:  # fail before the emulator announces a device, not at the first block
        raise ValueError(f"unknown scenario {name!r}; choose one of {', '.join(SCENARIOS)} or {PATTERN}")
    blocks = iter(simulate_blocks(name, None, seed=seed, duration=duration, fs=fs, block=block, **scenario_kw))
    # the first block now: the sensor model, its scenario and its filters (~0.1 s) are set up
    # before an emulator announces its device and its stream clock starts, not in the stream's first second
    first = next(blocks, None)
    return Source(_with_ticks(itertools.chain([] if first is None else [first], blocks)), fs, name)


def device_ticks(t: np.ndarray) -> np.ndarray:
    """The logger's 32-bit timer at ``t`` [s]: TICK_HZ, the rate every driver assumes."""
    return (np.rint(np.asarray(t, dtype=np.float64) * TICK_HZ).astype(np.int64) & 0xFFFFFFFF).astype(np.uint32)


def _with_ticks(blocks: Iterable[np.ndarray]) -> Iterator[np.ndarray]:
    """Stamp ``tick`` from ``t`` at the logger's TICK_HZ. The simulator's tick field counts at the
    sensor model's duty-cycle timer (e.g. 4 MHz), which is not the clock the logger stamps frames with."""
    for b in blocks:
        b = b.copy()
        b["tick"] = device_ticks(b["t"])
        yield b


def pattern_blocks(*, seed: int = 0, fs: float = 200.0, duration: float = 10.0,
                   block: int = 256) -> Iterator[np.ndarray]:
    """A deterministic test pattern: every field varies (random walks within the wire ranges)
    so a receiver comparing values field by field catches any mix-up. Not a sensor model.
    """
    rng = np.random.default_rng(seed)
    n_total = int(round(duration * fs))
    t2 = np.array([20000.0, 19500.0])
    duty = np.array([0.5, 0.52, 0.54, 0.5])
    temp, vsup = 25.0, 3.3
    for start in range(0, n_total, block):
        n = min(block, n_total - start)
        b = np.zeros(n, SAMPLE_DTYPE)
        idx = np.arange(start, start + n)
        b["t"] = idx / fs
        b["seq"] = idx
        b["tick"] = device_ticks(idx / fs)
        d = np.clip(duty + np.cumsum(rng.normal(0, 2e-3, (n, 4)), axis=0), 0.1, 0.9)
        duty = d[-1]
        tt2 = np.rint(t2 + rng.normal(0, 3, (n, 2)))
        b["t2"] = tt2
        b["t1"] = np.rint(d * tt2[:, [0, 0, 1, 1]])
        b["gyro"] = rng.integers(1000, 3000, n)
        tc = temp + np.cumsum(rng.normal(0, 0.05, n))
        temp = tc[-1]
        b["temp"] = tc
        b["vsupply"] = vsup + rng.normal(0, 0.01, n)
        yield b


def replay_source(path: str | Path, *, block: int = 256) -> Source:
    """A recording with timer counts (CSV/.npy as ``gravcal simulate`` writes them: columns t,
    t1_ax..t1_ax2, t2_a, t2_b, and optionally gyro, temp, vsupply, seq; ticks are restamped from t). Samples are
    flagged FLAG_REPLAYED; seq is renumbered from 0 so gaps in the file are not replayed as gaps.
    """
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{path}: no such recording")
    if path.suffix.lower() == ".npy":
        arr = np.load(path, mmap_mode="r")
        names = arr.dtype.names or ()
        cols = {n: np.asarray(arr[n]) for n in names}
    else:
        with open(path, encoding="utf-8") as f:
            header = ""
            for line in f:
                if line.strip() and not line.lstrip().startswith("#"):
                    header = line
                    break
            names = [h.strip() for h in header.replace(";", ",").replace("\t", ",").split(",")]
            try:
                data = np.loadtxt(f, delimiter=",", comments="#", ndmin=2)
            except ValueError as exc:
                raise ValueError(f"{path}: not a numeric CSV recording ({exc})") from None
        if data.shape[1] != len(names):
            raise ValueError(f"{path}: header has {len(names)} columns, data rows have {data.shape[1]}")
        cols = {n: data[:, i] for i, n in enumerate(names)}
    need = ["t"] + [f"t1_{c}" for c in CHANNELS] + ["t2_a", "t2_b"]
    missing = [n for n in need if n not in cols]
    if missing:
        raise ValueError(f"{path}: replay needs the timer counts; missing column(s) {', '.join(missing)} "
                         f"(record with `gravcal simulate` or a raw logger dump)")
    t = np.asarray(cols["t"], dtype=np.float64)
    n = t.shape[0]
    if n < 2:
        raise ValueError(f"{path}: fewer than 2 samples, nothing to replay")
    dt = np.diff(t)
    if not np.all(dt > 0):
        raise ValueError(f"{path}: time column t is not strictly increasing")
    fs = 1.0 / float(np.median(dt))

    def blocks() -> Iterator[np.ndarray]:
        for s in range(0, n, block):
            e = min(n, s + block)
            b = np.zeros(e - s, SAMPLE_DTYPE)
            b["t"] = t[s:e] - t[0]
            b["seq"] = np.arange(s, e)
            b["tick"] = device_ticks(b["t"])  # a recorded tick may count at another clock
            for i, c in enumerate(CHANNELS):
                b["t1"][:, i] = cols[f"t1_{c}"][s:e]
            b["t2"][:, 0], b["t2"][:, 1] = cols["t2_a"][s:e], cols["t2_b"][s:e]
            if "gyro" in cols:
                b["gyro"] = cols["gyro"][s:e]
            b["temp"] = cols["temp"][s:e] if "temp" in cols else np.nan
            b["vsupply"] = cols["vsupply"][s:e] if "vsupply" in cols else np.nan
            b["flags"] = FLAG_REPLAYED
            yield b

    return Source(blocks(), fs, f"replay:{path.name}")
