"""core._blockkernels (the compiled loops of core.fastdetect) against numpy/SciPy forms written out here.

block_pass accumulates in float64: it is checked against a float64 numpy oracle to a tolerance derived
from float rounding. lotters_chain and sosfilt do SciPy's sosfilt operations: checked against it to the
rounding bound of the recursion (tests/core/filter_bounds.py), never to SciPy's bits; variance_chain against
numpy's elementwise operations and running sums in the kernel's order, bit for bit.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

import gravcal.core.fastdetect as fastdetect
from gravcal.core._blockkernels import block_pass, lotters_chain, sosfilt, variance_chain
from gravcal.core.calibration import Calibration
from gravcal.core.butterworth import butter_sos, sos_rest_state
from gravcal.core.detectors.windowing import settle_samples
from gravcal.core.samples import raw_triad
from gravcal.core.simulate import simulate

from filter_bounds import cascade_gains, sosfilt_difference_bound

U64 = 2.0 ** -53  # unit roundoff of float64
U32 = 2.0 ** -24  # of float32
I6 = np.array([0, 1, 2, 0, 0, 1])
J6 = np.array([0, 1, 2, 1, 2, 2])


# ---- oracles -------------------------------------------------------------------------------------

def block_oracle(x: np.ndarray, t: np.ndarray, fs: float, B: int, aux: np.ndarray | None = None):
    """Block statistics in float64 numpy, each rule written out: x (n, 3), t (n,), aux (n, k).
    Returns mean (3, nb), scatter in float64 (6, nb), the bounds of the float64 rounding of both,
    aux means (k, nb) and usable (nb,)."""
    nb = x.shape[0] // B
    v = x[:nb * B].astype(np.float64).T.reshape(3, nb, B)
    with np.errstate(invalid="ignore"):  # inf - inf in a block holding inf: unusable either way
        d = v - v[:, :, :1]  # deviations from each block's first sample
        s = d.sum(axis=2)
        q = np.stack([(d[i] * d[j]).sum(axis=1) for i, j in zip(I6, J6)])
        mean = v[:, :, 0] + s / B
        scatter = q - s[I6] * s[J6] / B
    # recursive or pairwise summation of B terms errs by <= (B - 1) u Σ|term| on either side; the
    # mean's division and final add, the scatter's product, division and subtraction add a few u
    abs_d = np.abs(d)
    mean_tol = 2 * (B + 2) * U64 * (abs_d.sum(axis=2) / B + np.abs(mean))
    prods = np.stack([(abs_d[i] * abs_d[j]).sum(axis=1) for i, j in zip(I6, J6)])
    scatter_tol = 2 * (B + 4) * U64 * (prods + np.abs(s[I6] * s[J6]) / B)
    dt = np.concatenate([[1.0 / fs], np.diff(t.astype(np.float64))])
    good = (dt > 0) & (dt <= 1.5 / fs) & np.isfinite(x).all(axis=1)
    usable = good[:nb * B].reshape(nb, B).all(axis=1)
    aux_mean = np.zeros((0, nb))
    if aux is not None:
        aux_mean = aux[:nb * B].astype(np.float64).reshape(nb, B, -1).mean(axis=1).T
        usable &= np.isfinite(aux_mean).all(axis=0)
    return mean, scatter, mean_tol, scatter_tol, aux_mean, usable


def in_g(mean: np.ndarray, o: np.ndarray, kinv: np.ndarray) -> np.ndarray:
    """K^-1 (mean - o) for channel-major rows (3, m), column by column from zero, zero terms skipped."""
    out = np.zeros(mean.shape)
    for j in range(3):
        d = mean[j] - o[j]
        for i in range(3):
            if kinv[i, j] != 0.0:
                out[i] += kinv[i, j] * d
    return out


def axis_var_g(bs, kinv: np.ndarray, lo: int = 0, hi: int | None = None) -> np.ndarray:
    """(3, hi - lo) within-block per-axis scatter in g² of blocks [lo, hi): Σ_q c_iq W_q, zero terms skipped."""
    hi = len(bs) if hi is None else hi
    out = np.zeros((3, hi - lo))
    for i in range(3):
        for q in range(6):
            c = kinv[i, I6[q]] * kinv[i, J6[q]] * (1.0 if I6[q] == J6[q] else 2.0)
            if c != 0.0:
                out[i] += c * bs.scatter[q, lo:hi]
    return out


def variance_oracle(bs, to_g, *, window_s=1.0, threshold_g=0.02):
    """variance_still as numpy computes it: (still, per-axis variances (3, nb - wb + 1), wb)."""
    wb = max(1, int(round(window_s * bs.fs / bs.block_n)))
    _, kinv = fastdetect._to_g_affine(to_g)
    nb, ok, B = len(bs), bs.usable, bs.block_n
    with np.errstate(invalid="ignore"):
        a = np.where(ok, in_g(bs.mean, bs.mean[:, int(np.argmax(ok))], kinv), 0.0)
        within = np.where(ok, axis_var_g(bs, kinv), 0.0)

    def moving(x):  # sums over the trailing wb blocks
        c = np.cumsum(np.concatenate([np.zeros((x.shape[0], 1)), x], axis=1), axis=1)
        return c[:, wb:] - c[:, :-wb]

    s_a, s_aa, s_w = moving(a), moving(a * a), moving(within)
    var = np.clip((s_w + B * (s_aa - s_a * s_a / wb)) / (wb * B - 1), 0.0, None)
    bad = np.convolve((~ok).astype(np.int64), np.ones(wb, dtype=np.int64))[wb - 1:nb]
    still = np.zeros(nb, dtype=bool)
    still[wb - 1:] = (var.max(axis=0) < threshold_g ** 2) & (bad == 0)
    return still, var, wb


def lotters_oracle(bs, to_g, *, hp_hz=0.5, lp_hz=0.5, threshold_g=0.02, order=2, per_axis=True):
    """lotters_still as numpy and scipy.signal.sosfilt compute it, before the settling blocks are
    cleared: (still, detection signals (channels, nb), per-axis within-block scatter (3, nb)) from
    the first usable block on."""
    fs_b = bs.fs / bs.block_n
    o, kinv = fastdetect._to_g_affine(to_g)
    nb = len(bs)
    b0 = int(np.argmax(bs.usable))
    g = in_g(bs.mean[:, b0:], o, kinv)
    ok = bs.usable[b0:]
    idx = np.maximum.accumulate(np.where(ok, np.arange(nb - b0), 0))  # unusable: held at the last usable
    g = g[:, idx]
    norm = g[0] * g[0]
    norm += g[1] * g[1]
    norm += g[2] * g[2]
    u = np.vstack([np.sqrt(norm), g])[:4 if per_axis else 1]  # eq. 1 and the axes
    sos_hp, sos_lp = butter_sos(order, hp_hz, "highpass", fs_b), butter_sos(order, lp_hz, "lowpass", fs_b)
    zi = sos_rest_state(sos_hp)[:, None, :] * u[None, :, 0, None]  # (sections, channels, 2)
    y, _ = signal.sosfilt(sos_hp, u, axis=1, zi=zi)
    y, _ = signal.sosfilt(sos_lp, np.abs(y), axis=1, zi=np.zeros((sos_lp.shape[0], u.shape[0], 2)))
    var = axis_var_g(bs, kinv, b0, nb)
    still = np.zeros(nb, dtype=bool)
    still[b0:] = (y.max(axis=0) < threshold_g) & ok & (var.max(axis=0) < threshold_g ** 2 * bs.block_n)
    return still, y, var, b0


# ---- block_pass ----------------------------------------------------------------------------------

def _record(n: int, fs: float, dtype, rng) -> np.ndarray:
    """A .npy-like structured record: t float64, three channels of ``dtype`` (strided fields)."""
    rec = np.zeros(n, dtype=[("t", "<f8"), ("ax", dtype), ("ay", dtype), ("az", dtype), ("temp", "<f4")])
    rec["t"] = 1.7e9 + np.arange(n) / fs  # unix time: steps are differences of large numbers
    posture = np.repeat(rng.normal(size=(n // 500 + 1, 3)), 500, axis=0)[:n]
    for c, name in enumerate(("ax", "ay", "az")):
        rec[name] = 0.5 + 0.25 * posture[:, c] + 0.002 * rng.standard_normal(n)
    rec["temp"] = 25 + 0.01 * np.arange(n) / fs
    return rec


@pytest.mark.parametrize("dtype", ["<f4", "<f8"])
@pytest.mark.parametrize("block_n", [1, 3, 10])
@pytest.mark.parametrize("n_aux", [0, 1, 2])
def test_block_pass_equals_the_float64_oracle_to_rounding(dtype, block_n, n_aux):
    rng = np.random.default_rng(block_n * 10 + n_aux)
    fs = 100.0
    n = 4 * 1000 * block_n + 7  # a last partial block, left out
    rec = _record(n, fs, dtype, rng)
    x = np.column_stack([rec["ax"], rec["ay"], rec["az"]])
    aux = None if n_aux == 0 else np.column_stack([rec["temp"].astype(np.float64)] * n_aux) * np.arange(1, n_aux + 1)
    bs = fastdetect.block_stats(rec["t"], lambda c, i, j: rec[("ax", "ay", "az")[c]][i:j], n, fs, block_n=block_n,
                                aux=aux, threads=2)
    mean, scatter, mean_tol, scatter_tol, aux_mean, usable = block_oracle(x, rec["t"], fs, block_n, aux)
    assert bs.scatter.dtype == np.float32 and bs.mean.dtype == np.float64
    np.testing.assert_array_equal(bs.usable, usable)
    assert np.all(np.abs(bs.mean - mean) <= mean_tol)
    # the kernel's float64 scatter is rounded to float32: half an ulp of float32 more
    assert np.all(np.abs(bs.scatter.astype(np.float64) - scatter) <= scatter_tol + U32 * np.abs(scatter))
    np.testing.assert_allclose(bs.aux, aux_mean, rtol=4 * block_n * U64, atol=0)
    assert usable.all() and (block_n == 1 or bs.scatter.max() > 0)


def test_block_pass_flags_each_bad_sample_and_step():
    rng = np.random.default_rng(5)
    fs, B, n = 50.0, 5, 5000
    rec = _record(n, fs, "<f4", rng)
    aux = rec["temp"].astype(np.float64)
    rec["ax"][17] = np.nan
    rec["ay"][333] = np.inf
    rec["az"][1000] = -np.inf
    aux[2222] = np.nan
    rec["t"][3001] = rec["t"][3000]  # a repeated time
    rec["t"][3500:] += 0.5  # a gap
    rec["t"][3700:] += 0.015  # a step of 1.75 / fs: just too long
    rec["t"][3800:] += 0.009  # 1.45 / fs: still a usable step
    rec["t"][4000:] -= 2.0  # backwards
    rec["t"][4444] = np.nan
    x = np.column_stack([rec["ax"], rec["ay"], rec["az"]])
    *_, usable = block_oracle(x, rec["t"], fs, B, aux[:, None])
    bs = fastdetect.block_stats(rec["t"], lambda c, i, j: rec[("ax", "ay", "az")[c]][i:j], n, fs, block_n=B, aux=aux)
    np.testing.assert_array_equal(bs.usable, usable)
    # the NaN time spoils the steps into and out of its sample (4444: block 888, 4445: block 889)
    assert sorted(np.flatnonzero(~usable)) == [3, 66, 200, 444, 600, 700, 740, 800, 888, 889]


def test_block_pass_converts_integer_and_mixed_channels():
    rng = np.random.default_rng(2)
    n, fs = 3000, 30.0
    counts = rng.integers(-2048, 2048, size=(n, 3)).astype(np.int16)
    t = np.arange(n) / fs
    bs = fastdetect.block_stats(t, lambda c, i, j: counts[i:j, c], n, fs, block_n=3)
    mean, *_ = block_oracle(counts, t, fs, 3)
    np.testing.assert_allclose(bs.mean, mean, rtol=0, atol=1e-9)
    mixed = [counts[:, 0].astype(np.float32), counts[:, 1].astype(np.float64), counts[:, 2].astype(np.float32)]
    bm = fastdetect.block_stats(t, lambda c, i, j: mixed[c][i:j], n, fs, block_n=3)
    np.testing.assert_array_equal(bm.mean, bs.mean)


def _outputs(nb: int, k: int = 0):
    return (np.empty((3, nb)), np.empty((6, nb), np.float32), np.empty((k, nb)), np.empty(nb, bool))


@pytest.mark.parametrize("change, error, words", [
    (dict(x0=np.arange(40, dtype=np.int32)), TypeError, "channel 0 must hold native float32 or float64"),
    (dict(x1=np.zeros((40, 1))), ValueError, "channel 1 must be 1-D"),
    (dict(x2=np.zeros(39)), ValueError, "one length and one float type"),
    (dict(x2=np.zeros(40, dtype=np.float32)), ValueError, "one length and one float type"),
    (dict(block_n=3), ValueError, "divide the chunk length 40"),
    (dict(block_n=0), ValueError, "block_n must be >= 1"),
    (dict(t=np.zeros(42)), ValueError, "t must hold the chunk's 40 times"),
    (dict(t=np.zeros(40, dtype=np.float32)), TypeError, "t must hold native float64"),
    (dict(aux=np.zeros((39, 1))), ValueError, "aux must have the chunk's 40 rows"),
    (dict(b0=7), ValueError, "blocks [7, 17) lie outside the 10 output blocks"),
    (dict(b0=-1), ValueError, "lie outside"),
    (dict(mean=np.empty((3, 9))), ValueError, "mean must hold 30 items, got 27"),
    (dict(mean=np.empty((10, 3)).T), TypeError, "mean must be a C-contiguous writable float64"),
    (dict(scatter=np.empty((6, 10))), TypeError, "scatter must hold float32"),
    (dict(usable=np.empty(10, np.uint8)), TypeError, "usable must hold bool"),
    (dict(aux_mean=np.empty((1, 10))), ValueError, "aux_mean must hold 0 items"),
    (dict(x0=b"not an array of floats"), TypeError, "channel 0 must hold native float32 or float64"),
    (dict(x0=3.0), TypeError, "channel 0 must be an array of floats"),
    (dict(mean=bytes(240)), TypeError, "mean must be a C-contiguous writable float64"),
])
def test_block_pass_refuses_bad_buffers_by_name(change, error, words):
    good = dict(x0=np.zeros(40), x1=np.zeros(40), x2=np.zeros(40), t=np.arange(40.0), aux=None, block_n=4, b0=0,
                max_step=1.5)
    good.update(zip(("mean", "scatter", "aux_mean", "usable"), _outputs(10)))
    good.update(change)
    with pytest.raises(error) as exc:
        block_pass(*good.values())
    assert words in str(exc.value)


def test_block_pass_reads_big_endian_data_through_a_copy():
    n, fs = 600, 10.0
    x = np.random.default_rng(1).normal(size=(n, 3)).astype(">f4")
    t = np.arange(n, dtype=">f8") / fs
    bs = fastdetect.block_stats(t, lambda c, i, j: x[i:j, c], n, fs, block_n=2)
    mean, *_ = block_oracle(x.astype(np.float64), t.astype(np.float64), fs, 2)
    np.testing.assert_allclose(bs.mean, mean, rtol=0, atol=1e-15)


# ---- the Lötters chain ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def daily_blocks():
    sim = simulate("daily_living", seed=4, duration=3600.0)
    t, raw = sim.samples["t"], raw_triad(sim.samples).copy()
    raw[15_000:15_040, 1] = np.nan  # unusable blocks inside the recording: held at the last usable one
    raw[:35, 0] = np.nan  # and at its start: the chain starts at the first usable block
    bs = fastdetect.block_stats(t, lambda c, i, j: raw[i:j, c], raw.shape[0], 100.0)
    return bs, Calibration.from_dict(sim.truth["calibration"])


def frame_and_threshold(truth: Calibration, frame: str) -> tuple[Calibration | None, float]:
    """The detector's frame (the true calibration, one with skewed axes, or raw units) and its 0.02 g
    threshold in that frame's units."""
    skew = np.array([[1, 0.02, 0], [0, 1, -0.03], [0.01, 0, 1]])
    to_g = {"truth": truth, "raw": None, "skewed": Calibration("skewed", truth.offset, truth.sensitivity @ skew)}[frame]
    return to_g, 0.02 if to_g is not None else 0.02 * float(np.mean(np.diag(truth.sensitivity)))


