"""Drivers are found by the spec's scheme in one table; the real drivers never import the test rigs."""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

import gravcal.drivers as drivers_pkg
from gravcal.drivers import DriverError, open_driver, register_scheme
from gravcal.drivers.base import DRIVER_SCHEMES, Driver, driver_class
from tests.support.child import run_child

DRIVERS_DIR = Path(drivers_pkg.__file__).resolve().parent
RIGS = "gravcal.drivers.rigs"


def _imported_modules(path: Path, package: str = "gravcal.drivers") -> list[tuple[int, str]]:
    """Absolute names of every module ``path`` (a module of ``package``) imports, at any depth
    (function-level too)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module or ""
            out.append((node.lineno, module))
            out += [(node.lineno, f"{module}.{alias.name}") for alias in node.names]  # from . import rigs
    return out


def test_real_drivers_never_import_the_rigs():
    real = sorted(p for p in DRIVERS_DIR.glob("*.py"))
    names = {p.stem for p in real}
    assert {"base", "codec", "serial", "can", "i2c"} <= names
    offenders = [f"{p.name}:{line} imports {mod}" for p in real for line, mod in _imported_modules(p)
                 if mod == RIGS or mod.startswith(RIGS + ".") or mod.endswith(".rigs")]
    assert offenders == []


def test_no_driver_or_rig_knows_the_daemon():
    from gravcal.drivers.rigs import hil

    offenders = []
    for p in sorted(DRIVERS_DIR.rglob("*.py")):
        package = "gravcal.drivers" + ("" if p.parent == DRIVERS_DIR else ".rigs")
        offenders += [f"{p.name}:{line} imports {mod}" for line, mod in _imported_modules(p, package)
                      if mod.startswith("gravcal.daemon")]
    assert offenders == []
    assert hil.EMULATOR_MODULE == "gravcal.drivers.rigs.emulate"  # the HIL runner starts the rig's entry point


def test_import_checker_sees_relative_and_function_level_imports(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    from .rigs.fake_i2c import FakeSMBus\n"
                   "from . import rigs\nimport gravcal.drivers.rigs.hil\n")
    mods = [m for _, m in _imported_modules(bad)]
    assert "gravcal.drivers.rigs.fake_i2c" in mods
    assert "gravcal.drivers.rigs" in mods
    assert "gravcal.drivers.rigs.hil" in mods


def test_opening_real_drivers_loads_no_rig():
    code = ("import sys\n"
            "from gravcal.drivers import open_driver, DriverError\n"
            "import gravcal.drivers.serial, gravcal.drivers.can, gravcal.drivers.i2c, gravcal.drivers.codec\n"
            "d = open_driver('serial:loop://', open=True); d.close()\n"
            "print(sorted(m for m in sys.modules if m.startswith('gravcal.drivers.rigs')))\n")
    assert run_child(code, timeout=120, what="opening the real drivers").strip() == "[]"


def test_fake_i2c_scheme_imports_its_rig_on_first_use():
    code = ("import sys\n"
            "from gravcal.drivers import open_driver\n"
            "before = 'gravcal.drivers.rigs.fake_i2c' in sys.modules\n"
            "d = open_driver('fake-i2c://0x42?scenario=pattern&fs=200', open=False)\n"
            "print(before, 'gravcal.drivers.rigs.fake_i2c' in sys.modules, type(d).__name__, d.description)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["False", "True", "FakeI2CDriver", "fake@0x42"]


def test_known_schemes_resolve_to_driver_classes():
    assert {"serial", "can", "i2c", "fake-i2c"} <= set(DRIVER_SCHEMES)
    for scheme in ("serial", "can", "i2c", "fake-i2c"):
        cls = driver_class(scheme)
        assert issubclass(cls, Driver) and callable(cls.from_spec)
    assert driver_class("SERIAL").__name__ == "SerialDriver"  # schemes are case-insensitive, like URLs
    assert open_driver("/dev/ttyGRAVCAL_NOPE", open=False).port == "/dev/ttyGRAVCAL_NOPE"  # bare path: serial


def test_unknown_scheme_lists_the_known_ones():
    with pytest.raises(DriverError) as e:
        open_driver("usb://bus/1")
    msg = str(e.value)
    assert "unknown bus 'usb'" in msg and "'usb://bus/1'" in msg
    assert "can, fake-i2c, i2c, serial" in msg
    with pytest.raises(DriverError, match="has no scheme; use one of can:, fake-i2c:, i2c:, serial:"):
        open_driver("ttyUSB0")


def test_fake_i2c_bad_address_and_option():
    with pytest.raises(DriverError, match="fake I2C address 'x42' is not a number"):
        open_driver("fake-i2c://x42", open=False)
    with pytest.raises(DriverError, match="unknown option 'rate' for fake-i2c driver; known: .*scenario"):
        open_driver("fake-i2c://0x42?rate=200", open=False)
    with pytest.raises(DriverError, match="unknown scenario 'nope'"):
        open_driver("fake-i2c://0x42?scenario=nope", open=False)


def test_registered_scheme_is_used_and_bad_entries_are_refused(monkeypatch):
    monkeypatch.setitem(DRIVER_SCHEMES, "loopback", ("gravcal.drivers.serial", "SerialDriver"))
    assert type(open_driver("loopback:loop://", open=False)).__name__ == "SerialDriver"
    register_scheme("Mine+x", "gravcal.drivers.serial", "NoSuchDriver")
    try:
        with pytest.raises(DriverError, match="gravcal.drivers.serial has no NoSuchDriver"):
            open_driver("mine+x://a")
    finally:
        del DRIVER_SCHEMES["mine+x"]
    with pytest.raises(ValueError, match="not a URL scheme"):
        register_scheme("1bad", "m", "C")
