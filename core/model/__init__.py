"""The one sensor model: named terms, forward (simulator) and calibration-level view (estimators).

Importing this package registers every term (ADXL210 pair, ENC-03J), so ``SensorModel.from_dict``
can rebuild any saved model.
"""
from . import adxl210, enc03j  # noqa: F401  (registers the terms)
from .base import STAGES, TERM_REGISTRY, Context, SensorModel, Term, register, term_from_dict
from .defaults import CATALOGUE, default_model, triad_truth
from .stateful import StatefulTerm, reset_model

__all__ = ["STAGES", "TERM_REGISTRY", "Context", "SensorModel", "Term", "register", "term_from_dict",
           "CATALOGUE", "default_model", "triad_truth", "StatefulTerm", "reset_model"]
