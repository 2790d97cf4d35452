"""gravcal.core: numerics only, no I/O.

Sample layout, ring buffer, the sensor model (forward: the simulator; inverted: the
estimators), motion scenarios, quasi-static detectors, estimators and diagnosis.
"""
