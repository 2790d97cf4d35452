"""The simulator: block-split invariance, sample fields, truth, saturation flags, errors."""
import json

import numpy as np
import pytest

from gravcal.core.calibration import Calibration
from gravcal.core.model import SensorModel
from gravcal.core.model.defaults import default_model, triad_truth
from gravcal.core.samples import FLAG_SATURATED, SAMPLE_DTYPE, raw_triad
from gravcal.core.scenarios import Motion, make_motion
from gravcal.core.simulate import simulate, simulate_blocks

FULL = dict(misalignment=True, temperature=True, nonlinearity=True, drift=True, supply=True)


@pytest.mark.parametrize("block", [1, 997, 4096, 100_000])
def test_block_split_equals_one_shot(block):
    model = default_model(3, **FULL)
    duration = 3 if block == 1 else 120
    one = simulate("daily_living", model, seed=5, duration=duration)
    parts = list(simulate_blocks("daily_living", model, seed=5, duration=duration, block=block))
    assert all(len(p) <= block for p in parts)
    assert np.array_equal(one.samples, np.concatenate(parts))


def test_default_model_drawn_from_seed_and_blocks_agree():
    a = simulate("loetters", seed=11, duration=60)
    b = np.concatenate(list(simulate_blocks("loetters", seed=11, duration=60, block=500)))
    assert np.array_equal(a.samples, b)
    c = simulate("loetters", seed=12, duration=60)
    assert a.truth["model"] != c.truth["model"]
    assert not np.array_equal(a.samples["t1"], c.samples["t1"])


def test_sample_fields():
    sim = simulate("six_position", seed=2, duration=60, fs=50)
    s = sim.samples
    assert s.dtype == SAMPLE_DTYPE and len(s) == 3000
    np.testing.assert_array_equal(s["seq"], np.arange(3000))
    np.testing.assert_allclose(s["t"], np.arange(3000) / 50)
    clock = sim.model["timer"].params["clock_hz"]
    np.testing.assert_array_equal(s["tick"], (np.rint(s["t"] * clock).astype(np.int64) % 2**32).astype(np.uint32))
    rset = sim.model["timer"].params["rset_ohm"]
    assert np.all(np.abs(s["t2"] - rset / 125e6 * clock) <= 1)  # T2 = RSET / 125 Mohm
    np.testing.assert_allclose(s["temp"], sim.motion.temp.astype(np.float32))
    assert np.all((s["vsupply"] >= 3.0) & (s["vsupply"] <= 3.3))
    assert np.all(s["flags"] == 0)
    assert 1500 < np.median(s["gyro"]) < 2600


def test_tick_wraps_at_32_bits():
    n = 200
    t = 1073.0 + np.arange(n) / 100.0  # 4 MHz clock wraps after 2^32 / 4e6 = 1073.7 s
    m = Motion(t=t, specific_force=np.tile([0, 0, 1.0], (n, 1)), omega=np.zeros((n, 3)), temp=np.full(n, 25.0),
               vsupply=np.full(n, 3.3), still=np.ones(n, bool), posture=np.zeros(n, np.int32))
    tick = simulate(m, default_model(nominal=True)).samples["tick"].astype(np.int64)
    steps = np.diff(tick) % 2**32
    assert np.all(steps == 40000) and np.any(np.diff(tick) < 0)


def test_truth_is_jsonable_and_is_triad_truth_at_the_reported_conditions():
    model = default_model(4, temperature=True, misalignment=True)
    sim = simulate("daily_living", model, seed=3, duration=300)
    truth = json.loads(json.dumps(sim.truth))
    assert truth["scenario"] == "daily_living" and truth["seed"] == 3 and truth["fs"] == 100.0
    cal = Calibration.from_dict(truth["calibration"])
    ref = triad_truth(model, **truth["conditions"])
    np.testing.assert_allclose(cal.sensitivity, ref.sensitivity)
    np.testing.assert_allclose(cal.offset, ref.offset)
    assert SensorModel.from_dict(truth["model"]).to_dict() == model.to_dict()
    assert abs(truth["conditions"]["temp_c"] - np.median(sim.motion.temp[sim.motion.still])) < 1e-9


def test_end_to_end_still_means_match_truth_within_noise():
    """Window means of raw triad over still periods equal K a + o: noise 200 µg/√Hz through the
    10.6 Hz filter is ~0.8 mg rms -> 3e-5 duty; a 2 s mean of ~20 correlated samples/s is good
    to ~1e-5 duty. Tolerance 1e-4 duty (2.5 mg) also covers the quantisation (1.25 mg)."""
    model = default_model(8, misalignment=True)
    sim = simulate("six_position", model, seed=6, duration=120)
    cal = Calibration.from_dict(sim.truth["calibration"])
    raw = raw_triad(sim.samples)
    still = sim.motion.still
    d = np.diff(np.concatenate([[0], still.astype(int), [0]]))
    for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)):
        a, b = a + 50, b  # skip the analog filter settling
        expected = cal.sensitivity @ sim.motion.specific_force[a:b].mean(axis=0) + cal.offset
        assert np.abs(raw[a:b].mean(axis=0) - expected).max() < 1e-4


def test_saturated_samples_are_flagged():
    n = 1000
    f = np.tile([0, 0, 1.0], (n, 1))
    f[400:450, 2] = 14.0  # a hard impact
    m = Motion(t=np.arange(n) / 100, specific_force=f, omega=np.zeros((n, 3)), temp=np.full(n, 25.0),
               vsupply=np.full(n, 3.3), still=np.zeros(n, bool), posture=np.zeros(n, np.int32))
    s = simulate(m, default_model(1), seed=0).samples
    flagged = np.flatnonzero(s["flags"] & FLAG_SATURATED)
    assert flagged.min() >= 400 and flagged.max() < 460 and len(flagged) > 40


def test_motion_input_and_blocks_of_a_motion():
    motion = make_motion("static", duration=30, rng=1)
    model = default_model(2)
    a = simulate(motion, model, seed=1)
    b = np.concatenate(list(simulate_blocks(motion, model, seed=1, block=333)))
    assert np.array_equal(a.samples, b)
    assert a.truth["scenario"] == "static"


def test_week_long_stream_is_lazy():
    gen = simulate_blocks("daily_living", seed=1, duration=2 * 86400, block=1000)  # 17 M samples
    first = next(gen)
    assert len(first) == 1000 and first["seq"][-1] == 999
    second = next(gen)
    assert second["seq"][0] == 1000
    gen.close()


def test_errors_name_the_problem():
    with pytest.raises(ValueError, match=r"no 'counts'-stage term \(timer\)"):
        simulate("static", default_model(1, timer=False), duration=1)
    with pytest.raises(ValueError, match="block must be a positive"):
        next(simulate_blocks("static", duration=1, block=0))
    with pytest.raises(ValueError, match="unknown scenario"):
        simulate("moonwalk")
    with pytest.raises(ValueError, match="ready-made motion"):
        simulate(make_motion("static", duration=1), theta_max_deg=3)
