"""`gravcal --version` answers before any command is imported (their imports load numpy, python-can and
the emulator rigs: 443 modules, 0.35 s), and still says the installed version."""
from __future__ import annotations

import subprocess
import sys
from importlib.metadata import version

CODE = """
import sys
sys.argv = ["gravcal"] + sys.argv[1:]
import gravcal.cli.main as m
try:
    m.console()
except SystemExit as exc:
    code = exc.code
heavy = sorted(k for k in sys.modules if k.split(".")[0] in ("numpy", "scipy", "can", "serial")
               or k.startswith(("gravcal.cli.cmd_", "gravcal.drivers", "gravcal.core", "gravcal.io")))
print(code, len(sys.modules), heavy, file=sys.stderr)
"""


def run(*args):
    r = subprocess.run([sys.executable, "-c", CODE, *args], capture_output=True, text=True, timeout=60)
    code, n, heavy = r.stderr.strip().splitlines()[-1].split(" ", 2)
    return r.stdout, int(code), int(n), heavy


def test_version_imports_no_command():
    out, code, n, heavy = run("--version")
    assert out.strip() == f"gravcal {version('gravcal')}" and code == 0
    assert heavy == "[]" and n < 200, (n, heavy)
    out, code, n, heavy = run("-v", "--version")
    assert out.strip().startswith("gravcal ") and heavy == "[]"


def test_version_after_a_command_word_is_that_commands_business():
    out, code, _, heavy = run("calibrate", "--version")  # not a calibrate option: argparse refuses it
    assert code == 2 and "gravcal.cli.cmd_calibrate" in heavy
