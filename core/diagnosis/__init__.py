"""Measured data against the simulation: diagnose what the baseline model gets wrong,
name the cause among the catalogue terms, extend the model and measure the held-out gain."""
from __future__ import annotations

from typing import Any

__all__ = ["CATALOGUE", "Diagnosis", "diagnose", "diagnose_windows"]


def __getattr__(name: str) -> Any:
    # loaded on first use: `calibrate` imports the noise module (filler runs) alone, and diagnose
    # pulls in scipy.stats (~1 s of imports)
    if name in __all__:
        import importlib

        module = importlib.import_module(".procedure", __name__)
        # the functions live in .procedure, so no submodule shadows the function "diagnose"
        globals().update({n: getattr(module, n) for n in __all__})
        return globals()[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
