"""The ADXL210 sensor model: transfer function, saturation, misalignment, truth, registry."""
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gravcal.core.model import Context, SensorModel
from gravcal.core.model.defaults import default_model, triad_truth
from gravcal.core.model.terms import (
    AnalogLowpass, Axes, DutyCycle, Misalignment, Noise, OffsetDrift, Timer, misaligned_axes,
)
from gravcal.core.model.defaults import CATALOGUE, catalogue_term, linear_channels
from gravcal.core.samples import FLAG_SATURATED, duty_ratios, raw_triad
from gravcal.core.scenarios import Motion
from gravcal.core.simulate import simulate


def settled(n):
    """Samples of constant_motion where the analog filter (tau = 15 ms) has settled: last 20 of each 50."""
    return (np.arange(n) % 50) >= 30


def constant_motion(f, fs=100.0, temp=25.0, vsupply=3.3):
    """Motion holding each row of f (M, 3) [g] for 50 samples."""
    f = np.repeat(np.atleast_2d(np.asarray(f, float)), 50, axis=0)
    n = len(f)
    return Motion(t=np.arange(n) / fs, specific_force=f, omega=np.zeros((n, 3)), temp=np.full(n, temp),
                  vsupply=np.full(n, vsupply), still=np.ones(n, bool), posture=np.zeros(n, np.int32), fs=fs)


def ramp_motion(lo, hi, n=4000, fs=100.0):
    f = np.zeros((n, 3))
    f[:, 0] = np.linspace(lo, hi, n)
    f[:, 2] = 1.0
    return Motion(t=np.arange(n) / fs, specific_force=f, omega=np.zeros((n, 3)), temp=np.full(n, 25.0),
                  vsupply=np.full(n, 3.3), still=np.zeros(n, bool), posture=np.zeros(n, np.int32), fs=fs)


def run_to_duty(model, motion, seed=0):
    """Channel-stage output and duty cycles (N, 4) of a fresh copy of model, before the timer."""
    m = SensorModel.from_dict(model.to_dict())
    ctx = Context(t=motion.t, temp=motion.temp, vsupply=motion.vsupply, fs=motion.fs,
                  rng=np.random.default_rng(seed), omega=motion.omega)
    x = m.run_stage("board", motion.specific_force, ctx)
    x = m.run_stage("channel", x, ctx)
    return x, m.run_stage("duty", x, ctx)


ORIENTATIONS = Rotation.from_rotvec(np.array([[0, 0, 0], [0.3, -1.2, 0.4], [2.0, 0.5, -0.7], [-1.5, 0, 2.2],
                                              [0, np.pi, 0], [0.9, 0.9, 0.9]]))


def test_duty_cycle_transfer_matches_datasheet_formula_within_timer_quantisation():
    model = default_model(nominal=True, noise=False)
    f = ORIENTATIONS.inv().apply([0, 0, 1.0]) * np.array([[1.0], [2.5], [0.4], [7.0], [1.0], [9.0]])
    sim = simulate(constant_motion(f), model, seed=1)
    ok = settled(len(sim.samples))
    d = duty_ratios(sim.samples)[ok]
    a = (d - 0.5) / 0.04  # datasheet: A = (T1/T2 - 0.5)/k, k = 4 %/g
    truth = sim.motion.specific_force[ok] @ model["axes"].matrix.T
    # |t1/t2 - d| = |e1 - d e2| / t2 < (1 + d)/t2 with |e1|, |e2| < 1 count (async capture)
    t2 = sim.samples["t2"][ok][:, [0, 0, 1, 1]].astype(float)
    bound = (1 + d) / t2 / 0.04
    err = a - truth
    assert np.all(np.abs(err) < bound)
    assert np.abs(err).max() > 0.2 * bound.max()  # quantisation is actually there
    # T2 = RSET / 125 Mohm counted at 4 MHz: 625 kohm -> 5 ms -> 20000 counts
    assert np.all(np.abs(sim.samples["t2"].astype(float) - 20000) <= 1)
    # the asynchronous capture is unbiased: error std < bound/sqrt(6) (two uniform counts), mean of n
    assert abs(err.mean()) < 5 * bound.max() / np.sqrt(6 * err.size)


