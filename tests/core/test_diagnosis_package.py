"""The package's lazy names are its functions whatever was imported first: no submodule of core.diagnosis
is named like a function the package exports (importing such a submodule binds its name over the function)."""
from __future__ import annotations

import pkgutil
import subprocess
import sys

import gravcal.core.diagnosis as diagnosis


def test_no_submodule_shadows_an_exported_name():
    submodules = {m.name for m in pkgutil.iter_modules(diagnosis.__path__)}
    assert not submodules & set(diagnosis.__all__), submodules & set(diagnosis.__all__)


def test_diagnose_is_the_function_after_every_submodule_was_imported():
    code = ("import importlib, pkgutil, types, gravcal.core.diagnosis as d\n"
            "for m in pkgutil.iter_modules(d.__path__): importlib.import_module('gravcal.core.diagnosis.' + m.name)\n"
            "from gravcal.core.diagnosis import diagnose, diagnose_windows\n"
            "assert callable(diagnose) and not isinstance(diagnose, types.ModuleType), diagnose\n"
            "assert callable(diagnose_windows)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
