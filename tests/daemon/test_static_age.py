"""The published `static` of a sample is the detector's latest decision only while that decision is recent
(processing.STATIC_MAX_AGE_S of sensor time); when the processing thread falls behind (a loaded host, a
time-lapse emulator) it is null, never an old "still" on later motion. CALIB carries `data_through_seq`,
the last sample the estimator had analysed, so a client can tell which data a calibration rests on."""
from __future__ import annotations

import numpy as np

from gravcal.core.simulate import simulate
from gravcal.daemon.config import load_config
from gravcal.daemon.processing import STATIC_MAX_AGE_S, Processor, nominal_calibration
from gravcal.daemon.persistence import CalibrationState
from gravcal.daemon.protocol import STATIC_UNKNOWN

FS = 100.0


def processor() -> Processor:
    cfg = load_config(None, {"device.fs_hz": FS})
    return Processor(cfg, CalibrationState(nominal_calibration(), 0, None, False, {}), resumed=False)


def test_static_is_unknown_before_any_analysis_and_when_the_analysis_lags():
    samples = simulate("six_position", seed=3, duration=60.0, fs=FS).samples
    p = processor()
    _, _, before = p.correct(samples[:50])
    assert np.all(before == STATIC_UNKNOWN)  # no decision yet: unknown, not "moving"
    decisions = p.analyse(samples[:3000])  # 30 s analysed
    assert p.analysed[0] == int(samples["seq"][2999])
    _, _, codes = p.correct(samples[3000:4000])  # the next 10 s published while the analysis is still at 30 s
    age_s = (samples["seq"][3000:4000] - samples["seq"][2999]) / FS
    fresh = age_s <= STATIC_MAX_AGE_S
    assert fresh.sum() == int(STATIC_MAX_AGE_S * FS)
    assert np.all(codes[fresh] == int(decisions[-1]))
    assert np.all(codes[~fresh] == STATIC_UNKNOWN)
