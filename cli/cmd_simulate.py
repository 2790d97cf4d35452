"""``gravcal simulate``: a simulated recording in the format ``gravcal calibrate`` reads.

Writes FILE.csv (or FILE.npy by extension) with the triad's duty cycles ax, ay, az (the raw
units the estimators work in) plus the extra channels (ax2, gyro, temp, vsupply, seq, flags,
timer counts), and FILE.truth.json beside it: the true effective calibration of the
simulated triad ("calibration", a gravcal calibration object), the sensor model, the
scenario and the seed. Samples are generated and written block by block (simulate_blocks),
so a week at 100 Hz needs no more memory than one block.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from gravcal.core.model.terms import GROUPS, REGISTRY

from ..errors import InputError
from .summaries import SUMMARIES

log = logging.getLogger(__name__)

MODEL_FLAGS = tuple(GROUPS)  # one flag per group of registered terms
BLOCK_SAMPLES = 1 << 16


def scenario_choices() -> list[str]:
    from gravcal.core.scenarios import SCENARIOS

    return list(SCENARIOS)


def _kv(text: str) -> tuple[str, Any]:
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    key, value = text.split("=", 1)
    try:
        return key.strip(), json.loads(value)
    except json.JSONDecodeError:
        return key.strip(), value


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "simulate", help=SUMMARIES["simulate"],
        description="Simulate the IMU worn through a motion scenario; write the samples in the format "
                    "`gravcal calibrate` reads and the true parameters beside them as FILE.truth.json.",
    )
    p.add_argument("--scenario", default="daily_living", metavar="NAME",
                   help="motion scenario: daily_living (default), loetters, six_position, sagittal_postures, "
                        "static (gravcal.core.scenarios.SCENARIOS)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sensor draw and the session (default 0)")
    p.add_argument("--duration", type=float, default=3600.0, metavar="SECONDS", help="length [s] (default 3600)")
    p.add_argument("--fs", type=float, default=100.0, metavar="HZ", help="sample rate [Hz] (default 100)")
    p.add_argument("--out", type=Path, required=True, metavar="FILE.csv|FILE.npy", help="output recording")
    p.add_argument("--nominal", action="store_true", help="a datasheet-typical sensor instead of one drawn from the spreads")
    for flag in MODEL_FLAGS:
        p.add_argument(f"--{flag}", action="store_true", help=f"switch on the model's {flag} terms ({', '.join(GROUPS[flag])})")
    p.add_argument("--term", dest="terms", action="append", default=[], metavar="NAME",
                   help=f"add one registered term, repeatable ({', '.join(REGISTRY)})")
    p.add_argument("--set", dest="scenario_kw", action="append", type=_kv, default=[], metavar="KEY=VALUE",
                   help="scenario option, repeatable (e.g. --set orientation=2 --set theta_max_deg=60)")
    return p


def build_model(seed: int, *, nominal: bool = False, **flags: bool):
    """The simulated sensor: drawn from the datasheet spreads with ``seed`` (or nominal).

    Uses the same stream as core.simulate for ``model=None`` (the second child of
    SeedSequence(seed)), so without flags the sensor is the one ``simulate(seed=...)`` draws;
    default_model seeds every term separately, so flags add terms without changing the others.
    """
    from gravcal.core.model.defaults import default_model

    model_stream = np.random.SeedSequence(seed).spawn(3)[1]
    return default_model(np.random.default_rng(model_stream), nominal=nominal, **flags)


def run(args: argparse.Namespace) -> int:
    from gravcal.core.model.defaults import triad_truth
    from gravcal.core.simulate import simulate_blocks

    from ..io.recordings import write_recording, write_truth

    scenarios = scenario_choices()
    if args.scenario not in scenarios:
        raise InputError(f"unknown --scenario {args.scenario!r}; choose one of {', '.join(scenarios)}")
    if not (args.duration > 0 and math.isfinite(args.duration)):
        raise InputError(f"--duration must be a positive number of seconds, got {args.duration}")
    if not (args.fs > 0 and math.isfinite(args.fs)):
        raise InputError(f"--fs must be a positive number of Hz, got {args.fs}")
    if args.out.suffix.lower() not in (".csv", ".npy"):
        raise InputError(f"--out {args.out}: the extension must be .csv or .npy")
    if not args.out.parent.exists():
        raise InputError(f"--out {args.out}: directory {args.out.parent} does not exist")
    flags: dict[str, Any] = {f: bool(getattr(args, f)) for f in MODEL_FLAGS}
    for name in args.terms:
        if name not in REGISTRY:
            raise InputError(f"unknown --term {name!r}; registered terms: {', '.join(REGISTRY)}")
        flags[name] = True
    kw = dict(args.scenario_kw)
    model = build_model(args.seed, nominal=args.nominal, **flags)
    n_total = int(round(args.duration * args.fs))
    seen = _Conditions()
    blocks = simulate_blocks(args.scenario, model, seed=args.seed, duration=args.duration, fs=args.fs,
                             block=BLOCK_SAMPLES, **kw)
    n = write_recording(args.out, seen.watch(blocks), n_total=n_total if args.out.suffix.lower() == ".npy" else None)
    cond = seen.conditions()
    truth_cal = triad_truth(model, **cond)
    truth = {
        "calibration": truth_cal.to_dict(),
        "conditions": cond,
        "model": model.to_dict(),
        "scenario": args.scenario,
        "scenario_kw": kw,
        "seed": args.seed,
        "fs": args.fs,
        "duration_s": args.duration,
        "n_samples": n,
        "flags": flags,
        "nominal": bool(args.nominal),
        "recording": args.out.name,
        "raw_units": "duty cycle T1/T2 of channels ax, ay, az; raw = sensitivity @ a[g] + offset",
    }
    tp = write_truth(args.out, truth)
    print(f"wrote {n} samples ({args.duration:g} s at {args.fs:g} Hz, scenario {args.scenario}, seed {args.seed}) "
          f"to {args.out}; true parameters in {tp}")
    return 0


class _Conditions:
    """Median temperature [°C] and supply [V] over the stream and its mid time [s]: the
    conditions at which the truth is evaluated (exact unless temperature, supply or drift
    terms are on; core.simulate.simulate uses the still samples, which a stream of samples
    cannot tell apart, so over long sessions the two agree to the spread of the medians)."""

    def __init__(self) -> None:
        self.temp: list[np.ndarray] = []
        self.vsupply: list[np.ndarray] = []
        self.t0 = self.t1 = 0.0
        self.n = 0

    def watch(self, blocks):
        for b in blocks:
            if self.n == 0 and len(b):
                self.t0 = float(b["t"][0])
            if len(b):
                self.t1 = float(b["t"][-1])
                self.temp.append(b["temp"][::10].astype(float))  # every 10th sample: plenty for a median
                self.vsupply.append(b["vsupply"][::10].astype(float))
                self.n += len(b)
            yield b

    def conditions(self) -> dict[str, float]:
        if self.n == 0:
            raise InputError("the simulation produced no samples (duration shorter than one sample?)")
        return {"temp_c": float(np.median(np.concatenate(self.temp))),
                "vsupply": float(np.median(np.concatenate(self.vsupply))),
                "t": 0.5 * (self.t0 + self.t1)}
