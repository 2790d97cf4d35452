"""The sensor model's filters (core/model/filters.py, the compiled sosfilt kernel) against scipy.signal,
the oracle they replace: designs, filtering, carried state, rest states and frequency responses to bounds
derived from the operations each side rounds (never SciPy's bits, which change between its releases); the
same filter split into blocks bit for bit (one implementation against itself); every term that filters,
split into blocks, against the scipy.signal form it had; and no simulator process loading scipy.signal."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy import signal

from gravcal.core.butterworth import butter_sos
from gravcal.core.model.base import Context
from gravcal.core.model.filters import filter_sections, first_order_section, frequency_response, state_at, state_from
from gravcal.core.model.lag import first_order_lag
from gravcal.core.model.terms import REGISTRY

from filter_bounds import first_order_design_bound, sosfilt_difference_bound

EPS = np.finfo(float).eps
U = EPS / 2  # unit roundoff
SPLITS = ((0, 1), (1, 2), (2, 3), (3, 5), (5, None))  # block sizes 1, 1, 1, 2 and the rest


def _blocks(n, rng):
    """Cut points of n samples into blocks: single samples first, then two random lengths."""
    cuts = sorted(set([0, 1, 2, 3] + rng.integers(4, n, 2).tolist() + [n]))
    return list(zip(cuts[:-1], cuts[1:]))


def _zero_input_gain(sos, n):
    """max over the state elements of sum_k |y[k]|, y the cascade's response to that state alone (no input):
    how much a state error (or a rounding error injected into the state) can add up to in the output."""
    sos = np.asarray(sos, float)
    worst = 0.0
    for i in range(sos.shape[0] * 2):
        zi = np.zeros((sos.shape[0], 2))
        zi.flat[i] = 1.0
        worst = max(worst, float(np.abs(signal.sosfilt(sos, np.zeros(n), zi=zi)[0]).sum()))
    return worst


def _rest_state_rounding(sos):
    """Bound on |sos_rest_state - sosfilt_zi| per unit input. Both evaluate, per section with the earlier
    sections' DC gain g, z0 = g (b1 - a1 h + b2 - a2 h) with h = sum(b) / sum(a), sosfilt_zi as
    (b1 - a1 b0) / (1 + a1) through a linear solve: a handful of rounded operations on terms as large as
    |b1| + |b2| + (|a1| + |a2|)(|b0| + |h|), divided by 1 + a1 + a2 (small for a low corner: the
    cancellation amplifies the rounding); 4 eps of that bounds both."""
    bound, g = np.zeros((sos.shape[0], 2)), 1.0
    for s, (b0, b1, b2, _, a1, a2) in enumerate(np.asarray(sos, float)):
        h = (b0 + b1 + b2) / (1.0 + a1 + a2)
        size = abs(b1) + abs(b2) + (abs(a1) + abs(a2)) * (abs(b0) + abs(h))
        bound[s] = 4 * EPS * abs(g) * (size / abs(1.0 + a1 + a2) + abs(h))
        g *= h
    return bound


# -- design --------------------------------------------------------------------------------------------------------
def test_first_order_butterworth_is_scipys_within_the_rounding_bound():
    rng = np.random.default_rng(20)
    fss = [50.0, 100.0, 128.0, 200.0, 1000.0, 3.7]
    cases = [(0.3, 100.0), (0.3, 200.0), (25.0, 100.0), (45.0, 100.0), (5.0, 200.0)]
    cases += [(float(rng.uniform(1e-4, 0.4999) * fs), fs) for fs in rng.choice(fss, 400)]
    for corner, fs in cases:
        rel_hp, rel_lp, rel_pole = first_order_design_bound(corner, fs)
        for kind in ("highpass", "lowpass"):
            got = butter_sos(1, corner, kind, fs)
            ref = signal.butter(1, corner, kind, fs=fs, output="sos")
            assert got.shape == ref.shape == (1, 6) and got.flags.c_contiguous
            rel_k = rel_hp if kind == "highpass" else rel_lp
            tol = np.array([rel_k, rel_k, 0.0, 0.0, rel_pole, 0.0]) * np.abs(ref[0])
            assert np.all(np.abs(got[0] - ref[0]) <= tol), (corner, fs, kind, got - ref, tol)
            assert got[0, 1] == (-got[0, 0] if kind == "highpass" else got[0, 0])  # the zero exactly at z = ±1
    for corner in (0.0, 50.0, 70.0, -1.0):
        with pytest.raises(ValueError, match="corner"):
            butter_sos(1, corner, "lowpass", 100.0)
    with pytest.raises(ValueError, match="kind"):
        butter_sos(1, 1.0, "bandpass", 100.0)


# -- filtering -----------------------------------------------------------------------------------------------------
# the first-order filters of the model: (b, a) as each term builds them
FIRST_ORDER = {
    "analog_lowpass": lambda: ([1.0 - np.exp(-2 * np.pi * 50.0 / 100.0)], [1.0, -np.exp(-2 * np.pi * 50.0 / 100.0)]),
    "colored_noise": lambda: ([1.0], [1.0, -np.exp(-1.0 / (100.0 * 10.0))]),
    "random_walk": lambda: ([1.0], [1.0, -1.0]),
    "thermal_lag": lambda: ([1.0 - np.exp(-1.0 / (100.0 * 300.0))], [1.0, -np.exp(-1.0 / (100.0 * 300.0))]),
    "gyro_highpass": lambda: tuple(signal.butter(1, 0.3, "highpass", fs=100.0)),
}


def _one_section_bound(sos, x, y, z0):
    """sosfilt_difference_bound of a one-section filter, its signals bounded by what it saw: |x|, |y|, |z0| and
    the states b1 x - a1 y + z1, b2 x - a2 y they form."""
    c = np.abs(np.asarray(sos, float)[0])
    big = max(np.max(np.abs(x)), np.max(np.abs(y)), np.max(np.abs(z0)))
    return sosfilt_difference_bound(sos, 0.0, 0.0, n=len(y), signal_max=big * (1.0 + c[1] + c[2] + c[4] + c[5]))


@pytest.mark.parametrize("use", FIRST_ORDER)
@pytest.mark.parametrize("columns", [None, 1, 4])
def test_first_order_filter_is_lfilter_within_rounding_and_the_same_across_blocks(use, columns):
    """Direct form II transposed with b2 = a2 = 0: y = b0 x + z, z = b1 x - a1 y, lfilter's recursion: the
    outputs and the carried state are lfilter's to the rounding bound, and for any block split and for each
    column exactly what one call over the whole signal gives."""
    b, a = FIRST_ORDER[use]()
    rng = np.random.default_rng(len(use) * 7 + (columns or 0))
    n = 3000
    shape = (n,) if columns is None else (n, columns)
    x = rng.normal(20.0, 3.0, shape)
    z0 = rng.normal(0.0, 5.0, () if columns is None else (columns,))
    ref, zf = signal.lfilter(b, a, x, axis=0, zi=np.reshape(z0, (1,) + shape[1:]))
    sos = first_order_section(b, a)
    zi = state_from(sos, z0, 1 if columns is None else columns)
    x_before = x.copy()
    got = np.concatenate([filter_sections(sos, x[i:j], zi) for i, j in _blocks(n, rng)])
    assert np.array_equal(x, x_before), "the filter changed its input"
    assert got.shape == ref.shape
    whole_zi = state_from(sos, z0, 1 if columns is None else columns)
    assert np.array_equal(got, filter_sections(sos, x, whole_zi)) and np.array_equal(zi, whole_zi)
    tol = _one_section_bound(sos, x, ref, z0)
    assert np.max(np.abs(got - ref)) <= tol and tol < 1e-9 * max(1.0, np.max(np.abs(ref))) * n
    assert np.max(np.abs(zi[:, 0, 0] - np.ravel(zf))) <= tol and not zi[:, 0, 1].any()


def test_gyro_cascade_is_sosfilt_and_its_rest_state_within_rounding():
    """The conditioning's two sections: from SciPy's state the outputs are sosfilt's to the rounding bound
    (and across blocks what one call gives). The rest state is computed in closed form (butterworth.sos_rest_state, the detector's) where
    sosfilt_zi solves a linear system: the two differ by the rounding bounded in _rest_state_rounding, and the
    outputs by that times the cascade's zero-input gain, plus a rounding of each output propagated the same way."""
    rng = np.random.default_rng(5)
    for fs, hp, lp in ((100.0, 0.3, 25.0), (200.0, 0.3, 25.0), (200.0, 5.0, 45.0), (50.0, 0.1, 22.5)):
        sos = np.vstack([butter_sos(1, hp, "highpass", fs), butter_sos(1, lp, "lowpass", fs)])
        n = 4000
        x = 1.35 + 0.05 * rng.standard_normal(n)
        x0 = x[0]
        ref_zi = signal.sosfilt_zi(sos) * x0
        ref, ref_zf = signal.sosfilt(sos, x, zi=ref_zi)
        zi = ref_zi[None].copy()
        got = np.concatenate([filter_sections(sos, x[i:j], zi) for i, j in _blocks(n, rng)])
        whole_zi = ref_zi[None].copy()
        assert np.array_equal(got, filter_sections(sos, x, whole_zi)) and np.array_equal(zi, whole_zi)
        tol = sosfilt_difference_bound(sos, np.max(np.abs(x)), np.max(np.abs(ref_zi)), n=n)
        assert np.max(np.abs(got - ref)) <= tol and np.max(np.abs(zi[0] - ref_zf)) <= tol

        mine = state_at(sos, x0)
        assert mine.shape == (1, 2, 2)
        state_tol = _rest_state_rounding(sos) * abs(x0)
        assert np.all(np.abs(mine[0] - ref_zi) <= state_tol)
        state_tol = np.max(state_tol)
        y = filter_sections(sos, x, mine)
        tol = (state_tol + 2 * EPS * np.max(np.abs(ref))) * _zero_input_gain(sos, n)
        assert np.max(np.abs(y - ref)) <= tol, (np.max(np.abs(y - ref)), tol)


def test_first_order_rest_state_within_rounding_of_lfilter_zi():
    """The analog low-pass starts settled: state_at gives p x0 (h = 1 exactly), lfilter_zi p (1 - p) / (1 - p)."""
    rng = np.random.default_rng(8)
    for c_uf in rng.uniform(0.01, 1.0, 200):
        p = np.exp(-2 * np.pi * (5.0 / c_uf) / 100.0)
        sos = first_order_section([1.0 - p], [1.0, -p])
        x0 = rng.normal(0.0, 2.0, 4)
        ref = signal.lfilter_zi([1.0 - p], [1.0, -p])[0] * x0
        got = state_at(sos, x0, 4)
        assert got.shape == (4, 1, 2) and not got[:, 0, 1].any()
        assert np.all(np.abs(got[:, 0, 0] - ref) <= 4 * EPS * np.abs(ref))


def test_frequency_response_within_rounding_of_sosfreqz():
    """sosfreqz evaluates the same two polynomials per section (through numpy's polyval); about ten rounded
    complex operations per section: 64 eps relative per section bounds both."""
    f = np.linspace(0.0, 49.9, 300)
    sos = np.vstack([butter_sos(1, 0.3, "highpass", 100.0), butter_sos(1, 25.0, "lowpass", 100.0)])
    _, ref = signal.sosfreqz(sos, worN=f, fs=100.0)
    got = frequency_response(sos, f, 100.0)
    assert np.all(np.abs(got - ref) <= 64 * EPS * sos.shape[0] * np.maximum(np.abs(ref), EPS))


def test_bad_state_or_input_is_refused_with_a_clear_error():
    sos = first_order_section([0.5], [1.0, -0.5])
    with pytest.raises(ValueError, match="state"):
        filter_sections(sos, np.zeros((10, 4)), state_from(sos, 0.0, 3))
    with pytest.raises(ValueError, match="state"):
        filter_sections(sos, np.zeros(10), np.zeros((1, 1, 2), dtype=np.float32))
    with pytest.raises(ValueError, match="input"):
        filter_sections(sos, np.zeros((2, 2, 2)), state_from(sos, 0.0, 4))
    with pytest.raises(ValueError, match="first-order"):
        first_order_section([1.0, 2.0, 3.0], [1.0, 0.5])
    with pytest.raises(ValueError, match="first-order"):
        first_order_section([1.0], [2.0, 0.5])


# -- every filtering term against its scipy.signal form -----------------------------------------------------------
def _term_stream(seed):
    """The term's own random stream, as StatefulTerm seeds it from ctx.rng on its first block."""
    return np.random.default_rng(int(np.random.default_rng(seed).integers(0, 2**63 - 1)))


def _run_term(term, x, t, temp, fs, seed, blocks):
    ctx_rng = np.random.default_rng(seed)
    out = []
    for i, j in blocks:
        ctx = Context(t[i:j], temp[i:j], np.full(j - i, 3.3), fs, rng=ctx_rng)
        out.append(term.forward(x[i:j], ctx))
    return np.concatenate(out)


def _inputs(n, fs, seed):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    temp = 25.0 + 6.0 * np.sin(t / 20.0) + 0.1 * rng.standard_normal(n)
    x = rng.normal(0.0, 0.3, (n, 4))
    return rng, t, temp, x


def test_colored_noise_random_walk_and_thermal_lag_terms_are_their_scipy_forms_within_rounding():
    fs, n, seed = 100.0, 5000, 31
    rng, t, temp, x = _inputs(n, fs, seed)
    blocks = _blocks(n, rng)

    sigma, taus = np.array([1e-3, 2e-3, 5e-4, 1e-3]), np.array([1.0, 10.0, 100.0])
    got = _run_term(REGISTRY["colored_noise"].forward(sigma_g=sigma, tau_s=taus), x, t, temp, fs, seed, blocks)
    r = _term_stream(seed)
    s = sigma / np.sqrt(taus.size)
    phi = np.exp(-1.0 / (fs * taus))
    p0 = r.standard_normal((taus.size, 4)) * s
    w = r.standard_normal((n, taus.size, 4))
    ref, tol = x.copy(), np.zeros(4)
    for j in range(taus.size):
        drive = w[:, j] * (s * np.sqrt(1.0 - phi[j] ** 2))
        y = signal.lfilter([1.0], [1.0, -phi[j]], drive, axis=0, zi=(phi[j] * p0[j])[None, :])[0]
        ref += y
        sos = first_order_section([1.0], [1.0, -phi[j]])
        # each filter to its rounding bound, then one rounding per addition of the terms (both sides)
        tol += [_one_section_bound(sos, drive[:, c], y[:, c], phi[j] * p0[j, c]) for c in range(4)]
    tol += 2 * (taus.size + 1) * U * (np.abs(x) + taus.size * np.abs(ref - x)).max(axis=0)
    assert np.all(np.abs(got - ref).max(axis=0) <= tol)

    walk = np.array([1e-3, 3e-3, 2e-3, 1e-3])
    term = REGISTRY["offset_drift"].forward(rate_g_per_h=np.zeros(4), walk_g_per_sqrt_h=walk)
    got = _run_term(term, np.zeros((n, 4)), t, temp, fs, seed, blocks)
    steps = _term_stream(seed).standard_normal((n, 4)) * (walk * np.sqrt(1.0 / fs / 3600.0))
    ref = signal.lfilter([1.0], [1.0, -1.0], steps, axis=0, zi=np.zeros((1, 4)))[0]
    walk_sos = first_order_section([1.0], [1.0, -1.0])
    tol = [_one_section_bound(walk_sos, steps[:, c], ref[:, c], 0.0) for c in range(4)]
    assert np.all(np.abs(got - ref).max(axis=0) <= tol)

    coef, tau = np.array([2e-3, -1e-3, 1.5e-3, 2e-3]), 30.0
    got = _run_term(REGISTRY["thermal_lag"].forward(coef_g_per_c=coef, t0_c=25.0, tau_s=tau), np.zeros((n, 4)),
                    t, temp, fs, seed, blocks)
    a = np.exp(-1.0 / (fs * tau))
    lagged = signal.lfilter([1.0 - a], [1.0, -a], temp, zi=[a * temp[0]])[0]
    lag_tol = _one_section_bound(first_order_section([1.0 - a], [1.0, -a]), temp, lagged, a * temp[0])
    # the lag, then (lagged - 25) coef: one rounding each, the lag's error scaled by |coef| (both sides)
    tol = np.abs(coef) * lag_tol + 4 * U * np.abs(coef * (lagged[:, None] - 25.0)).max(axis=0) \
        + 2 * U * np.abs(coef) * np.abs(lagged).max()
    assert np.all(np.abs(got - coef * (lagged[:, None] - 25.0)).max(axis=0) <= tol)
    # the diagnosis' lag of a uniform series (its filter path) is the same lfilter
    assert np.max(np.abs(first_order_lag(t, temp, tau) - lagged)) <= lag_tol


def test_analog_lowpass_and_gyro_conditioning_terms_are_their_scipy_forms_within_rounding():
    """Both start settled on their first sample: the rest state differs from lfilter_zi / sosfilt_zi by the
    rounding bounded above, the filtering is the same."""
    fs, n, seed = 100.0, 5000, 32
    rng, t, temp, x = _inputs(n, fs, seed)
    blocks = _blocks(n, rng)
    x = x + 0.5

    c_uf = np.array([0.1, 0.12, 0.09, 0.5])
    got = _run_term(REGISTRY["analog_lowpass"].forward(c_uf=c_uf), x, t, temp, fs, seed, blocks)
    for c in range(4):
        p = np.exp(-2.0 * np.pi * (5.0 / c_uf[c]) / fs)
        b, a = [1.0 - p], [1.0, -p]
        ref = signal.lfilter(b, a, x[:, c], zi=signal.lfilter_zi(b, a) * x[0, c])[0]
        sos = first_order_section(b, a)
        tol = (4 * EPS * abs(p * x[0, c]) + 2 * EPS * np.max(np.abs(ref))) * _zero_input_gain(sos, n)
        assert np.max(np.abs(got[:, c] - ref)) <= tol

    volts = 1.35 + 0.02 * rng.standard_normal(n)
    cond = REGISTRY["gyro_conditioning"].forward(hp_hz=0.3, gain=7.5, lp_hz=25.0, vref_ratio=0.5)
    got = _run_term(cond, volts, t, temp, fs, seed, blocks)
    sos = np.vstack([signal.butter(1, 0.3, "highpass", fs=fs, output="sos"),
                     signal.butter(1, 25.0, "lowpass", fs=fs, output="sos")])
    zi = signal.sosfilt_zi(sos) * volts[0]
    y = signal.sosfilt(sos, volts, zi=zi)[0]
    ref = np.clip(0.5 * 3.3 + 7.5 * y, 0.0, 3.3)
    tol = 7.5 * (np.max(_rest_state_rounding(sos)) * abs(volts[0]) + 2 * EPS * np.max(np.abs(y))) * _zero_input_gain(sos, n) \
        + 2 * EPS * np.max(np.abs(ref))
    assert np.max(np.abs(got - ref)) <= tol


def test_a_simulator_process_does_not_load_scipy_signal():
    """The simulator's filters are the compiled kernel: a session with the gyro, the drift walks, the
    colored noise and the thermal lag switched on runs without importing scipy.signal."""
    code = ("import sys\n"
            "from gravcal.core.model.defaults import default_model\n"
            "from gravcal.core.simulate import simulate\n"
            "m = default_model(1, drift=True, temperature=True, thermal_lag={'coef_g_per_c': [1e-3] * 4})\n"
            "s = simulate('six_position', m, seed=1, duration=20.0, fs=100.0)\n"
            "assert len(s.samples) == 2000 and s.samples['gyro'].std() > 0\n"
            "print(sorted(m for m in sys.modules if m.startswith('scipy.signal')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]"
