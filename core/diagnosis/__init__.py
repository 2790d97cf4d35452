"""Measured data against the simulation: diagnose what the baseline model gets wrong,
name the cause among the catalogue terms, extend the model and measure the held-out gain."""
from .diagnose import CATALOGUE, Diagnosis, diagnose, diagnose_windows

__all__ = ["CATALOGUE", "Diagnosis", "diagnose", "diagnose_windows"]
