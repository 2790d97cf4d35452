"""A driver that is connected but never delivers a sample (for daemon tests that need no data)."""
from __future__ import annotations

import time

from gravcal.core.samples import empty


class SilentDriver:
    def read(self, max_samples=256, timeout=0.1):
        time.sleep(timeout)
        return empty(0)

    def stats(self):
        return {}

    def close(self):
        pass