@pytest.mark.parametrize("per_axis", [True, False])
@pytest.mark.parametrize("order", [2, 4])
@pytest.mark.parametrize("frame", ["truth", "skewed", "raw"])
def test_lotters_chain_is_the_numpy_scipy_form_within_rounding(daily_blocks, per_axis, order, frame):
    bs, truth = daily_blocks
    to_g, thr = frame_and_threshold(truth, frame)
    still, y, var, b0 = lotters_oracle(bs, to_g, threshold_g=thr, order=order, per_axis=per_axis)
    o, kinv = fastdetect._to_g_affine(to_g)
    fs_b = bs.fs / bs.block_n
    sos_hp, sos_lp = butter_sos(order, 0.5, "highpass", fs_b), butter_sos(order, 0.5, "lowpass", fs_b)
    got = np.zeros(len(bs), dtype=bool)
    trace = np.full((7, len(bs)), np.nan)
    lotters_chain(bs.mean, bs.usable, bs.scatter, o, kinv, sos_hp, sos_lp, np.ascontiguousarray(sos_rest_state(sos_hp)),
                  y.shape[0], thr, thr ** 2 * bs.block_n, b0, got, trace)
    assert b0 == 4
    # every detection signal to the rounding bound: the high-pass's reaches the low-pass through the
    # rectifier (1-Lipschitz) and the low-pass's input gain
    u_max = float(np.abs(np.vstack([np.sqrt((in_g(bs.mean[:, b0:], o, kinv)[:, bs.usable[b0:]] ** 2).sum(axis=0))]))
                  .max()) * 1.01 if frame != "raw" else float(np.nanmax(np.abs(bs.mean))) * 2
    hp_bound = sosfilt_difference_bound(sos_hp, u_max, u_max * np.abs(sos_rest_state(sos_hp)).max())
    bound = hp_bound * cascade_gains(sos_lp)[0] + sosfilt_difference_bound(sos_lp, u_max * (1 + cascade_gains(sos_hp)[0]), 0.0)
    assert bound < 1e-3 * thr
    assert np.max(np.abs(trace[:y.shape[0], b0:] - y)) <= bound
    usable = bs.usable[b0:]  # an unusable block's scatter may be NaN: it is not still either way
    np.testing.assert_array_equal(trace[4:, b0:][:, usable], var[:, usable])  # numpy's elementwise operations
    clear = np.ones(len(bs), dtype=bool)  # blocks whose every signal lies farther than the bound from thr
    clear[b0:] = (np.abs(y - thr) > bound).all(axis=0)
    np.testing.assert_array_equal(got[clear], still[clear])
    assert clear.mean() > 0.99
    assert 0.2 < still.mean() < 0.9  # the comparison covers both decisions
    # and lotters_still is the chain plus the settling blocks
    public = fastdetect.lotters_still(bs, to_g, threshold_g=thr, order=order, per_axis=per_axis)
    settle = settle_samples(sos_hp, 0.0, fs_b, 0.5) + settle_samples(sos_lp, 1.0, fs_b, 0.5)
    still[b0:b0 + settle] = False
    assert settle > 0
    np.testing.assert_array_equal(public[clear], still[clear])


