"""CPU seconds of diagnose's parts, the ones the test suite repeats most.

    python bench/diagnose_speed.py [--sessions 6] [--recording actigraph_cpw_thermal_chamber]

Window-level sessions (core/diagnosis/synthetic.py, the hidden-effect tests' sessions): diagnose_windows
without and with the nested held-out gain, all registered terms; a measured recording (GRAVCAL_DATA):
diagnose end to end and its quantization test alone. CPU time of this process (time.process_time), so a
machine shared with other work reads about the same; the minimum of ``--repeat`` runs.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from gravcal.core.diagnosis import diagnose, diagnose_windows
from gravcal.core.diagnosis.noise import quantization_test
from gravcal.core.diagnosis.synthetic import PLANT, window_session
from gravcal.core.model.terms import CALIBRATION_TERMS


def cpu(fn, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t = time.process_time()
        fn()
        best = min(best, time.process_time() - t)
    return best


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sessions", type=int, default=6)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--recording", default="actigraph_cpw_thermal_chamber")
    args = ap.parse_args()
    sessions = [window_session(6000 + k, {"supply_offset": PLANT["supply_offset"]}) for k in range(args.sessions)]
    for nested in (False, True):
        def run(nested=nested):
            for s in sessions:
                diagnose_windows(s.ws, s.start, has_temp=True, candidates=CALIBRATION_TERMS, simulate=False,
                                 nested=nested)
        print(f"diagnose_windows, nested={nested!s:5}: {cpu(run, args.repeat) / len(sessions):.3f} s CPU per session")
    try:
        from gravcal.io import datasets

        r = datasets.load(args.recording)
    except (OSError, ValueError, KeyError) as e:
        print(f"recording {args.recording}: not measured ({e})")
        return
    d = diagnose(r.t, r.acc, temp=r.temp, fs=r.fs, replicas=10)
    print(f"diagnose {args.recording}: {cpu(lambda: diagnose(r.t, r.acc, temp=r.temp, fs=r.fs, replicas=10), 1):.2f} s CPU")
    stretches = [np.asarray(r.acc[w0:w1], dtype=float) for w0, w1 in zip(d.windows.start, d.windows.end)]
    scale = np.abs(np.diag(d.baseline_cal.sensitivity))
    n = sum(s.shape[0] for s in stretches)
    print(f"quantization_test on its {len(stretches)} windows ({n} samples): "
          f"{cpu(lambda: quantization_test(stretches, scale), args.repeat):.3f} s CPU")


if __name__ == "__main__":
    main()
