"""Test rigs: the logger without the hardware, for HIL tests, benchmarks and ``gravcald --emulate``.

- ``sources``: where emulated samples come from (sensor model, recording, test pattern);
- ``emulator``: paces a source onto a link (a serial pty; ``can_links``: an slcan pty or a
  python-can bus), with fault injection and a log of every sample's fate;
- ``fake_i2c``: the logger as an I2C target behind a fake ``smbus2.SMBus`` (the ``fake-i2c://``
  driver scheme); ``i2c_dev``: that target at ``/dev/i2c-N`` for another process, through umockdev;
- ``emulate``: the emulator's entry point (``python -m gravcal.drivers.rigs.emulate``), and
  ``options`` its argument parsers;
- ``hil``: runs that entry point in a child process and reads its announcements.

The real drivers never import this package: a rig reaches them only through the scheme table
of ``gravcal.drivers.base`` (imported on first use of its scheme), so a production install
opens hardware without loading any of it.
"""
