"""Long coverage-guided runs of one fuzz target (fuzz_targets.py) under atheris (pip install 'gravcal[fuzz]')::

    python tests/fuzz/run.py NAME [libFuzzer options] [CORPUS_DIR ...]
    python tests/fuzz/run.py frame_decoder -runs=10000000 -print_final_stats=1 /tmp/fd-corpus \
        tests/fuzz/corpus/frame_decoder
    python tests/fuzz/run.py NAME --replay DIR_OR_FILE ...

NAME is one of fuzz_targets.TARGETS. libFuzzer adds what it finds to the first directory given: give a scratch
one, then the seed corpus (tests/fuzz/corpus/NAME); given none, a temporary directory and the seed corpus are
used. A crash is written as crash-<sha1> in the working directory: copy it into tests/fuzz/corpus/NAME/ under a
name that says what it found, fix the code, and the suite's short run (test_fuzz_short.py) keeps it fixed.

--replay runs every input once through the target, uninstrumented, and lists those that fail: how the corpus a
native harness grew (native/, C kernels only) is checked against the Python reference.
"""
from __future__ import annotations

import logging
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE.parent)]


def replay(name: str, paths: list[str]) -> int:
    import fuzz_targets

    logging.getLogger("gravcal").setLevel(logging.CRITICAL)  # each moved-aside state file logs a warning
    if name not in fuzz_targets.TARGETS:
        print(f"unknown target {name!r}; one of {', '.join(fuzz_targets.TARGETS)}", file=sys.stderr)
        return 2
    files = [f for p in map(Path, paths) for f in (sorted(p.iterdir()) if p.is_dir() else [p])]
    failed = 0
    try:
        for f in files:
            try:
                fuzz_targets.TARGETS[name](f.read_bytes())
            except Exception as exc:  # noqa: BLE001 - every failure is listed, then counted
                failed += 1
                print(f"{f}: {type(exc).__name__}: {str(exc)[:300]}")
    finally:
        fuzz_targets.cleanup()
    print(f"{name}: {len(files)} inputs replayed, {failed} failed")
    return 1 if failed else 0


def main() -> int:
    name, rest = (sys.argv[1], sys.argv[2:]) if len(sys.argv) > 1 else ("", [])
    if rest[:1] == ["--replay"]:
        return replay(name, rest[1:])
    import atheris

    with atheris.instrument_imports(include=["gravcal"]):  # before anything imports gravcal uninstrumented
        import fuzz_targets
    if name not in fuzz_targets.TARGETS:
        print(f"usage: {sys.argv[0]} NAME [libFuzzer options] [CORPUS_DIR ...] | NAME --replay PATH ...; "
              f"NAME: {', '.join(fuzz_targets.TARGETS)}", file=sys.stderr)
        return 2
    if not [a for a in rest if not a.startswith("-")]:  # libFuzzer writes what it finds into the first directory
        rest += [tempfile.mkdtemp(prefix=f"gravcal-fuzz-{name}-"), str(HERE / "corpus" / name)]
        print(f"corpus found: {rest[-2]}", file=sys.stderr)
    atheris.Setup([sys.argv[0], *rest], fuzz_targets.TARGETS[name])
    try:
        atheris.Fuzz()
    finally:
        fuzz_targets.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