def test_lotters_chain_refuses_bad_buffers_by_name(daily_blocks):
    bs, _ = daily_blocks
    sos = butter_sos(2, 0.5, "highpass", 10.0)
    rest = np.ascontiguousarray(sos_rest_state(sos))
    args = dict(mean=bs.mean, usable=bs.usable, scatter=bs.scatter, o=np.zeros(3), kinv=np.eye(3), hp=sos, lp=sos,
                rest=rest, chans=4, thr=0.02, var=1e-3, b0=0, still=np.zeros(len(bs), bool))
    cases = [
        (dict(mean=bs.mean[:, :-1].copy()), ValueError, "mean must hold"),
        (dict(scatter=bs.scatter.astype(np.float64)), TypeError, "scatter must hold float32"),
        (dict(kinv=np.eye(2)), ValueError, "kinv must hold 9 items"),
        (dict(hp=np.zeros((1, 5))), ValueError, "sos_hp and sos_lp must be (sections, 6)"),
        (dict(lp=np.zeros((9, 6))), ValueError, "1 to 8 sections"),
        (dict(rest=np.zeros(4)), ValueError, "rest_hp must hold 2 items"),
        (dict(chans=5), ValueError, "channels must be 1 (the norm) to 4"),
        (dict(b0=len(bs) + 1), ValueError, "first block"),
        (dict(still=np.zeros(len(bs), bool)[::-1]), TypeError, "still must be a C-contiguous writable bool"),
        (dict(still=np.zeros(len(bs) - 1, bool)), ValueError, "still must hold"),
    ]
    for change, error, words in cases:
        with pytest.raises(error) as exc:
            lotters_chain(*{**args, **change}.values())
        assert words in str(exc.value), change
    with pytest.raises(ValueError, match="trace must hold"):
        lotters_chain(*args.values(), np.zeros((7, 3)))


