"""CPU seconds per stage of `gravcal calibrate` on one recording (all threads: process_time).

    python bench/calibrate_stages.py FILE.npy [--repeat 1]

Stages: imports (the CLI's calibrate imports), read (daemon.recordings.read_recording: mapping,
validating, finding exactly repeated runs and the block statistics in the same pass, as `gravcal
calibrate` reads; "block pass" is then only a recomputation when reading dropped rows), filler (dropping those runs' rows,
which `calibrate` does by default), start (the bootstrap calibration), block pass (core.fastdetect.block_stats), detection
(detectors on the block statistics, window statistics, screening), fit (order and extended-term
selection, re-detection's refit included), held-out (the contiguous folds). CPU time (all threads) and wall time per stage: on a shared
machine the wall time also measures the neighbours, and with threads CPU time exceeds wall time.
Prints one JSON object: seconds per stage, the total and the result (model, windows, held-out).
"""
from __future__ import annotations

import argparse
import json
import sys
import time

C0, W0 = time.process_time(), time.perf_counter()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file")
    args = ap.parse_args()
    from gravcal.core import pipeline  # noqa: PLC0415
    from gravcal.io import recordings  # noqa: PLC0415

    spent = {"imports": time.process_time() - C0}
    wall = {"imports": time.perf_counter() - W0}

    def timed(module, name, stage):
        fn = getattr(module, name)

        def run(*a, **k):
            c, w = time.process_time(), time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                spent[stage] = spent.get(stage, 0.0) + time.process_time() - c
                wall[stage] = wall.get(stage, 0.0) + time.perf_counter() - w

        setattr(module, name, run)

    timed(pipeline, "_bootstrap", "start")
    timed(pipeline, "block_stats", "block pass")
    timed(pipeline, "detect_blocks", "detection")
    timed(pipeline, "screen_windows", "detection")
    timed(pipeline, "_fit_order", "fit")
    timed(pipeline, "heldout_error", "held-out")
    timed(recordings, "_without_filler", "filler")
    c, w = time.process_time(), time.perf_counter()
    rec = recordings.read_recording(args.file, exclude_filler=True, blocks=True)  # as `gravcal calibrate` reads
    spent["read"] = time.process_time() - c - spent["filler"]
    wall["read"] = time.perf_counter() - w - wall["filler"]
    c, w = time.process_time(), time.perf_counter()
    rep = pipeline.calibrate_recording(rec.t, rec.raw, temp=rec.temp, vsupply=rec.vsupply, fs=rec.fs, blocks=rec.blocks)
    staged = ("imports", "read", "filler")
    spent["other"] = time.process_time() - c - sum(v for k, v in spent.items() if k not in staged)
    wall["other"] = time.perf_counter() - w - sum(v for k, v in wall.items() if k not in staged)
    spent["total"], wall["total"] = time.process_time() - C0, time.perf_counter() - W0
    print(json.dumps({"cpu_s": {k: round(v, 3) for k, v in spent.items()},
                      "wall_s": {k: round(v, 3) for k, v in wall.items()}, "model": rep.calibration.model, "windows": rep.n_windows,
                      "heldout_rms_mg": rep.heldout_rms_mg, "python": sys.version.split()[0]}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
