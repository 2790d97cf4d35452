"""A sensor model: an ordered set of terms, run in the order the registry's forward chain gives."""
from __future__ import annotations

from typing import Any

import numpy as np

from .base import Context, Term
from .terms import FORWARD_POSITION, term_from_dict


class SensorModel:
    """An ordered collection of terms, at most one per name."""

    def __init__(self, terms: list[Term]):
        names = [t.name for t in terms]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"sensor model has duplicate terms: {sorted(dup)}")
        unknown = [t.name for t in terms if FORWARD_POSITION.get(t.name) is None]
        if unknown:
            raise ValueError(f"sensor model has unregistered terms {unknown}; registered: "
                             f"{', '.join(FORWARD_POSITION)}")
        self.terms: list[Term] = sorted(terms, key=lambda t: FORWARD_POSITION[t.name])

    def __contains__(self, name: str) -> bool:
        return any(t.name == name for t in self.terms)

    def __getitem__(self, name: str) -> Term:
        for t in self.terms:
            if t.name == name:
                return t
        raise KeyError(f"sensor model has no term {name!r}; it has {[t.name for t in self.terms]}")

    def with_term(self, term: Term) -> "SensorModel":
        """A new model with ``term`` added, replacing any term of the same name."""
        return SensorModel([t for t in self.terms if t.name != term.name] + [term])

    def without(self, name: str) -> "SensorModel":
        return SensorModel([t for t in self.terms if t.name != name])

    def stage_terms(self, stage: str) -> list[Term]:
        return [t for t in self.terms if t.stage == stage]

    def run_stage(self, stage: str, x: np.ndarray, ctx: Context) -> np.ndarray:
        for term in self.stage_terms(stage):
            x = term.forward(x, ctx)
        return x

    def to_dict(self) -> dict[str, Any]:
        return {"terms": [t.to_dict() for t in self.terms]}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "SensorModel":
        return cls([term_from_dict(t) for t in d["terms"]])

    def __repr__(self) -> str:
        return "SensorModel(\n  " + ",\n  ".join(repr(t) for t in self.terms) + "\n)"
