"""Window-level sessions of a sensor with (or without) a planted temperature offset and a 22 -> 32 °C ramp,
and the online calibrator run over them (tests/core/test_online_extended.py; bench_soak.py --controls)."""
from __future__ import annotations

import numpy as np
from gravcal.core.calibration import Calibration
from gravcal.core.estimators.consider import datasheet_held_uncertainty
from gravcal.core.estimators.online import OnlineCalibrator
from gravcal.core.estimators.remount import session_windows
from gravcal.core.model.defaults import default_model

DURATION = 5400.0
EXT = "6+temperature_offset"


def ramp(t: float) -> float:
    return 22.0 + 10.0 * t / DURATION


def session(seed: int, planted: bool, **kw):
    model = default_model(seed, temperature_offset=planted)
    kw.setdefault("temp_c", ramp)
    return session_windows("loetters", seed=seed, duration=DURATION, model=model, **kw)


def previous_calibration(info) -> Calibration:
    tr = info["truth"](25.0)
    rng = np.random.default_rng(1)
    K = np.diag(np.diag(tr.sensitivity) * (1 + 0.01 * rng.choice([-1, 1], 3)))
    o = tr.offset + 0.010 * np.diag(K) * rng.choice([-1, 1], 3)
    return datasheet_held_uncertainty(Calibration("6", o, K))


def run(ws, start, terms=("temperature_offset",), upto=None) -> OnlineCalibrator:
    oc = OnlineCalibrator(start, candidates=("offsets", "6"), terms=terms)
    for i in range(len(ws) if upto is None else upto):
        oc.update(ws.subset(np.arange(i, i + 1)))
    return oc
