"""``gravcal reproduce loetters``: the simulation of Lötters et al. 1998, Sections 3-4.

Error of the estimated sensitivities and offsets (eq. 15-16, % of 1 g) against θ, the part of
the ellipsoid the quasi-static moments cover, for orientations 1 and 2, all parameters vs
offsets only (numerics in gravcal.core.reproduce). Prints a table and the θ from which the
error stays under 3 %, writes a PNG figure when matplotlib is installed, and with ``--json``
prints one object with those thresholds under o1_all, o1_offsets, o2_all, o2_offsets.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path
from typing import Any

from .errors import InputError
from .recordings import jsonable

log = logging.getLogger(__name__)

EXPERIMENTS = ("loetters",)
FIGURE_NAME = "loetters_theta.png"
PAPER_WORDING = {"o1_all": ">", "o1_offsets": ">", "o2_all": "≥"}  # Sect. 4 as the issue quotes it
LABELS = {"o1_all": "orient. 1, all", "o1_offsets": "orient. 1, offsets", "o2_all": "orient. 2, all",
          "o2_offsets": "orient. 2, offsets"}


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "reproduce", help="re-run a paper's experiment (loetters: error vs θ, Sections 3-4)",
        description="Lötters et al. 1998, Sections 3-4: sensitivity/offset error (eq. 15-16, %% of 1 g) against θ "
                    "for orientations 1 and 2, all parameters vs offsets only, Monte-Carlo over seeds.",
    )
    p.add_argument("experiment", choices=EXPERIMENTS, help="which experiment")
    p.add_argument("--seeds", type=int, default=None, help="Monte-Carlo runs per θ (default: the library's, 40)")
    p.add_argument("--points", type=int, default=None, help="quasi-static points per run (default: the library's)")
    p.add_argument("--c-mu-reading", choices=("variance", "std"), default=None,
                   help="read the paper's C_mu = 0.05 as a variance [g²] (default) or a std [g]")
    p.add_argument("--out", type=Path, default=Path("."), metavar="DIR", help="where the figure goes (default .)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    return p


def _fmt(v: float | None) -> str:
    return "never" if v is None else f"≥ {v:g}°"


def table(result: Any) -> str:
    from gravcal.core.reproduce import KEYS, PAPER_THRESHOLDS_DEG

    lim = result.config.threshold_pct
    lines = [f"error [% of 1 g] (all: max of sensitivity and offset error, eq. 15-16); mean over "
             f"{result.config.seeds} seeds",
             "   θ [deg] " + "".join(f"{LABELS[k]:>20}" for k in KEYS)]
    for i, th in enumerate(result.theta_deg):
        cells = []
        for k in KEYS:
            v = float(result.error_pct(k)[i])
            cells.append(f"{'n/a' if not math.isfinite(v) else f'{v:.3g}':>20}")
        lines.append(f"{th:10g} " + "".join(cells))
    lines.append(f"θ from which the error stays under {lim:g} %:")
    for k in KEYS:
        paper = PAPER_THRESHOLDS_DEG.get(k)
        ref = f"(paper: {PAPER_WORDING.get(k, '')} {paper:g}°)" if paper is not None else "(paper: not stated)"
        lines.append(f"   {LABELS[k]:<20} {_fmt(result.thresholds_deg.get(k)):>10}   {ref}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from gravcal.core.reproduce import KEYS, make_figure, reproduce_loetters

    overrides: dict[str, Any] = {}
    if args.seeds is not None:
        if args.seeds < 1:
            raise InputError(f"--seeds must be at least 1, got {args.seeds}")
        overrides["seeds"] = args.seeds
    if args.points is not None:
        overrides["n_points"] = args.points
    if args.c_mu_reading is not None:
        overrides["c_mu_reading"] = args.c_mu_reading
    if args.out.exists() and not args.out.is_dir():
        raise InputError(f"--out {args.out}: exists and is not a directory")
    result = reproduce_loetters(**overrides)

    figure: str | None = None
    figure_note: str
    try:
        fig = make_figure(result)
    except ImportError:
        figure_note = "no figure: matplotlib is not installed (pip install 'gravcal[figures]')"
    else:
        args.out.mkdir(parents=True, exist_ok=True)
        path = args.out / FIGURE_NAME
        fig.savefig(path, dpi=120)
        figure = str(path)
        figure_note = f"figure written to {path}"

    if args.json:
        out = {k: result.thresholds_deg.get(k) for k in KEYS}
        out.update(result.to_dict())
        out["figure"] = figure
        print(json.dumps(jsonable(out)))
    else:
        print(table(result))
        print(figure_note)
    if figure is None:
        log.warning("%s", figure_note)
    return 0
