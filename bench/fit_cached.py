"""CPU seconds of the bootstrap start, the fit and the held-out folds of `gravcal calibrate`, in-process on
cached windows (the block pass and detection run once, not per repeat).

    python bench/fit_cached.py FILE.npy --cache /tmp/FILE.windows.pkl [--repeat 5]

The first run with a new --cache path reads FILE as `gravcal calibrate` does, calibrates it once and stores
what the three stages receive (the bootstrap's samples, the screened windows, the start) in that pickle
(keep it outside the repository); later runs load it. Each repeat times core.estimators.start.bootstrap,
the model-auto fit (core/estimators/order_fit.py: order selection and extended-term trials) and
core.heldout.heldout_error with time.process_time (the machine is shared: wall time measures the
neighbours). Prints one JSON object: min and median CPU s per stage and the result (model, windows,
held-out error, which equal `gravcal calibrate --json`'s).
"""
from __future__ import annotations

import argparse
import json
import os
import pickle
import statistics
import time


def cache_inputs(path: str, cache: str) -> None:
    import numpy as np  # noqa: PLC0415

    from gravcal.core import pipeline  # noqa: PLC0415
    from gravcal.io import recordings  # noqa: PLC0415

    got: dict = {}
    real = {name: getattr(pipeline, name) for name in ("bootstrap", "_fit_order", "heldout_error")}

    def keep(name):
        def run(*a, **k):
            got.setdefault(name, (a, k))
            return real[name](*a, **k)
        return run

    for name in real:
        setattr(pipeline, name, keep(name))
    try:
        rec = recordings.read_recording(path, exclude_filler=True)
        pipeline.calibrate_recording(rec.t, rec.raw, temp=rec.temp, vsupply=rec.vsupply, fs=rec.fs)
    finally:
        for name, fn in real.items():
            setattr(pipeline, name, fn)
    (t, raw, fs), _ = got["bootstrap"]
    with open(cache, "wb") as f:
        pickle.dump({"bootstrap": (np.asarray(t), np.asarray(raw), fs), "fit": got["_fit_order"],
                     "heldout_kw": got["heldout_error"][1]}, f)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file")
    ap.add_argument("--cache", required=True, help="pickle of the stages' inputs (written on first use)")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    if not os.path.exists(args.cache):
        cache_inputs(args.file, args.cache)
    from gravcal.core import pipeline  # noqa: PLC0415

    with open(args.cache, "rb") as f:
        got = pickle.load(f)
    spent: dict[str, list[float]] = {"start": [], "fit": [], "held-out": []}

    @pipeline._blas_single_threaded  # as calibrate_recording runs
    def once():
        c = time.process_time()
        pipeline.bootstrap(*got["bootstrap"])
        spent["start"].append(time.process_time() - c)
        (ws, *rest), kw = got["fit"]
        c = time.process_time()
        fitted = pipeline._fit_order(ws, *rest, **kw)
        spent["fit"].append(time.process_time() - c)
        c = time.process_time()
        ho = pipeline.heldout_error(ws, fitted.model, **{**got["heldout_kw"], "start": fitted.fold_start,
                                                           "full_fit": fitted.calibration, "estimator": fitted.estimator})
        spent["held-out"].append(time.process_time() - c)
        return fitted.model, len(ws), ho.heldout_rms_mg

    for _ in range(args.repeat):
        result = once()
    print(json.dumps({"cpu_s": {k: {"min": round(min(v), 3), "median": round(statistics.median(v), 3)}
                                for k, v in spent.items()},
                      "model": result[0], "windows": result[1], "heldout_rms_mg": result[2],
                      "repeat": args.repeat, "load_average": round(os.getloadavg()[0], 2)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
