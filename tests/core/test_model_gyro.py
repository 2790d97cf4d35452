"""The ENC-03J path: axis, scale through the conditioning stage, high-pass, range, ADC."""
import numpy as np
from scipy import signal

from gravcal.core.model.defaults import default_model
from gravcal.core.model.enc03j import gyro_null_counts, gyro_scale_counts_per_rad_s
from gravcal.core.scenarios import Motion
from gravcal.core.simulate import simulate


def rate_motion(omega, fs=100.0):
    n = len(omega)
    f = np.tile([0.0, 0.0, 1.0], (n, 1))
    return Motion(t=np.arange(n) / fs, specific_force=f, omega=omega, temp=np.full(n, 25.0),
                  vsupply=np.full(n, 3.3), still=np.zeros(n, bool), posture=np.zeros(n, np.int32), fs=fs)


def quiet_model():
    return default_model(nominal=True, gyro_sensor={"noise_dps_rthz": 0.0})


def test_sinusoidal_rate_about_board_y_gives_the_predicted_adc_amplitude():
    fs, f0, amp_dps = 100.0, 2.0, 60.0
    t = np.arange(3000) / fs
    omega = np.zeros((t.size, 3))
    omega[:, 1] = np.deg2rad(amp_dps) * np.sin(2 * np.pi * f0 * t)
    model = quiet_model()
    sim = simulate(rate_motion(omega, fs), model, seed=0)
    g = sim.samples["gyro"].astype(float)[1000:]  # high-pass transient gone (tau = 0.5 s)
    # passband gain: 0.67 mV/(°/s) * 7.5 * 4096 / 3.3 V, times the two first-order sections at f0
    cond = model["gyro_conditioning"]
    _, h = signal.sosfreqz(cond.sos(fs), worN=[f0], fs=fs)
    expected = gyro_scale_counts_per_rad_s(model, 3.3) * np.deg2rad(amp_dps) * abs(h[0])
    measured = (g.max() - g.min()) / 2
    assert abs(measured - expected) < 1.0 + 0.01 * expected  # one ADC count + 1 %
    assert abs(g.mean() - gyro_null_counts(model)) < 1.0


def test_rates_about_the_other_axes_are_not_sensed():
    t = np.arange(1000) / 100.0
    omega = np.zeros((t.size, 3))
    omega[:, 0] = 3.0 * np.sin(2 * np.pi * 1.5 * t)
    omega[:, 2] = 3.0 * np.cos(2 * np.pi * 1.5 * t)
    g = simulate(rate_motion(omega), quiet_model(), seed=0).samples["gyro"].astype(float)
    assert np.ptp(g) <= 1.0


def test_high_pass_removes_constant_rate_and_null_voltage():
    omega = np.zeros((2000, 3))
    omega[500:, 1] = np.deg2rad(50.0)  # step to a constant 50 °/s
    g = simulate(rate_motion(omega), quiet_model(), seed=0).samples["gyro"].astype(float)
    null = gyro_null_counts(quiet_model())
    assert abs(g[400] - null) <= 1  # null voltage 1.35 V removed
    assert g[510] - null > 100  # the step passes
    assert abs(g[-1] - null) <= 2  # and decays with tau = 1/(2 pi 0.3 Hz) = 0.53 s


def test_range_and_adc_limits():
    omega = np.zeros((400, 3))
    omega[200:, 1] = np.deg2rad(1000.0)
    g = simulate(rate_motion(omega), quiet_model(), seed=0).samples["gyro"].astype(float)
    null = gyro_null_counts(quiet_model())
    peak = g.max() - null
    # the sensor clips at 300 °/s, then the filters only attenuate
    assert peak <= gyro_scale_counts_per_rad_s(quiet_model()) * np.deg2rad(300.0) + 1
    assert peak > 0.8 * gyro_scale_counts_per_rad_s(quiet_model()) * np.deg2rad(300.0)
    assert g.max() <= 4095


def test_gyro_noise_level():
    """White rate noise 0.05 (°/s)/√Hz over 50 Hz is 0.35 °/s rms before the filters; through the
    25 Hz low-pass about 0.27 °/s ~ 0.8 counts; with 3000 samples the std is known to ~3 %."""
    omega = np.zeros((6000, 3))
    model = default_model(nominal=True)
    g = simulate(rate_motion(omega), model, seed=1).samples["gyro"].astype(float)[1000:]
    sos = model["gyro_conditioning"].sos(100.0)
    w, h = signal.sosfreqz(sos, worN=4096, fs=100.0)
    power_gain = np.trapezoid(np.abs(h) ** 2, w) / 50.0
    sigma_dps = 0.05 * np.sqrt(50.0) * np.sqrt(power_gain)
    expected = np.sqrt((gyro_scale_counts_per_rad_s(model) * np.deg2rad(sigma_dps)) ** 2 + 1 / 12)
    assert abs(g.std() / expected - 1) < 0.15