@pytest.mark.parametrize("window_s", [0.1, 1.0, 2.5])
@pytest.mark.parametrize("frame", ["truth", "skewed", "raw"])
def test_variance_chain_is_the_numpy_form_bit_for_bit(daily_blocks, window_s, frame):
    bs, truth = daily_blocks
    to_g, thr = frame_and_threshold(truth, frame)
    still, var, wb = variance_oracle(bs, to_g, window_s=window_s, threshold_g=thr)
    _, kinv = fastdetect._to_g_affine(to_g)
    got, trace = np.zeros(len(bs), dtype=bool), np.full((3, len(bs)), np.nan)
    variance_chain(bs.mean, bs.usable, bs.scatter, np.ascontiguousarray(bs.mean[:, int(np.argmax(bs.usable))]), kinv,
                   wb, bs.block_n, thr ** 2, got, trace)
    np.testing.assert_array_equal(trace[:, wb - 1:], var)  # every window's variances, bit for bit
    np.testing.assert_array_equal(got, still)
    np.testing.assert_array_equal(fastdetect.variance_still(bs, to_g, window_s=window_s, threshold_g=thr), still)
    assert 0.2 < still.mean() < 0.9 and not still[1500:1504].any()  # both decisions; the NaN blocks are not still


def test_variance_chain_refuses_bad_arguments_by_name(daily_blocks):
    bs, _ = daily_blocks
    args = dict(mean=bs.mean, usable=bs.usable, scatter=bs.scatter, ref=np.zeros(3), kinv=np.eye(3), wb=10, B=10,
                thr2=4e-4, still=np.zeros(len(bs), bool))
    cases = [
        (dict(wb=0), ValueError, "need 1 to 4096 blocks"),
        (dict(wb=5000), ValueError, "need 1 to 4096 blocks"),
        (dict(ref=np.zeros(2)), ValueError, "ref must hold 3 items"),
        (dict(scatter=bs.scatter[:, :-1].copy()), ValueError, "scatter must hold"),
        (dict(still=np.zeros(len(bs), np.int8)), TypeError, "still must hold bool"),
    ]
    for change, error, words in cases:
        with pytest.raises(error) as exc:
            variance_chain(*{**args, **change}.values())
        assert words in str(exc.value), change


