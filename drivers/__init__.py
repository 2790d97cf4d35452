"""gravcal.drivers: buses and framing only (serial, I2C, CAN).

``open_driver(spec)`` gives a :class:`Driver` for a URL-like spec, found by the spec's scheme
in ``base.DRIVER_SCHEMES``; ``codec.py`` is the shared frame format. The test rigs (emulator,
fake devices, HIL runner) are the subpackage ``rigs``, which no driver imports.
"""
from .base import Backoff, Driver, DriverError, open_driver, register_scheme

__all__ = ["Backoff", "Driver", "DriverError", "open_driver", "register_scheme"]
