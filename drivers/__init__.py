"""gravcal.drivers: buses and framing only (serial, I2C, CAN), their fakes and the emulator.

``open_driver(spec)`` gives a :class:`Driver` for a URL-like spec (see ``base.py``);
``codec.py`` is the shared frame format, ``emulator.py``/``fakes.py`` the HIL rig.
"""
from .base import Backoff, Driver, DriverError, open_driver

__all__ = ["Backoff", "Driver", "DriverError", "open_driver"]
