"""The one sensor model: named terms, forward (simulator) and calibration-level view (estimators).

The registry (``terms``: the ADXL210 pair's effects and the ENC-03J path) lists every term once;
``SensorModel.from_dict`` rebuilds any saved model from it. The default model and
the calibration-level truth are in ``defaults``.
"""
from .base import STAGES, Context, Term
from .sensor_model import SensorModel
from .stateful import StatefulTerm, reset_model
from .terms import CALIBRATION_TERMS, CATALOGUE, REGISTRY, term_from_dict, term_spec

__all__ = ["STAGES", "Context", "SensorModel", "Term", "term_from_dict",
           "StatefulTerm", "reset_model", "CALIBRATION_TERMS", "CATALOGUE", "REGISTRY", "term_spec"]
