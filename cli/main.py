"""The ``gravcal`` command line: argparse with one module per subcommand.

Each subcommand lives in ``cli/cmd_<name>.py`` and exposes ``add_parser(subparsers)``
and ``run(args) -> int``; only the command named is imported. ``gravcal --help`` lists them
with their lines from cli/summaries.py and imports none.

Exit status: 0 ok, 1 internal error, 2 bad input (one line ``gravcal: error: ...`` on
stderr), 3 calibration computed but not trustworthy (not converged / not observable),
130 interrupted. ``--debug`` shows the traceback of any error.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import os
import pkgutil
import sys
import traceback
from pathlib import Path
from typing import Sequence

from .._version import __version__
from ..closed_pipe import write_or_stop
from ..errors import GravcalError, InputError
from .summaries import SUMMARIES

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_BAD_INPUT = 2
EXIT_NOT_TRUSTWORTHY = 3
EXIT_INTERRUPTED = 130

COMMANDS = ("demo", "simulate", "calibrate", "reproduce", "emulate", "watch")
"""--help order of the known subcommands; any other cli/cmd_<name>.py is listed after them,
and a module that is not there (yet) is skipped."""

log = logging.getLogger("gravcal")
_UNAVAILABLE: dict[str, str] = {}  # subcommand -> why it could not be loaded
_PROMPT_EXIT = [False]  # set by a command that has written its output and closed what it opened
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS", "OMP_NUM_THREADS")
"""What OpenBLAS reads for its thread count at load (in this order); a user's setting of any is kept."""
SINGLE_BLAS_COMMANDS = ("calibrate",)
"""Commands whose BLAS products are all small (core.pipeline runs them with one BLAS thread anyway)."""


def request_prompt_exit() -> None:
    """Let the program (``console``, not an in-process caller of ``main``) end without tearing the
    interpreter down: a command calls it once its results are written and its files closed. The
    teardown frees every array and module one by one (~0.05 s after a week's calibration); the
    kernel releases the memory at exit anyway."""
    _PROMPT_EXIT[0] = True


class _VersionAction(argparse.Action):
    def __init__(self, option_strings: Sequence[str], dest: str = argparse.SUPPRESS, **kwargs: object) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help="show the version and exit")

    def __call__(self, parser: argparse.ArgumentParser, *args: object) -> None:
        write_or_stop(f"gravcal {__version__}")
        parser.exit()


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The parser; with ``argv`` naming a subcommand, only that subcommand's module is imported. A command
    line without one (``gravcal --help``, no command, a typo) lists every subcommand with its line from
    cli/summaries.py and imports none: their imports load numpy, python-can and the emulator rigs (~1 s).
    Without ``argv``: the whole parser, every subcommand's module imported."""
    parser = argparse.ArgumentParser(
        prog="gravcal",
        description="In-use calibration of body-worn accelerometers from quasi-static moments (Lötters et al. 1998).",
        epilog="Exit status: 0 ok, 2 bad input, 3 calibration not trustworthy (flags in the output), 1 internal error.",
    )
    parser.add_argument("--version", action=_VersionAction)
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-v info, -vv debug)")
    parser.add_argument("--debug", action="store_true", help="show the traceback of any error")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    names = _command_names(argv)
    if argv is not None and (len(names) != 1 or names[0] != _first_word(argv)):
        for name in names:  # a listing: nothing imported
            sub.add_parser(name, help=SUMMARIES.get(name, ""))
        return parser
    for name in names:
        module_name = f"gravcal.cli.cmd_{name.replace('-', '_')}"
        try:
            module = importlib.import_module(module_name)
        except ImportError as exc:
            if getattr(exc, "name", "") != module_name:
                # present but broken (e.g. an optional dependency missing): the other
                # subcommands must keep working; say why this one is absent.
                _UNAVAILABLE[name] = f"{type(exc).__name__}: {exc}"
            continue
        sp = module.add_parser(sub)
        sp.set_defaults(_run=module.run)
    return parser


def _first_word(argv: Sequence[str] | None) -> str | None:
    words = [a for a in (argv or ()) if not a.startswith("-")]
    return words[0] if words else None


def _commands_dir() -> Path:
    return Path(__file__).resolve().parent


