"""A calibration result: a saveable object with its metadata (imucal's style).

Convention (the same everywhere in gravcal, and in ``gravcal calibrate --json``)::

    raw = sensitivity @ a + offset          a in g, raw in the recording's raw units
    a   = sensitivity^-1 (raw - offset)

``sensitivity`` is 3x3 (diagonal for the 6-parameter model), in raw units per g;
``offset`` in raw units. ``covariance`` is over the estimated parameters named in
``param_names``, in the same raw units; parameters held fixed have no entry.

An extended calibration (model ``"<order>+<term>..."``, e.g. ``"6+temperature_offset"``) holds K and
o at reference conditions and, in ``metadata``, the parameters of its terms (``params``) and their
references (``extended``); :meth:`Calibration.apply` applies every term at each sample's covariates.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .model.effect import apply_terms, needed_covariates, references
from .model.terms import CALIBRATION_TERMS, COVARIATES, calibration_view

SCHEMA = "gravcal.calibration/1"


@dataclass
class Calibration:
    model: str
    offset: np.ndarray
    sensitivity: np.ndarray
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    param_names: list[str] = field(default_factory=list)
    n_windows: int = 0
    converged: bool = True
    observable: bool = True
    message: str = ""
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.offset = np.asarray(self.offset, dtype=float).reshape(3)
        self.sensitivity = np.asarray(self.sensitivity, dtype=float).reshape(3, 3)
        self.covariance = np.asarray(self.covariance, dtype=float)
        if self.covariance.size == 0:
            self.covariance = np.zeros((len(self.param_names), len(self.param_names)))

    # -- use -------------------------------------------------------------------------
    def apply(self, raw: np.ndarray, *, temp: Any = None, vsupply: Any = None, t: Any = None) -> np.ndarray:
        """Calibrated acceleration [g] from raw triad rows (N, 3) or one row (3,), with every term the
        calibration carries applied at each row's covariates: ``temp`` [°C], ``vsupply`` [V], ``t`` [s]
        (arrays of N or scalars; only those its terms need). A covariate the terms need and not given
        is an error naming it: applying the reference K, o alone would silently drop the terms."""
        terms = self.extended_terms
        if not terms:
            return self.apply_reference(raw)
        given = {"temp": temp, "vsupply": vsupply, "time": t}
        missing = [c for c in needed_covariates(terms) if given[c] is None]
        if missing:
            raise ValueError(f"calibration {self.model} needs the {' and '.join(COVARIATES[c].label for c in missing)} of each sample "
                             f"(its terms: {', '.join(terms)})")
        raw = np.asarray(raw, dtype=float)
        params = self.metadata.get("params") or {}
        extra = np.array([float(params[n]) for n in self.extended_param_names])
        a = apply_terms(self.sensitivity, self.offset, terms, extra, raw.reshape(-1, 3), given,
                        references(self.metadata["extended"]))
        return a.reshape(raw.shape)

    def apply_reference(self, raw: np.ndarray) -> np.ndarray:
        """K^-1 (raw - o) at the reference conditions [g]: for directions (postures, coverage), where
        the terms' small changes do not matter; a plain calibration's whole correction."""
        raw = np.asarray(raw, dtype=float)
        return np.linalg.solve(self.sensitivity, (raw - self.offset).T).T

    @property
    def extended_metadata(self) -> dict[str, Any] | None:
        """``metadata['extended']`` of an extended calibration (its terms, references), None for a plain one;
        a calibration named after an extended model without it is refused."""
        ext = self.metadata.get("extended") if isinstance(self.metadata, dict) else None
        if not ext:
            if "+" in str(self.model):
                raise ValueError(f"calibration of extended model {self.model!r} carries no metadata['extended'] "
                                 f"(its terms' parameters are unknown): re-fit it")
            return None
        return ext

    @property
    def extended_terms(self) -> tuple[str, ...]:
        """The terms an extended calibration carries (empty for a plain one); a calibration named after an
        extended model without its terms' parameters is refused."""
        ext = self.extended_metadata
        return tuple(ext.get("terms", ())) if ext else ()

    @property
    def extended_param_names(self) -> list[str]:
        """Names of the terms' parameters in ``metadata['params']`` (3 per term, in term order)."""
        names = [n for t in self.extended_terms for n in calibration_view(t).param_names()]
        params = self.metadata.get("params") or {}
        missing = [n for n in names if n not in params]
        if missing:
            raise ValueError(f"calibration {self.model!r}: metadata['params'] lacks {missing}: cannot apply its terms")
        return names

    @property
    def std(self) -> dict[str, float]:
        d = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        return {name: float(s) for name, s in zip(self.param_names, d)}

    # -- persistence -----------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "schema": SCHEMA,
            "model": self.model,
            "offset": self.offset.tolist(),
            "sensitivity": self.sensitivity.tolist(),
            "param_names": list(self.param_names),
            "covariance": self.covariance.tolist(),
            "std": self.std,
            "n_windows": int(self.n_windows),
            "converged": bool(self.converged),
            "observable": bool(self.observable),
            "message": self.message,
            "metadata": jsonable(self.metadata),
        }

    def to_json(self, **kwargs: Any) -> str:
        return json.dumps(self.to_dict(), **kwargs)

    @classmethod
    def from_dict(cls, d: Any) -> "Calibration":
        if not isinstance(d, dict):  # a state file's "calibration" may hold anything a hand or a fault wrote
            raise ValueError(f"a calibration must be a JSON object, got {type(d).__name__}")
        if d.get("schema") != SCHEMA:
            raise ValueError(f"not a gravcal calibration (schema {d.get('schema')!r}, expected {SCHEMA!r})")
        try:
            cal = cls(
                model=str(d["model"]),
                offset=np.asarray(d["offset"], dtype=float),
                sensitivity=np.asarray(d["sensitivity"], dtype=float),
                covariance=np.asarray(d.get("covariance", []), dtype=float),
                param_names=list(d.get("param_names", [])),
                n_windows=int(d.get("n_windows", 0)),
                converged=bool(d.get("converged", True)),
                observable=bool(d.get("observable", True)),
                message=str(d.get("message", "")),
                metadata=dict(d.get("metadata", {})),
            )
        except (KeyError, ValueError, TypeError) as exc:
            raise ValueError(f"malformed calibration: {exc}") from exc
        unknown = [t for t in cal.model.split("+")[1:] if t not in CALIBRATION_TERMS]
        if unknown:  # a file from another version, or edited by hand
            raise ValueError(f"calibration model {cal.model!r}: unknown term(s) {unknown}; known: {list(CALIBRATION_TERMS)}")
        if not (np.all(np.isfinite(cal.offset)) and np.all(np.isfinite(cal.sensitivity))):
            raise ValueError("malformed calibration: non-finite offset or sensitivity")
        if abs(np.linalg.det(cal.sensitivity)) < 1e-300:
            raise ValueError("malformed calibration: singular sensitivity matrix")
        n = len(cal.param_names)
        if cal.covariance.shape != (n, n):
            raise ValueError(f"malformed calibration: covariance shape {cal.covariance.shape} != ({n}, {n})")
        return cal

    @classmethod
    def from_json(cls, text: str) -> "Calibration":
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"calibration is not valid JSON: {exc}") from exc
        if not isinstance(d, dict):
            raise ValueError("calibration JSON must be an object")
        return cls.from_dict(d)

    @classmethod
    def nominal(cls, offset: np.ndarray, sensitivity: np.ndarray | float, model: str = "nominal") -> "Calibration":
        """A calibration from datasheet values, with no data behind it."""
        s = np.asarray(sensitivity, dtype=float)
        k = np.diag(np.broadcast_to(s, (3,))) if s.ndim < 2 else s
        return cls(model=model, offset=offset, sensitivity=k, n_windows=0, message="nominal (datasheet) values")


def jsonable(x: Any) -> Any:
    """``x`` with numpy types as Python ones and non-finite floats as None (strict JSON has no NaN)."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, np.generic):
        return x.item()
    return x
