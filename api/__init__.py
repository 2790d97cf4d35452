"""gravcal: in-use calibration of body-worn accelerometers from their quasi-static moments.

The Python API (docs/python-api.md)::

    import gravcal
    rec = gravcal.read("subject01.gt3x")          # t, acc (N, 3 raw), temp, vsupply, fs, units, metadata
    cal = gravcal.calibrate(rec)                  # offset (3), sensitivity (3x3), held-out error, report
    g = cal.apply(rec.acc, temp=rec.temp)         # calibrated acceleration [g]
    cal.write(rec, "subject01.calibrated.parquet")  # t, a [g], flags and the calibration, to a file

Attributes load on first use, so ``import gravcal`` (and the daemon, which imports
gravcal.daemon) pays for none of the numerics.
"""
from __future__ import annotations


__all__ = ["__version__", "read", "calibrate", "write_calibrated", "Calibration", "Recording", "study_report"]
_API = {"read", "calibrate", "write_calibrated", "Calibration", "Recording"}


def __getattr__(name: str) -> object:
    if name == "__version__":
        from ._version import __version__

        return __version__
    if name in _API:
        from . import api

        return getattr(api, name)
    if name == "study_report":
        from .io.study_report import write_report

        return write_report
    raise AttributeError(f"module 'gravcal' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