@pytest.mark.parametrize("sections", [1, 2, 3])
def test_sosfilt_is_scipys_within_rounding(sections):
    rng = np.random.default_rng(sections)
    sos = signal.butter(2 * sections, [0.05, 0.3], "bandpass", output="sos")[:sections]
    x = rng.normal(size=(3, 5000))
    zi = rng.normal(size=(3, sections, 2))
    want, zf = signal.sosfilt(sos, x, axis=1, zi=np.moveaxis(zi, 1, 0))
    got, z = x.copy(), zi.copy()
    sosfilt(np.ascontiguousarray(sos), got, z)
    bound = sosfilt_difference_bound(sos, np.abs(x).max(), np.abs(zi).max(), n=x.shape[1])
    assert np.abs(got - want).max() <= bound and bound < 1e-5 * np.abs(want).max()  # not vacuous
    assert np.abs(z - np.moveaxis(zf, 0, 1)).max() <= bound * (1 + np.abs(sos).max())
    with pytest.raises(ValueError, match=f"zi must hold {3 * sections * 2} items"):
        sosfilt(np.ascontiguousarray(sos), got, np.zeros((3, sections + 2, 2)))
    with pytest.raises(ValueError, match="x must be 2-D"):
        sosfilt(np.ascontiguousarray(sos), got[0].copy(), z[0].copy())


