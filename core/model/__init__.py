"""The one sensor model: named terms, forward (simulator) and calibration-level view (estimators).

Importing this package registers every term (``terms``: the ADXL210 pair's effects and the
ENC-03J path), so ``SensorModel.from_dict`` can rebuild any saved model. The default model and
the calibration-level truth are in ``defaults``.
"""
from .base import STAGES, TERM_REGISTRY, Context, SensorModel, Term, register, term_from_dict
from .stateful import StatefulTerm, reset_model
from .terms import CALIBRATION_TERMS, CATALOGUE, REGISTRY, term_spec

__all__ = ["STAGES", "TERM_REGISTRY", "Context", "SensorModel", "Term", "register", "term_from_dict",
           "StatefulTerm", "reset_model", "CALIBRATION_TERMS", "CATALOGUE", "REGISTRY", "term_spec"]
