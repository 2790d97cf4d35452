"""Long coverage-guided runs of one fuzz target (fuzz_targets.py) under atheris (pip install 'gravcal[fuzz]')::

    python tests/fuzz/run.py NAME [libFuzzer options] [CORPUS_DIR ...]
    python tests/fuzz/run.py frame_decoder -runs=10000000 -print_final_stats=1 /tmp/fd-corpus

NAME is one of fuzz_targets.TARGETS. Without a corpus directory the seed corpus (tests/fuzz/corpus/NAME) is read;
give a scratch directory first to keep what the run finds without touching the repository. A crash is written
as crash-<sha1> in the working directory: copy it into tests/fuzz/corpus/NAME/ under a name that says what it
found, fix the code, and the suite's short run (test_fuzz_short.py) keeps it fixed.
"""
from __future__ import annotations

import sys
from pathlib import Path

import atheris

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE.parent)]

with atheris.instrument_imports(include=["gravcal"]):
    import fuzz_targets


def main() -> int:
    if len(sys.argv) < 2 or sys.argv[1] not in fuzz_targets.TARGETS:
        print(f"usage: {sys.argv[0]} NAME [libFuzzer options] [CORPUS_DIR ...]; NAME: "
              f"{', '.join(fuzz_targets.TARGETS)}", file=sys.stderr)
        return 2
    name, rest = sys.argv[1], sys.argv[2:]
    if not [a for a in rest if not a.startswith("-")]:
        rest.append(str(HERE / "corpus" / name))
    target = fuzz_targets.TARGETS[name]
    atheris.Setup([sys.argv[0], *rest], target)
    try:
        atheris.Fuzz()
    finally:
        fuzz_targets.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