def _command_names(argv: Sequence[str] | None = None) -> list[str]:
    here = _commands_dir()
    word = _first_word(argv)
    if word and (here / f"cmd_{word.replace('-', '_')}.py").is_file():
        return [word]  # listing the package (pkgutil, inspect: ~15 ms) only for a listing or a typo
    # cmd_daemon_demo.py is the command daemon-demo
    found = sorted(m.name[4:].replace("_", "-") for m in pkgutil.iter_modules([str(here)]) if m.name.startswith("cmd_"))
    if not found:  # argparse would say "invalid choice (choose from )": say what is wrong instead
        unreadable = not os.access(here, os.R_OK | os.X_OK)
        raise GravcalError(f"no gravcal commands found in {here}" + (
            f": the directory is not readable by this user (uid {os.getuid()}); install gravcal where it can read it"
            if unreadable else ""))
    names = [c for c in COMMANDS if c in found] + [c for c in found if c not in COMMANDS]
    if word in names:
        return [word]
    return names


def _setup_logging(verbosity: int) -> None:
    level = logging.WARNING if verbosity <= 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("gravcal: %(levelname)s: %(message)s"))
    root = logging.getLogger()
    # In-process callers (tests) may call main() many times: replace our handler, keep theirs.
    for h in list(root.handlers):
        if getattr(h, "_gravcal", False):
            root.removeHandler(h)
    handler._gravcal = True  # type: ignore[attr-defined]
    root.addHandler(handler)
    root.setLevel(level)


def _error(msg: str) -> None:
    # One line, always: a message spanning lines would read as a traceback.
    print(f"gravcal: error: {' '.join(str(msg).split())}", file=sys.stderr)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point (``gravcal``). Returns the exit status instead of raising SystemExit
    for the program's own outcomes; argparse usage errors still exit with status 2."""
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        parser = build_parser(argv)
    except GravcalError as exc:
        _error(exc)
        return EXIT_INTERNAL
    args = parser.parse_args(argv)
    _setup_logging(args.verbose)
    for name, why in _UNAVAILABLE.items():
        log.info("subcommand %r unavailable: %s", name, why)
    if not getattr(args, "_run", None):
        parser.print_help(sys.stderr)
        return EXIT_BAD_INPUT
    try:
        return int(args._run(args))
    except KeyboardInterrupt:
        print("gravcal: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # e.g. `gravcal demo | head`
        return EXIT_OK
    except (InputError, ValueError, FileNotFoundError, IsADirectoryError, PermissionError) as exc:
        if args.debug:
            traceback.print_exc()
        _error(exc)
        return EXIT_BAD_INPUT
    except (GravcalError, OSError) as exc:
        if args.debug:
            traceback.print_exc()
        _error(exc)
        return EXIT_INTERNAL
    except Exception as exc:  # noqa: BLE001 - the user gets one line; --debug gives the traceback
        if args.debug:
            traceback.print_exc()
        _error(f"internal error: {type(exc).__name__}: {exc} (run with --debug for the traceback)")
        return EXIT_INTERNAL


def pin_blas_threads(argv: Sequence[str]) -> bool:
    """For a command of SINGLE_BLAS_COMMANDS, set OPENBLAS_NUM_THREADS=1 before numpy loads, unless the
    user set one of BLAS_THREAD_VARIABLES or numpy is already loaded (the setting would come too late).
    OpenBLAS otherwise starts a worker per core whose spinning takes core time from the reading pass's
    threads; child processes (a study's local Dask workers) inherit the setting. True when it was set."""
    words = [a for a in argv if not a.startswith("-")]
    if not words or words[0] not in SINGLE_BLAS_COMMANDS or "numpy" in sys.modules:
        return False
    if any(v in os.environ for v in BLAS_THREAD_VARIABLES):
        return False
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    return True


def console() -> None:
    """The ``gravcal`` program: ``main()``, then the exit status; after a command that asked for it
    (request_prompt_exit), the standard streams and log handlers are flushed and the process ends
    at once (os._exit: no atexit handlers, no teardown). ``gravcal calibrate`` runs with one OpenBLAS
    thread (pin_blas_threads), and the memory of its file's block statistics is faulted in while the
    imports run (io/prestart.py); ``main()`` called in-process does neither. The installed program
    enters through cli/launch.py, which answers ``gravcal --version`` before this module is imported."""
    pin_blas_threads(sys.argv[1:])
    from ..io import prestart

    prestart.start(sys.argv[1:])  # before numpy loads: one core is idle while the interpreter imports
    status = main()
    if _PROMPT_EXIT[0]:
        logging.shutdown()
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):  # a closed pipe or stream: nothing more can reach it
                pass
        os._exit(status)
    sys.exit(status)


if __name__ == "__main__":  # pragma: no cover
    from gravcal.cli.main import console as _console  # the package's module: the one whose flag commands set

    _console()
