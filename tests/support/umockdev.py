"""Tests of the emulated I2C bus need umockdev's preload library (Debian: package umockdev; drivers/rigs/i2c_dev.py):
:func:`require_umockdev` skips them on a developer's machine without it, and fails them where
GRAVCAL_REQUIRE_UMOCKDEV=1 (.ci/run sets it and installs the package), so CI cannot pass without running them."""
from gravcal.drivers.rigs.i2c_dev import INSTALL_HINT, preload_library
from support.inputs import skip_or_fail


def require_umockdev() -> None:
    if preload_library() is None:
        skip_or_fail(INSTALL_HINT, "GRAVCAL_REQUIRE_UMOCKDEV")