def test_rounding_timer_error_is_half_a_count():
    model = default_model(nominal=True, noise=False, timer={"async_phase": 0.0})
    sim = simulate(constant_motion([[0.3, -0.2, 0.93], [5.0, 1.0, -3.0]]), model, seed=2)
    ok = settled(len(sim.samples))
    d_true = 0.5 + 0.04 * (sim.motion.specific_force[ok] @ model["axes"].matrix.T)
    t2 = sim.samples["t2"][ok][:, [0, 0, 1, 1]].astype(float)
    err = duty_ratios(sim.samples)[ok] - d_true
    assert np.all(np.abs(err) <= (0.5 + 0.5 * d_true) / t2 + 1e-12)


def test_saturation_clips_at_10_g_and_flags_exactly_the_rail_samples():
    model = default_model(nominal=True, noise=False, analog_lowpass=False)
    motion = ramp_motion(-15.0, 15.0)
    sim = simulate(motion, model, seed=3)
    a = (duty_ratios(sim.samples)[:, 0] - 0.5) / 0.04
    fx = motion.specific_force[:, 0]
    lsb = 1.5 / 20000 / 0.04  # quantisation bound [g]
    assert np.all(np.abs(a - np.clip(fx, -10, 10)) < lsb)
    flagged = (sim.samples["flags"] & FLAG_SATURATED) != 0
    assert np.array_equal(flagged, np.abs(fx) >= 10.0)
    assert 0.25 < flagged.mean() < 0.42  # |x| > 10 on a -15..15 ramp: 1/3 of it


def test_misalignment_gives_predicted_off_diagonal_sensitivity():
    psi, alpha, d1, d2 = 0.02, -0.03, 0.01, -0.015
    mis = Misalignment(chip_a=[0, 0, psi], mount_b=[alpha, 0, 0], axis_err=[[d1, d2], [0, 0], [0, 0], [0, 0]])
    k = np.array([0.041, 0.039, 0.04, 0.038])
    model = default_model(nominal=True, misalignment=mis, duty_cycle={"k": k.tolist()})
    K = triad_truth(model).sensitivity
    # chip A yawed by psi: ay axis = (-sin psi, cos psi, 0); its in-die error tilts ax toward y and z
    v = np.array([1, np.tan(d1), np.tan(d2)])
    ax_axis = Rotation.from_rotvec([0, 0, psi]).apply(v / np.linalg.norm(v))
    np.testing.assert_allclose(K[0], k[0] * ax_axis, atol=1e-15)
    np.testing.assert_allclose(K[1], k[1] * np.array([-np.sin(psi), np.cos(psi), 0]), atol=1e-15)
    # chip B's carrier rolled by alpha about board x: az axis = (0, -sin alpha, cos alpha)
    np.testing.assert_allclose(K[2], k[2] * np.array([0, -np.sin(alpha), np.cos(alpha)]), atol=1e-15)
    assert abs(K[0, 1]) > 0.5e-3 and abs(K[2, 1]) > 1e-3


def test_ideal_axes_are_the_zero_angle_misalignment():
    np.testing.assert_array_equal(misaligned_axes(), Axes().matrix)
    with pytest.raises(ValueError, match="either 'axes' or 'misalignment'"):
        simulate("static", SensorModel([Axes(), Misalignment()] + default_model(nominal=True).without("axes").terms),
                 duration=1)


@pytest.mark.parametrize("flags", [{}, {"misalignment": True, "temperature": True, "supply": True},
                                   {"misalignment": True, "temperature": True, "supply": True, "drift": True}])
