"""The one sensor model: named terms, forward (simulator) and calibration-level view (estimators)."""
from .base import STAGES, TERM_REGISTRY, Context, SensorModel, Term, register, term_from_dict

__all__ = ["STAGES", "TERM_REGISTRY", "Context", "SensorModel", "Term", "register", "term_from_dict"]
