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

from ..errors import InputError
from ..io.recordings import jsonable
from .summaries import SUMMARIES

log = logging.getLogger(__name__)

EXPERIMENTS = ("loetters",)
FIGURE_NAME = "loetters_theta.png"
LABELS = {"o1_all": "orient. 1, all", "o1_offsets": "orient. 1, offsets", "o2_all": "orient. 2, all",
          "o2_offsets": "orient. 2, offsets"}


# option -> ReproduceConfig field; every default shown in --help is the config's own
OPTION_FIELDS = {"seeds": "seeds", "points": "n_points", "c_mu_reading": "c_mu_reading", "spread": "spread",
                 "theta_step": None, "held_sensitivity_error": "held_sensitivity_error", "criterion": "criterion"}


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    from gravcal.core.reproduce_config import (C_MU_READINGS, CRITERIA, DEFAULT_THETA_STEP_DEG, SPREADS,
                                               ReproduceConfig)

    d = ReproduceConfig()
    p = subparsers.add_parser(
        "reproduce", help=SUMMARIES["reproduce"],
        description="Lötters et al. 1998, Sections 3-4: sensitivity/offset error (eq. 15-16, % of 1 g) against θ "
                    "for orientations 1 and 2, all parameters vs offsets only, Monte-Carlo over seeds. "
                    "docs/loetters.md explains every option.",
    )
    p.add_argument("experiment", choices=EXPERIMENTS, help="which experiment")
    p.add_argument("--seeds", type=int, default=d.seeds, help="Monte-Carlo runs per θ (default %(default)s)")
    p.add_argument("--points", type=int, default=d.n_points, help="quasi-static points per run (default %(default)s)")
    p.add_argument("--c-mu-reading", choices=C_MU_READINGS, default=d.c_mu_reading,
                   help=f"read the paper's C_mu = {d.c_mu:g} as a std [g] or a variance [g²] (default %(default)s)")
    p.add_argument("--spread", choices=SPREADS, default=d.spread,
                   help="points uniform over the cap's area, or polar angle uniform (default %(default)s)")
    p.add_argument("--theta-step", type=float, default=DEFAULT_THETA_STEP_DEG, metavar="DEG",
                   help="θ grid step from 0 to 180° (default %(default)s)")
    p.add_argument("--held-sensitivity-error", type=float, default=d.held_sensitivity_error, metavar="FRACTION",
                   help="offsets only: hold the sensitivities off the truth by up to this fraction (default %(default)s)")
    p.add_argument("--criterion", choices=CRITERIA, default=d.criterion,
                   help="combine the three axes' errors by their mean or take the worst axis (default %(default)s)")
    p.add_argument("--out", type=Path, default=Path("."), metavar="DIR", help="where the figure goes (default .)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    return p


def _fmt(v: float | None) -> str:
    return "never" if v is None else f"≥ {v:g}°"


def table(result: Any) -> str:
    from gravcal.core.reproduce_config import KEYS, PAPER_STRICT, PAPER_THRESHOLDS_DEG, paper_threshold_on_grid

    c = result.config
    lim = c.threshold_pct
    axes = "mean over the axes" if c.criterion == "mean" else "worst axis"
    lines = [f"error [% of 1 g] (all: max of sensitivity and offset error, eq. 15-16); {axes}, mean over "
             f"{c.seeds} seeds; {c.n_points} points per run, σ_μ {c.sigma_mu_g:.3g} g, spread {c.spread}"
             + (f", held sensitivities off by up to {c.held_sensitivity_error:g}" if c.held_sensitivity_error else ""),
             "   θ [deg] " + "".join(f"{LABELS[k]:>20}" for k in KEYS)]
    for i, th in enumerate(result.theta_deg):
        cells = []
        for k in KEYS:
            v, se = (float(x[i]) for x in result.error_and_se_pct(k))
            cell = "n/a" if not math.isfinite(v) else f"{v:.3g}" + (f" ± {se:.2g}" if math.isfinite(se) else "")
            cells.append(f"{cell:>20}")
        lines.append(f"{th:10g} " + "".join(cells))
    lines.append(f"θ from which the error stays under {lim:g} % (± one standard error over the seeds above):")
    for k in KEYS:
        paper = PAPER_THRESHOLDS_DEG.get(k)
        if paper is None:
            ref = "(paper: not stated)"
        else:
            try:
                on_grid = f", on this grid ≥ {paper_threshold_on_grid(k, result.theta_deg):g}°"
            except ValueError:
                on_grid = ""
            ref = f"(paper: {'>' if PAPER_STRICT[k] else '≥'} {paper:g}°{on_grid})"
        lines.append(f"   {LABELS[k]:<20} {_fmt(result.thresholds_deg.get(k)):>10}   {ref}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from gravcal.core.reproduce import KEYS, make_figure, reproduce_loetters
    from gravcal.core.reproduce_config import theta_grid

    if args.seeds < 1:
        raise InputError(f"--seeds must be at least 1, got {args.seeds}")
    if args.points < 6:
        raise InputError(f"--points must be at least 6 (six parameters), got {args.points}")
    if not (0 <= args.held_sensitivity_error < 1):
        raise InputError(f"--held-sensitivity-error must be a fraction in [0, 1), got {args.held_sensitivity_error:g}")
    try:
        theta = theta_grid(args.theta_step)
    except ValueError as exc:
        raise InputError(f"--theta-step: {exc}") from None
    overrides = {field: getattr(args, opt) for opt, field in OPTION_FIELDS.items() if field is not None}
    overrides["theta_deg"] = theta
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