def test_triad_truth_equals_noiseless_forward_model(flags):
    model = default_model(7, **flags, noise=False, colored_noise=False)
    if "offset_drift" in model:  # keep the deterministic drift, drop the random walks
        model = default_model(7, **flags, noise=False, colored_noise=False,
                              offset_drift={"walk_g_per_sqrt_h": [0, 0, 0, 0]},
                              sensitivity_drift={"walk_per_sqrt_h": [0, 0, 0, 0]})
    a = ORIENTATIONS.inv().apply([0, 0, 1.0])
    for temp, vs in ((25.0, 3.3), (31.5, 3.05)):
        motion = constant_motion(a, temp=temp, vsupply=vs)
        _, duty = run_to_duty(model, motion)
        for i, t in enumerate(motion.t):
            if i % 50 != 49:  # settled after the step
                continue
            cal = triad_truth(model, temp_c=temp, vsupply=vs, t=t)
            # with drift the input is a ramp: the 15 ms analog filter lags it by rate * tau ~ 2e-10 duty
            atol = 1e-9 if "offset_drift" in model else 1e-13
            np.testing.assert_allclose(duty[i, :3], cal.sensitivity @ motion.specific_force[i] + cal.offset,
                                       rtol=0, atol=atol)


def test_triad_truth_matches_simulated_counts_at_several_orientations():
    model = default_model(11, misalignment=True, temperature=True, noise=False)
    a = ORIENTATIONS.inv().apply([0, 0, 1.0])
    sim = simulate(constant_motion(a, temp=30.0, vsupply=3.2), model, seed=4)
    cal = triad_truth(model, temp_c=30.0, vsupply=3.2)
    ok = settled(len(sim.samples))
    raw = raw_triad(sim.samples)[ok]
    expected = sim.motion.specific_force[ok] @ cal.sensitivity.T + cal.offset
    bound = 2.0 / sim.samples["t2"][ok][:, [0, 0, 1]].astype(float)  # (1 + d)/t2 with d < 1
    assert np.all(np.abs(raw - expected) < bound)
    # and the calibration inverts it: |apply(raw)| = 1 g to the quantisation level
    assert np.abs(np.linalg.norm(cal.apply(raw), axis=1) - 1).max() < 5e-3


def test_registry_round_trip_gives_identical_output():
    model = default_model(5, misalignment=True, temperature=True, nonlinearity=True, drift=True, supply=True)
    copy = SensorModel.from_dict(json.loads(json.dumps(model.to_dict())))
    assert [t.name for t in copy.terms] == [t.name for t in model.terms]
    a = simulate("loetters", model, seed=9, duration=30)
    b = simulate("loetters", copy, seed=9, duration=30)
    assert np.array_equal(a.samples, b.samples)
    # a changed parameter does change the output (the comparison can fail)
    other = model.with_term(DutyCycle(d0=model["duty_cycle"].params["d0"] + 1e-3, k=model["duty_cycle"].params["k"]))
    c = simulate("loetters", other, seed=9, duration=30)
    assert not np.array_equal(a.samples["t1"], c.samples["t1"])
    with pytest.raises(ValueError, match="unknown sensor-model term"):
        SensorModel.from_dict({"terms": [{"name": "flux_capacitor", "params": {}}]})


def test_default_model_flags_overrides_and_independent_draws():
    base = default_model(3)
    assert [t.name for t in base.terms] == ["axes", "noise", "analog_lowpass", "saturation", "duty_cycle", "timer",
                                           "gyro_sensor", "gyro_conditioning", "gyro_adc"]
    full = default_model(3, misalignment=True, temperature=True, nonlinearity=True, drift=True, supply=True)
    for cat, term in CATALOGUE.items():
        assert term in full, cat
    assert "axes" not in full
    # switching groups on does not change the draws of the base terms
    np.testing.assert_array_equal(base["duty_cycle"].params["k"], full["duty_cycle"].params["k"])
    assert not np.array_equal(base["duty_cycle"].params["k"], default_model(4)["duty_cycle"].params["k"])
    k = base["duty_cycle"].params["k"]
    assert np.all((k >= 0.032) & (k <= 0.048)) and np.ptp(k) > 0
    nominal = default_model(nominal=True, temperature=True)
    np.testing.assert_array_equal(nominal["duty_cycle"].params["k"], np.full(4, 0.04))
    np.testing.assert_allclose(nominal["temperature_offset"].params["coef_g_per_c"], [2e-3, -2e-3, 2e-3, -2e-3])
    assert "noise" not in default_model(1, noise=False)
    assert default_model(1, noise={"density_ug": [500.0] * 4})["noise"].params["density_ug"][0] == 500.0
    with pytest.raises(ValueError, match="no parameter"):
        default_model(1, noise={"density": 1.0})
    with pytest.raises(ValueError, match="unknown override"):
        default_model(1, wobble=True)
    assert catalogue_term("quantization").name == "timer"


