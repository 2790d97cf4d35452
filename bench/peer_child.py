"""Child-process entry point for bench_calibrate.py: one peer calibrator on one cached recording.

    python bench/peer_child.py PEER FILE.npy [--fs 100]

Prints one JSON object on stdout. Runs in its own process so the parent can take this run's
own peak RSS (ru_maxrss via os.wait4) and nothing else's.

Reading is what a peer's user does before calling it, timed apart from the calibration:
the structured .npy (t f8, ax/ay/az f4 duty cycles) is read in blocks straight into the arrays
the peer takes, converted to nominal g with the ADXL210 datasheet scale (duty - 0.5) / 0.04,
so the peak memory is the peer's input plus what the peer itself allocates, not a second copy
of the file:
    skdh    t (N,) float64 [s] and accel (N, 3) float64 [g] -> CalibrateAccelerometer().predict(...,
            apply=True), through bench/peers.py's adapter (its users keep the calibrated data).
    actipy  a DataFrame with a DatetimeIndex and x, y, z columns [g] -> calibrate_gravity(df,
            return_coeffs=True), called directly: peers.py's adapter builds its own DataFrame from
            arrays, which would hold both and overstate actipy's memory.
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peers  # noqa: E402

ADXL_ZERO, ADXL_PER_G = 0.5, 0.04  # ADXL210 datasheet: 50 % duty at 0 g, 4 %/g
READ_BLOCK = 1 << 20  # records per read: 20 MB of buffer


def read_nominal_g(path: Path, zero=(ADXL_ZERO,) * 3, per_g=(ADXL_PER_G,) * 3) -> tuple[np.ndarray, np.ndarray]:
    """t [s] (N,) and acceleration (duty - zero) / per_g [g] (N, 3), both float64, read block by block."""
    with open(path, "rb") as f:
        version = np.lib.format.read_magic(f)
        read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, fortran, dtype = read_header(f)
        if fortran or len(shape) != 1 or dtype.names is None or not {"t", "ax", "ay", "az"} <= set(dtype.names):
            raise ValueError(f"{path}: expected a 1-D structured array with fields t, ax, ay, az; got {dtype} {shape}")
        n = shape[0]
        t = np.empty(n)
        acc = np.empty((n, 3))
        buf = np.empty(READ_BLOCK, dtype=dtype)
        i = 0
        while i < n:
            k = min(READ_BLOCK, n - i)
            view = buf[:k]
            got = f.readinto(memoryview(view).cast("B"))
            if got != k * dtype.itemsize:
                raise ValueError(f"{path}: truncated at record {i + got // dtype.itemsize} of {n}")
            t[i:i + k] = view["t"]
            for j, name in enumerate(("ax", "ay", "az")):
                acc[i:i + k, j] = view[name]
            i += k
    acc -= np.asarray(zero, dtype=float)
    acc /= np.asarray(per_g, dtype=float)
    return t, acc


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("peer", choices=["skdh", "actipy"])
    ap.add_argument("path", type=Path)
    ap.add_argument("--fs", type=float, default=100.0)
    ap.add_argument("--zero", type=float, nargs=3, default=[ADXL_ZERO] * 3, help="duty cycle read as 0 g, per axis")
    ap.add_argument("--per-g", type=float, nargs=3, default=[ADXL_PER_G] * 3, help="duty cycle per g, per axis")
    ap.add_argument("--sphere-crit", type=float, default=None,
                    help="override the peer's sphere/cube gate [g] (default: the peer's own, 0.3; NOT as users run it)")
    args = ap.parse_args()
    t_start = time.perf_counter()
    # import the peer first: its import time is start-up, not reading or calibrating
    if args.peer == "skdh":
        import skdh.preprocessing  # noqa: F401

        if args.sphere_crit is not None:
            import functools

            # peers._skdh builds CalibrateAccelerometer(min_hours=...) from this module attribute
            skdh.preprocessing.CalibrateAccelerometer = functools.partial(skdh.preprocessing.CalibrateAccelerometer,
                                                                          sphere_crit=args.sphere_crit)
    else:
        import actipy.processing  # noqa: F401
        import pandas  # noqa: F401
    t0, c0 = time.perf_counter(), cpu_s()
    t, acc = read_nominal_g(args.path, args.zero, args.per_g)
    df = peers.actipy_frame(t, acc) if args.peer == "actipy" else None
    if df is not None:
        del t  # the DataFrame holds acc and its own index; the user keeps only the frame
    t_read, c_read = time.perf_counter() - t0, cpu_s() - c0
    rss_after_read = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    t1, c1 = time.perf_counter(), cpu_s()
    if args.peer == "skdh":
        res = peers._skdh(t, acc, args.fs, None)  # the adapter's call is the user's call, on these arrays
    else:
        res = peers.run_actipy(df, args.sphere_crit)
    t_cal, c_cal = time.perf_counter() - t1, cpu_s() - c1
    out = {"peer": args.peer, "ok": res.ok, "message": res.message, "n_samples": int(acc.shape[0]),
           "offset_g": res.offset_g.tolist(), "matrix": res.matrix.tolist(),
           "timing_s": {"startup": t0 - t_start, "read": t_read, "calibrate": t_cal, "peer_call": res.seconds,
                        "read_cpu": c_read, "calibrate_cpu": c_cal},
           "rss_after_read_bytes": rss_after_read, "sphere_crit": args.sphere_crit}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
