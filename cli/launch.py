"""The ``gravcal`` program's entry point (pyproject.toml's console script).

It answers ``gravcal --version`` from a constant before importing the command line: cli/main.py's own
imports (argparse, logging, traceback, pathlib) cost ~25 ms, importlib.metadata ~15 ms more, against a
bare interpreter's ~50 ms. Everything else goes to cli/main.py's ``console``."""
import sys


def asks_version(argv: list[str]) -> bool:
    """``--version`` among the options before any command word (after one it is that command's option)."""
    for a in argv:
        if a == "--version":
            return True
        if not a.startswith("-") or a in ("-h", "--help"):
            return False
    return False


def console() -> None:
    if asks_version(sys.argv[1:]):
        from .._version import __version__
        from ..closed_pipe import write_or_stop

        write_or_stop(f"gravcal {__version__}")
        sys.exit(0)
    from .main import console as run_command

    run_command()
