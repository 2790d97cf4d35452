"""The functions ``gravcal.read`` and ``gravcal.calibrate`` and the ``gravcal.Calibration`` they give.

They run exactly what ``gravcal calibrate`` runs (daemon.offline), so a notebook and the command
line report the same numbers under the same keys.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from gravcal.core.calibration import Calibration as _CoreCalibration
from gravcal.core.calibration import jsonable
from gravcal.io import offline
from gravcal.io.recordings import Recording, read_recording, recording_from_arrays
from gravcal.jsonbounds import JSONInputError, loads

__all__ = ["read", "calibrate", "write_calibrated", "Calibration", "Recording"]


@dataclass
class Calibration(_CoreCalibration):
    """A calibration: ``offset`` (3,) [raw], ``sensitivity`` (3, 3) [raw per g], with
    a [g] = sensitivity^-1 (raw - offset) (plus any terms the model carries).

    ``apply(acc, temp=..., vsupply=...)`` -> g. ``report``: the ``gravcal calibrate --json`` object
    (held-out error, order, windows, input notes); its keys read as attributes too, e.g.
    ``cal.heldout_rms_mg``. ``to_json()`` writes the ``calibrate --save`` format with the report
    added (``--start`` accepts it); ``Calibration.from_json()`` reads either back.
    """

    report: dict[str, Any] = field(default_factory=dict, repr=False)

    @property
    def heldout_rms_mg(self) -> float | None:
        """RMS of |a| - 1 g on windows not used for the fit (contiguous folds) [mg]."""
        return self.report.get("heldout_rms_mg")

    @property
    def insample_rms_mg(self) -> float | None:
        return self.report.get("insample_rms_mg")

    @property
    def status(self) -> str:
        """The verdict: "ok" or "partial" (offsets only) to use; "not_improved" (the start is returned),
        "unreliable" or "refused" (the start is returned; nothing determined) not to (``gravcal calibrate``
        exits 3 for these). ``reason`` says why."""
        return str(self.report.get("status", "ok"))

    @property
    def reason(self) -> str:
        return str(self.report.get("reason", ""))

    def __getattr__(self, name: str) -> Any:
        report = self.__dict__.get("report") or {}
        if name in report:
            return report[name]
        raise AttributeError(f"'Calibration' has no attribute {name!r} (report keys: {', '.join(report) or 'none'})")

    def to_dict(self) -> dict[str, Any]:
        d = super().to_dict()
        if self.report:
            d["report"] = jsonable(self.report)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Calibration":
        cal = super().from_dict(d)
        cal.report = dict(d.get("report") or {})
        return cal

    def write(self, rec: "Recording | str | Path", path: str | Path) -> Path:
        """Write ``rec`` (a Recording or a path) calibrated by this calibration to ``path``: see
        :func:`write_calibrated`."""
        return write_calibrated(rec, self, path)

    @classmethod
    def from_json(cls, text: str | bytes) -> "Calibration":
        """A calibration from its JSON (``to_json``'s or ``calibrate --save``'s), its nesting and size bounded
        (gravcal.jsonbounds); ValueError with a one-line message when unusable."""
        d = loads(text)
        if not isinstance(d, dict):
            raise JSONInputError("calibration JSON must be an object")
        return cls.from_dict(d)

    @classmethod
    def _from_core(cls, core: _CoreCalibration, report: dict[str, Any]) -> "Calibration":
        return cls(**{f.name: getattr(core, f.name) for f in fields(_CoreCalibration)}, report=report)


def read(path: str | Path, *, columns: str | dict[str, str] | None = None, exclude_filler: bool = True,
         check_saturation: bool = True, progress: bool = False, blocks: bool = False) -> Recording:
    """Read and validate a recording (.csv, .csv.gz, .npy, .gt3x, .agdc, .cwa, .bin; recognised by content).

    Returns a Recording: ``t`` (N,) [s], ``acc`` (N, 3) in the file's raw ``units``, ``temp`` [°C] and
    ``vsupply`` [V] (None when absent), ``fs`` [Hz], ``metadata``, ``warnings``. ``columns`` maps other
    CSV names, e.g. ``{"t": "t_unix", "ax": "x_counts"}``; ``exclude_filler`` drops exactly repeated
    runs (idle sleep) and notes it in ``warnings``; ``progress=True`` shows a tqdm bar of the
    validation pass (tqdm installed: the ``study`` extra); ``blocks=True`` also keeps the block
    detector's statistics from the same pass (``Recording.blocks``, ~0.24x a 20-byte-sample file's
    size), which ``calibrate`` then uses instead of a second pass. Errors: ValueError with a
    one-line message.
    """
    with offline.progress_bar("reading", progress) as bar:
        return read_recording(path, columns=columns, exclude_filler=exclude_filler, check_saturation=check_saturation,
                              progress=bar, blocks=blocks)


def calibrate(data: Recording | str | Path | tuple, model: str = "auto", *, temp: Any = None, vsupply: Any = None,
              detector: str = "lotters", folds: int = 5, start: _CoreCalibration | None = None,
              columns: str | dict[str, str] | None = None, progress: bool = False) -> Calibration:
    """Calibrate a recording (a Recording, a path, or a tuple ``(t, acc)`` with t [s], acc (N, 3) raw).

    ``model``: "auto" (the largest order the windows determine), "offsets", "6", "9", "12" or an order
    with terms ("6+temperature_offset" style names from the registry). Raises ValueError when the
    recording is unusable input (the message says why). A readable recording always gets a verdict:
    check ``status`` ("ok", "partial", "not_improved", "unreliable", "refused") and ``reason`` before
    using the result, as ``gravcal calibrate`` does (exit 3 unless ok or partial). ``progress=True``:
    tqdm bars of the reading and of the calibration's block pass and stages.
    """
    opts = offline.Options(model=model, detector=detector, folds=folds, start=start, columns=columns)
    offline.check_options(opts)
    if isinstance(data, (str, Path)):
        rec = read(data, columns=columns, progress=progress, blocks=True)
    elif isinstance(data, Recording):
        rec = data
    elif isinstance(data, tuple) and len(data) == 2:
        rec = recording_from_arrays(data[0], data[1], temp=temp, vsupply=vsupply)
    else:
        raise TypeError(f"calibrate() takes a Recording, a path or a tuple (t, acc); got {type(data).__name__}")
    with offline.progress_bar("calibrating", progress) as bar:
        report, out = offline.calibrate(rec, opts, progress=bar)
    return Calibration._from_core(report.calibration, out)


def write_calibrated(rec: Recording | str | Path, cal: _CoreCalibration, path: str | Path, *,
                     columns: str | dict[str, str] | None = None) -> Path:
    """Write the calibrated samples of ``rec`` (a Recording, or the path of a recording) to ``path``, as
    ``gravcal calibrate REC --write OUT`` does: .npy, .csv, .csv.gz or .parquet by the ending; columns
    t [s], ax, ay, az [g] (``cal.apply`` with every term, at each sample's temperature and supply) and
    flags (core.samples.FLAG_SATURATED, io.recordings.FLAG_FILLER: rows excluded from the fit, kept
    here); the calibration in OUT.json (parquet: in its metadata). Every finite row of the file is
    written (read again with its saturated and filler rows kept when ``rec`` dropped some; a
    Recording made from arrays is written as it is). Returns the path written."""
    from gravcal.io.calibrated import write_calibrated as write, write_for

    report = jsonable(cal.report) if isinstance(cal, Calibration) else None
    if isinstance(rec, (str, Path)):
        return write(path, read_recording(rec, columns=columns, flag_only=True), cal, report)
    return write_for(path, rec, cal, columns=columns, report=report)
