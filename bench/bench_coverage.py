"""Coverage of every std the batch fit states, on sessions gravcal's simulator did not make: not a test.

    python bench/bench_coverage.py [--seeds 400] [--first 1000] [--workers 2] [--json PATH]
    python bench/bench_coverage.py --boundary 20 [--seeds 80] [--kind temperature_offset]
    python bench/bench_coverage.py --diagnose [--seeds 100] [--kinds temperature_offset,supply_offset]

Sessions from tests/support/independent_sessions.py (the physics written anew, its own random streams; the
kinds are listed there), each fitted with the model it was made with (tests/support/coverage_runs.py, the same
code tests/core/test_coverage.py asserts on). Prints, per session kind and pooled, for each stated quantity:
n (estimates scored), RMS of z = (estimate - truth) / stated std, the share beyond 2σ (4.55 % for an honest
Gaussian std) and the sessions refused or stated as not determined. ``--first``: the first seed (the test uses
0-99; the default here starts at 1000, sessions the test never saw).

``--boundary LAMBDA``: instead, sessions of ``--kind`` with the planted term scaled to noncentrality LAMBDA
against the 6-parameter baseline (tests/support/boundary_sessions.py), diagnosed at the ΔBIC threshold and at
half of it: the share named at each, beside the share whose ΔBIC would exceed the threshold by theory.

``--diagnose``: instead, the magnitudes diagnose states for a term (tests/support/diagnose_coverage.py: one
planted term, offered alone, scored in every session where it is testable, named or not), per kind and regime,
with the share named and the named ones' z apart.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from support.coverage_runs import KINDS, QUANTITIES, pooled, rms, rms_bounds  # noqa: E402


def _pmap(workers: int):
    if workers <= 1:
        return None
    import multiprocessing as mp  # noqa: PLC0415
    from concurrent.futures import ProcessPoolExecutor  # noqa: PLC0415

    def run(fn, args):
        with ProcessPoolExecutor(workers, mp_context=mp.get_context("fork")) as pool:
            return list(pool.map(fn, *zip(*args), chunksize=16))
    return run


def _cell(z: np.ndarray) -> str:
    return f"{rms(z):.3f} ({np.mean(np.abs(z) > 2) * 100:.1f} %)"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=400, help="sessions per kind")
    ap.add_argument("--first", type=int, default=1000, help="first seed")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", metavar="PATH")
    ap.add_argument("--boundary", type=float, metavar="LAMBDA")
    ap.add_argument("--kind", default="temperature_offset", help="--boundary: the session kind (a term kind)")
    ap.add_argument("--diagnose", action="store_true", help="diagnose's term magnitudes instead of the batch fit")
    ap.add_argument("--kinds", help="--diagnose: only these kinds (comma-separated; a quick look at a few)")
    a = ap.parse_args(argv)
    if a.boundary is not None:
        return _boundary(a)
    if a.diagnose:
        return _diagnose(a)
    t0 = time.perf_counter()
    res = pooled(KINDS, range(a.first, a.first + a.seeds), mapper=_pmap(a.workers))
    wall = time.perf_counter() - t0
    cols = [q for q in QUANTITIES if any(q in d for d in res.values())]
    print(f"RMS z (share beyond 2σ), {a.seeds} sessions per kind, seeds {a.first}-{a.first + a.seeds - 1}, "
          f"{wall:.0f} s on {a.workers} worker(s)\n")
    print("| kind | model | " + " | ".join(cols) + " | refused / not determined |")
    print("|---" * (len(cols) + 3) + "|")
    from support.independent_sessions import MODEL  # noqa: PLC0415
    for kind, d in res.items():
        cells = [_cell(d[q]) if q in d else "" for q in cols]
        skipped = f"{len(d.get('refused', ()))} / {len(d.get('flagged', ()))}"
        print(f"| {kind} | {MODEL[kind]} | " + " | ".join(cells) + f" | {skipped} |")
    pooled_z = {q: np.concatenate([d[q] for d in res.values() if q in d]) for q in cols}
    print("| **pooled** | | " + " | ".join(_cell(pooled_z[q]) for q in cols) + " | |")
    print("| n (pooled) | | " + " | ".join(str(pooled_z[q].size) for q in cols) + " | |")
    print("| chi² bounds (1e-3) | | " + " | ".join("{:.3f}-{:.3f}".format(*rms_bounds(pooled_z[q].size)) for q in cols)
          + " | |")
    if a.json:
        out = {"seeds": a.seeds, "first": a.first, "wall_s": wall,
               "kinds": {k: {q: {"n": int(z.size), "rms_z": rms(z), "beyond_2sigma": float(np.mean(np.abs(z) > 2))}
                             for q, z in d.items() if q not in ("refused", "flagged")}
                         | {"refused": len(d.get("refused", ())), "not_determined": len(d.get("flagged", ()))}
                         for k, d in res.items()},
               "pooled": {q: {"n": int(z.size), "rms_z": rms(z), "beyond_2sigma": float(np.mean(np.abs(z) > 2))}
                          for q, z in pooled_z.items()}}
        Path(a.json).write_text(json.dumps(out, indent=1))
    return 0


def _diagnose(a) -> int:
    """diagnose's term magnitudes (tests/support/diagnose_coverage.py), scored in every session where the term is
    testable, named or not, per kind and regime; beside them the share named and the z of the named ones alone."""
    from support.diagnose_coverage import DIAGNOSE_KINDS, session_z  # noqa: PLC0415

    kinds = tuple(a.kinds.split(",")) if a.kinds else DIAGNOSE_KINDS
    unknown = sorted(set(kinds) - set(DIAGNOSE_KINDS))
    if unknown:
        raise SystemExit(f"unknown kind(s) {unknown}: choose from {', '.join(DIAGNOSE_KINDS)}")
    args = [(k, s) for k in kinds for s in range(a.first, a.first + a.seeds)]
    t0 = time.perf_counter()
    mapper = _pmap(a.workers)
    results = mapper(session_z, args) if mapper else [session_z(*x) for x in args]
    print(f"diagnose, term magnitudes: RMS z (share beyond 2σ), {a.seeds} sessions per kind, seeds "
          f"{a.first}-{a.first + a.seeds - 1}, {time.perf_counter() - t0:.0f} s\n")
    print("| kind | statistical: sessions, named | n, RMS z, every session | named only | not named | "
          "chi² bounds (1e-3) | held: sessions, n, RMS z | held: chi² bounds | refused / untestable |")
    print("|---|---|---|---|---|---|---|---|---|")
    for kind in kinds:
        res = [r for (k, _), r in zip(args, results) if k == kind]
        stat = [r for r in res if r["regime"] == "statistical"]
        z_of = lambda rs: np.asarray([v for r in rs for v in r["z"]])  # noqa: E731
        z, zn, zu, zh = (z_of(stat), z_of([r for r in stat if r["named"]]), z_of([r for r in stat if not r["named"]]),
                         z_of([r for r in res if r["regime"] == "held"]))
        cell = lambda z: f"{z.size}, {_cell(z)}" if z.size else ""  # noqa: E731
        named = sum(r["named"] for r in stat)
        bounds = "{:.3f}-{:.3f}".format(*rms_bounds(z.size)) if z.size else ""
        held = [r for r in res if r["regime"] == "held"]
        print(f"| {kind} | {len(stat)}, {named / max(len(stat), 1) * 100:.0f} % | {cell(z)} | {cell(zn)} | {cell(zu)} | "
              f"{bounds} | {len(held)}, {cell(zh)} | {'{:.3f}-{:.3f}'.format(*rms_bounds(zh.size)) if zh.size else ''} | "
              f"{sum(r['regime'] == 'refused' for r in res)} / {sum(r['regime'] == 'untestable' for r in res)} |")
    return 0


def _boundary(a) -> int:
    from gravcal.core.diagnosis.noise import DELTA_BIC  # noqa: PLC0415
    from scipy.stats import ncx2  # noqa: PLC0415
    from support.boundary_sessions import named_share  # noqa: PLC0415
    from support.independent_sessions import session  # noqa: PLC0415

    seeds = range(a.first, a.first + a.seeds)
    t0 = time.perf_counter()
    res = named_share(a.kind, seeds, a.boundary, (DELTA_BIC, DELTA_BIC / 2))
    m = len(session(a.kind, a.first).windows)
    pred = {t: float(ncx2.sf(t + 3 * np.log(m), 3, a.boundary)) for t in (DELTA_BIC, DELTA_BIC / 2)}
    print(f"{a.kind}, noncentrality {a.boundary:g}, {a.seeds} sessions ({time.perf_counter() - t0:.0f} s); "
          f"ΔBIC median {res['delta_bic_median']:.1f} (theory {ncx2.median(3, a.boundary) - 3 * np.log(m):.1f}); "
          f"largest ΔBIC of any of {res['term_tests']} term tests {res['delta_bic_max_any_term']:.1f}")
    for t in (DELTA_BIC, DELTA_BIC / 2):
        print(f"  threshold {t:g}: named in {res['named'][t] * 100:.1f} % of {res['sessions'][t]} sessions "
              f"(another term in {res['other_named'][t] * 100:.1f} %); ΔBIC > {t:g} by theory {pred[t] * 100:.1f} %")
    if a.json:
        Path(a.json).write_text(json.dumps({"kind": a.kind, "lambda": a.boundary, **res, "theory": pred}, indent=1,
                                           default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