def test_white_noise_through_the_analog_filter_has_the_theoretical_level():
    fs, n = 100.0, 200_000
    noise, lp = Noise(density_ug=np.full(4, 200.0)), AnalogLowpass(c_uf=np.full(4, 0.47))
    ctx = Context(t=np.arange(n) / fs, temp=np.full(n, 25.0), vsupply=np.full(n, 3.3), fs=fs,
                  rng=np.random.default_rng(0))
    y = lp.forward(noise.forward(np.zeros((n, 4)), ctx), ctx)
    p = np.exp(-2 * np.pi * (5 / 0.47) / fs)
    sigma_in = 200e-6 * np.sqrt(fs / 2)
    expected = sigma_in * np.sqrt((1 - p) / (1 + p))  # one-pole filter of white noise
    # effective independent samples ~ n (1 - p)/(1 + p) ~ 50k: relative std of the std ~ 0.3 % per channel
    np.testing.assert_allclose(y.std(axis=0), expected, rtol=0.03)


def test_offset_random_walk_variance_and_rate():
    """Var W(T) = walk^2 T_h; 100 seeds x 4 channels = 400 draws -> std of the variance estimate
    is sqrt(2/400) = 7 %; tolerance 25 % (3.5 sigma)."""
    walk, rate, fs, n = 2e-3, 1e-3, 1.0, 3600
    ends = []
    for seed in range(100):
        term = OffsetDrift(rate_g_per_h=np.full(4, rate), walk_g_per_sqrt_h=np.full(4, walk))
        ctx = Context(t=np.arange(n) / fs, temp=np.full(n, 25.0), vsupply=np.full(n, 3.3), fs=fs,
                      rng=np.random.default_rng(seed))
        half = n // 2  # two blocks: the walk state carries over
        sub = lambda a, b: Context(t=ctx.t[a:b], temp=ctx.temp[a:b], vsupply=ctx.vsupply[a:b], fs=fs, rng=ctx.rng)
        term.forward(np.zeros((half, 4)), sub(0, half))
        y = term.forward(np.zeros((n - half, 4)), sub(half, n))
        ends.append(y[-1] - rate * (n - 1) / 3600)
    ends = np.concatenate(ends)
    assert abs(ends.var() / (walk**2 * (n - 1) / 3600) - 1) < 0.25
    assert abs(ends.mean()) < 4 * walk / np.sqrt(ends.size)


def test_linear_channels_reports_the_redundant_x_channel():
    model = default_model(2, misalignment=True)
    s, d = linear_channels(model)
    cal = triad_truth(model)
    np.testing.assert_allclose(cal.metadata["ax2_sensitivity"], s[3])
    # ax2 nominally senses board x like ax
    assert np.argmax(np.abs(s[3])) == 0 and np.argmax(np.abs(s[0])) == 0


def test_timer_rejects_nothing_silently_for_out_of_range_duty():
    timer = Timer(async_phase=0.0)
    n = 3
    ctx = Context(t=np.zeros(n), temp=np.full(n, 25.0), vsupply=np.full(n, 3.3), fs=100.0,
                  rng=np.random.default_rng(0))
    out = timer.forward(np.array([[-0.2, 0.5, 1.3, 0.25]] * n), ctx)
    np.testing.assert_array_equal(out[0], [0, 10000, 20000, 5000, 20000, 20000])
