"""Compiled kernels as accelerators: each offline kernel module (``_name``, a C extension) has its
numpy reference (``_name_reference``) beside it, which computes the same quantities.

``kernels("gravcal.core._fitsums")`` returns the compiled module when it was built and the environment
does not say ``GRAVCAL_NATIVE=0``, else the reference: an install without a C compiler calibrates, and the
tests run both forms. A compiled module that exists but fails to load is an error, not a fallback.
"""
from __future__ import annotations

import importlib
import os
from types import ModuleType

ENV = "GRAVCAL_NATIVE"


def native_wanted() -> bool:
    """False when the environment forces the numpy references (GRAVCAL_NATIVE=0, no, false or off)."""
    return os.environ.get(ENV, "1").strip().lower() not in ("0", "no", "false", "off")


def kernels(name: str) -> ModuleType:
    """The compiled module ``name`` or, when it is absent or not wanted, ``name + "_reference"``."""
    if native_wanted():
        try:
            return importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:  # something the extension itself needs: a real error
                raise
    return importlib.import_module(name + "_reference")


def is_native(module: ModuleType) -> bool:
    """True for a compiled kernel module, False for its numpy reference."""
    return not module.__name__.endswith("_reference")
