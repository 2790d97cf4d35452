"""`gravcal --version` answers before the command line is imported: the installed console script loads
nothing beyond a bare interpreter but gravcal's launcher and its version constant (the commands' imports
load numpy, python-can and the emulator rigs; cli/main.py's own argparse, logging and traceback ~25 ms;
importlib.metadata ~15 ms), and still says the installed version."""
from __future__ import annotations

import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest

SCRIPT = Path(sys.executable).parent / "gravcal"  # the console script pip generated beside this Python
LAUNCHER = {"gravcal", "gravcal._version", "gravcal.cli", "gravcal.cli.launch", "gravcal.closed_pipe"}


def imported(*args: str) -> tuple[subprocess.CompletedProcess, set[str]]:
    """The run and the modules it imported (-X importtime names every module the first time it loads)."""
    r = subprocess.run([sys.executable, "-X", "importtime", *args], capture_output=True, text=True, timeout=60)
    names = {line.rsplit("|", 1)[1].strip() for line in r.stderr.splitlines() if line.startswith("import time:")}
    return r, names - {"package"}  # the header line's column title


@pytest.mark.skipif(not SCRIPT.is_file(), reason="gravcal is not installed as a console script here")
def test_console_script_version_imports_only_the_launcher():
    _, bare = imported("-c", "pass")
    r, names = imported(str(SCRIPT), "--version")
    assert r.returncode == 0 and r.stdout.strip() == f"gravcal {version('gravcal')}"
    assert names - bare <= LAUNCHER, sorted(names - bare - LAUNCHER)
    r, names = imported(str(SCRIPT), "-v", "--version")
    assert r.stdout.strip() == f"gravcal {version('gravcal')}" and names - bare <= LAUNCHER


AFTER = """
import sys
sys.argv = ["gravcal", "calibrate", "--version"]
from gravcal.cli.launch import console
try:
    console()
finally:
    print("gravcal.cli.cmd_calibrate" in sys.modules, file=sys.stderr)
"""


def test_version_after_a_command_word_is_that_commands_business():
    r = subprocess.run([sys.executable, "-c", AFTER], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.split()[-1] == "True"  # not a calibrate option: argparse refuses it


@pytest.mark.skipif(not SCRIPT.is_file(), reason="gravcal is not installed as a console script here")
def test_help_lists_every_command_without_importing_one():
    """`gravcal --help` lists each cli/cmd_*.py's command with the line its own parser gives (cli/summaries.py),
    and imports no command module, numpy or python-can."""
    import argparse
    import importlib
    import pkgutil

    import gravcal.cli as cli

    r, names = imported(str(SCRIPT), "--help")
    assert r.returncode == 0
    heavy = sorted(n for n in names if n.split(".")[0] in ("numpy", "scipy", "can", "serial")
                   or n.startswith(("gravcal.cli.cmd_", "gravcal.core", "gravcal.drivers")))
    assert heavy == [], heavy
    listing = " ".join(r.stdout.split())
    for m in pkgutil.iter_modules(cli.__path__):
        if not m.name.startswith("cmd_"):
            continue
        sub = argparse.ArgumentParser().add_subparsers()
        importlib.import_module(f"gravcal.cli.{m.name}").add_parser(sub)
        (action,) = sub._choices_actions
        assert action.help and f"{action.dest} {' '.join(action.help.split())}" in listing, (m.name, action.help)
