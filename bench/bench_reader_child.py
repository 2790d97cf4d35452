"""What reading scikit-digital-health's files in a child process costs (io/formats/isolated.py), against the same
reader in this process, the same run:

    GRAVCAL_SKDH_FIXTURES=DIR python bench/bench_reader_child.py [--repeat 5] [FILE ...]

Per file: the in-process read (skdh imported beforehand, as a process that has read one file already), the read
through the warm child (its columns through a tmpfs as .npy), and the first read of a fresh child (its start and
skdh's imports), each the median of --repeat; wall seconds and this process's CPU seconds.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path


def timed(f, repeat: int) -> tuple[float, float]:
    walls, cpus = [], []
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        f()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return statistics.median(walls), statistics.median(cpus)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="*")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    folder = Path(os.environ.get("GRAVCAL_SKDH_FIXTURES", "."))
    files = [Path(f) for f in args.files] or [folder / n for n in ("ax3_sample.cwa", "ax6_sample.cwa",
                                                                   "gnactv_sample.bin")]
    from gravcal.io.formats import isolated, wearables
    from gravcal.io.formats.sniff import sniff

    w, c = timed(lambda: __import__("skdh.io"), 1)
    print(f"import skdh.io in this process: {w:.2f} s wall, {c:.2f} s CPU")
    for f in files:
        found = sniff(f)
        here = timed(lambda: wearables.read_skdh_here(f, found), args.repeat)
        wearables.read_skdh(f, found)  # the child warm
        child = timed(lambda: wearables.read_skdh(f, found), args.repeat)

        def cold():
            isolated._CHILD.close()
            wearables.read_skdh(f, found)
        first = timed(cold, max(1, args.repeat // 2))
        n = wearables.read_skdh_here(f, found)[0]["t"].shape[0]
        print(f"{f.name}: {n} samples; in process {here[0] * 1e3:.1f} ms wall ({here[1] * 1e3:.1f} ms CPU), "
              f"warm child {child[0] * 1e3:.1f} ms wall ({child[1] * 1e3:.1f} ms CPU here), "
              f"fresh child {first[0]:.2f} s wall")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
