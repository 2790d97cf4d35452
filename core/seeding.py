"""The seed -> (motion, model, sensor) random streams of the simulator, in a module light enough for
the daemon's emulation to draw the emulated sensor's truth without importing the motion scenarios."""
from __future__ import annotations

import numpy as np


def seed_streams(seed: int) -> tuple[np.random.Generator, np.random.Generator, np.random.Generator]:
    motion, model, sensor = np.random.SeedSequence(seed).spawn(3)
    return np.random.default_rng(motion), np.random.default_rng(model), np.random.default_rng(sensor)