def test_scan_chunk_refuses_bad_buffers_by_name():
    from gravcal.core._scankernel import scan_chunk

    good = dict(t=np.arange(10.0), x0=np.zeros(10), x1=np.zeros(10), x2=np.zeros(10), prev=None, state=np.zeros(14),
                runs=np.zeros((2, 2), np.int64))
    cases = [
        (dict(t=np.arange(10, dtype=np.int64)), TypeError, "t must hold native float64"),
        (dict(x1=np.zeros(9)), ValueError, "must have one length (10)"),
        (dict(x2=np.zeros(10, np.float32)), ValueError, "the channels one float type"),
        (dict(prev=np.zeros(3)), ValueError, "prev must hold 4 items"),
        (dict(state=np.zeros(13)), ValueError, "state must hold 14 items"),
        (dict(state=np.zeros(28)[::2]), TypeError, "state must be a C-contiguous writable float64"),
        (dict(runs=np.zeros((2, 2), np.int32)), TypeError, "runs must hold int64"),
        (dict(runs=np.zeros(5, np.int64)), ValueError, "an even number of int64"),
        (dict(runs=np.zeros((0, 2), np.int64)), ValueError, "room for 0 runs"),  # the zeros are one run
    ]
    for change, error, words in cases:
        with pytest.raises(error) as exc:
            scan_chunk(*{**good, **change}.values())
        assert words in str(exc.value), change
    assert scan_chunk(*good.values()) == (1, 9)  # and the good arguments pass: one run of 9 steps


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("min_run", [1, 3, 10])
@pytest.mark.parametrize("with_prev", [False, True])
def test_scan_chunk_runs_are_chunk_runs_of_the_repeated_steps(seed, dtype, min_run, with_prev):
    """The kernel's runs equal core.repeats.chunk_runs of repeated_steps (the numpy form), runs at the
    chunk's ends and a first row equal to ``prev`` included."""
    from gravcal.core._scankernel import scan_chunk
    from gravcal.core.repeats import chunk_runs, repeated_steps

    rng = np.random.default_rng(seed)
    m = 3000
    x = rng.integers(0, 3, size=(m + 1, 3)).astype(dtype)  # row 0: the row before the chunk
    for start in rng.integers(0, m - 40, 12):
        x[start:start + rng.integers(2, 40)] = x[start]
    x[:6] = x[0]  # a run at the chunk's start (and across it, with prev)
    x[-5:] = x[-5]  # and at its end
    t = np.arange(m + 1, dtype=np.float64)
    rows, prev = (x[1:], np.array([t[0], *x[0]], dtype=np.float64)) if with_prev else (x[1:], None)
    same = repeated_steps(x if with_prev else x[1:])  # the chunk's steps
    starts, lengths, n_rep = chunk_runs(same, min_run)
    runs = np.empty((m // min_run + 2, 2), dtype=np.int64)
    n_runs, got_rep = scan_chunk(t[1:], rows[:, 0], rows[:, 1], rows[:, 2], prev, np.array(
        [np.inf] * 3 + [-np.inf] * 3 + [0.0] * 6 + [np.inf, 1.0]), runs, min_run)
    assert got_rep == n_rep > 0
    np.testing.assert_array_equal(runs[:n_runs, 0], starts)
    np.testing.assert_array_equal(runs[:n_runs, 1], lengths)
    assert starts[0] == 0 and starts[-1] + lengths[-1] == same.shape[0]


# ---- window statistics ---------------------------------------------------------------------------

def window_oracle(bs, ps, pe):
    """The windows' mean, scatter and aux means in numpy, with bounds of their float64 rounding."""
    mean, scat, aux, mean_tol, scat_tol = [], [], [], [], []
    B = bs.block_n
    for a, b in zip(ps, pe):
        n = b - a
        d = bs.mean[:, a:b] - bs.mean[:, a, None]
        s, ad = d.sum(axis=1), np.abs(d)
        q = np.array([(d[i] * d[j]).sum() for i, j in zip(I6, J6)])
        w = bs.scatter[:, a:b].astype(np.float64).sum(axis=1)
        mean.append(bs.mean[:, a] + s / n)
        scat.append(w + B * (q - s[I6] * s[J6] / n))
        aux.append(bs.aux[:, a:b].mean(axis=1))
        # sums of n terms err by <= (n - 1) u Σ|term| either side; a few u more for the rest
        mean_tol.append(2 * (n + 2) * U64 * (ad.sum(axis=1) / n + np.abs(mean[-1])))
        prods = np.array([(ad[i] * ad[j]).sum() for i, j in zip(I6, J6)])
        scat_tol.append(2 * (n + 4) * U64 * (np.abs(bs.scatter[:, a:b]).sum(axis=1) + B * (prods + np.abs(s[I6] * s[J6]) / n)))
    return (np.array(mean).T, np.array(scat).T, np.array(aux).T, np.array(mean_tol).T, np.array(scat_tol).T)


def test_window_sums_equal_the_numpy_form_to_rounding(daily_blocks):
    bs, truth = daily_blocks
    aux = np.vstack([np.linspace(20, 30, len(bs)), 1.5 + np.cos(np.arange(len(bs)))])  # no cancelling sums
    bs = fastdetect.BlockStats(bs.fs, bs.block_n, bs.mean, bs.scatter, aux, bs.usable)
    rng = np.random.default_rng(8)
    ps = np.sort(rng.integers(1600, len(bs) - 700, 300))  # after the fixture's NaN blocks
    pe = ps + rng.integers(1, 600, 300)  # overlapping, one-block and 60 s windows alike
    mean, scat, amean = fastdetect._window_sums(bs, ps, pe)
    want, want_scat, want_aux, mean_tol, scat_tol = window_oracle(bs, ps, pe)
    assert np.all(np.abs(mean - want) <= mean_tol)
    assert np.all(np.abs(scat - want_scat) <= scat_tol)
    np.testing.assert_allclose(amean, want_aux, rtol=1e-13)
    assert np.abs(scat).max() > 0


def test_window_sums_refuse_ranges_outside_the_blocks(daily_blocks):
    bs, _ = daily_blocks
    for ps, pe in (([5], [5]), ([-1], [3]), ([0], [len(bs) + 1]), ([7], [3])):
        with pytest.raises(ValueError, match="not a non-empty range of the"):
            fastdetect._window_sums(bs, np.array(ps), np.array(pe))
