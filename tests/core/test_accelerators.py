"""Each compiled offline kernel against its numpy reference beside it (core.accelerator): bit for bit where
the kernel does the reference's operations in its order; to a bound derived from the operation count where
they round differently (the filters' recursions, OpenBLAS's fused products). The loader's choice is tested
too: GRAVCAL_NATIVE=0 gives the references, an absent extension gives its reference."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from gravcal.core.accelerator import is_native, kernels
from gravcal.core.butterworth import butter_sos, sos_rest_state

from filter_bounds import U, cascade_gains, sosfilt_difference_bound
from test_jacobians import sensor_like as _sensor_like  # the same sensor-like inputs as the Jacobian tests

OFFLINE = ("gravcal.core._fitsums", "gravcal.core._blockkernels", "gravcal.core._scankernel",
           "gravcal.core.detectors._movingstd", "gravcal.core.estimators._jacobians", "gravcal.io._pages")


def pair(name: str):
    """(compiled, reference): the compiled module must be built where these tests run."""
    import importlib

    return importlib.import_module(name), importlib.import_module(name + "_reference")


# ---- the loader ----------------------------------------------------------------------------------

def test_every_offline_kernel_has_its_reference_with_the_same_functions():
    for name in OFFLINE:
        compiled, ref = pair(name)
        public = {f for f in dir(compiled) if not f.startswith("_")}
        assert public <= set(dir(ref)), (name, public - set(dir(ref)))
        assert is_native(compiled) and not is_native(ref)


def test_the_environment_forces_the_references_and_an_absent_extension_falls_back(tmp_path):
    code = ("import sys\nfrom gravcal.core import fastdetect\nfrom gravcal.core.estimators import parameterization\n"
            "print(fastdetect._kernels.__name__, parameterization._jacobians.__name__)\n"
            "print(any(m.startswith('gravcal.daemon') or m.endswith(('_fastpath', '_correctkernel', '_framekernel',"
            " '_linekernel', '_clienttable')) for m in sys.modules))\n")
    env = {**os.environ, "GRAVCAL_NATIVE": "0"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout.split()
    assert out == ["gravcal.core._blockkernels_reference", "gravcal.core.estimators._jacobians_reference", "False"]
    env["GRAVCAL_NATIVE"] = "1"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout.split()
    assert out == ["gravcal.core._blockkernels", "gravcal.core.estimators._jacobians", "False"]
    # an extension that is not there (a build without a compiler): its name cannot be found
    hide = ("import importlib.abc, sys\nclass Hide(importlib.abc.MetaPathFinder):\n"
            "    def find_spec(self, name, path, target=None):\n"
            "        if name == 'gravcal.core._blockkernels':\n"
            "            raise ModuleNotFoundError(name=name)\n"
            "sys.meta_path.insert(0, Hide())\n")
    out = subprocess.run([sys.executable, "-c", hide + code], env=env, capture_output=True, text=True,
                         check=True).stdout.split()
    assert out[0] == "gravcal.core._blockkernels_reference"


# ---- bit for bit ---------------------------------------------------------------------------------

def test_fitsums_are_their_reference_bit_for_bit():
    c, r = pair("gravcal.core._fitsums")
    rng = np.random.default_rng(1)
    for M, P in ((0, 3), (1, 1), (257, 9), (1000, 15)):
        coef, rows = rng.standard_normal(P), rng.standard_normal((M, P, 9)) * 10.0 ** rng.integers(-6, 2, (M, P, 1))
        outs = [np.full((M, 9), np.nan), np.full((M, 9), np.nan)]
        for mod, out in zip((c, r), outs):
            mod.combine(coef, rows, out, M, P, 9)
        a = rng.standard_normal((M, 3))
        a[: M // 10] *= 1e-8  # near the origin too
        J = rng.standard_normal((M, 3, P))
        hb = [(np.empty(M), np.empty((M, P))) for _ in range(2)]
        for mod, (h, B) in zip((c, r), hb):
            mod.norm_project(a, J, h, B, M, P)
        C = rng.standard_normal((M, 3, 3))
        qs = [np.empty(M), np.empty(M)]
        for mod, q in zip((c, r), qs):
            mod.quadratic(a, C, q, M)
        assert np.array_equal(outs[0], outs[1])
        assert np.array_equal(hb[0][0], hb[1][0]) and np.array_equal(hb[0][1], hb[1][1])
        assert np.array_equal(qs[0], qs[1])


def test_moving_std_is_its_reference_bit_for_bit():
    c, r = pair("gravcal.core.detectors._movingstd")
    rng = np.random.default_rng(2)
    for w, n in ((2, 0), (2, 5), (100, 3000), (7, 1)):
        y = np.cumsum(rng.standard_normal((3, w + n)) * 1e-3, axis=1)
        y[:, rng.integers(0, w + n, 3)] = 0.0  # exact ties and zero variances
        ext = np.vstack([y, y * y])
        sums0 = np.concatenate([y[:, :w].sum(axis=1), (y[:, :w] ** 2).sum(axis=1)])
        got = [(sums0.copy(), np.empty(n)) for _ in range(2)]
        for mod, (s, d) in zip((c, r), got):
            mod.moving_std(ext, w, s, d)
        assert np.array_equal(got[0][0], got[1][0])
        assert np.array_equal(got[0][1], got[1][1]) and np.array_equal(np.signbit(got[0][1]), np.signbit(got[1][1]))


def _fresh_state():
    st = np.empty(14)
    st[0:3], st[3:6], st[6:12], st[12], st[13] = np.inf, -np.inf, 0.0, np.inf, 1.0
    return st


@pytest.mark.parametrize("layout", ["record20", "record_f8", "columns_f4"])
def test_scan_chunk_is_its_reference(layout):
    c, r = pair("gravcal.core._scankernel")
    rng = np.random.default_rng(3)
    m = 5000
    kind = "<f8" if layout == "record_f8" else "<f4"
    rec = np.zeros(m, dtype=[("t", "<f8"), ("ax", kind), ("ay", kind), ("az", kind)])  # 20 bytes a row for f4
    rec["t"] = 1.7e9 + np.arange(m) / 100.0
    for name in ("ax", "ay", "az"):
        rec[name] = rng.integers(0, 4, m)
    for s in rng.integers(0, m - 50, 20):
        rec[s:s + rng.integers(2, 50)] = rec[s]
    rec["t"][100] = rec["t"][99]  # a zero step
    if layout == "columns_f4":
        cols = [np.ascontiguousarray(rec[n]) for n in ("ax", "ay", "az")]
        t = np.ascontiguousarray(rec["t"])
    else:
        cols, t = [rec[n] for n in ("ax", "ay", "az")], rec["t"]
    states = [_fresh_state(), _fresh_state()]  # one per form, carried from chunk to chunk as scan_columns does
    for lo, hi, prev in ((0, 2500, None), (2500, m, np.array([t[2499], *[x[2499] for x in cols]], dtype=float))):
        res = []
        for mod, st in zip((c, r), states):
            runs = np.zeros((hi - lo, 2), np.int64)
            n_runs, n_rep = mod.scan_chunk(t[lo:hi], *[x[lo:hi] for x in cols], prev, st, runs, 3)
            res.append((n_runs, n_rep, st.copy(), runs[:n_runs]))
        assert res[0][:2] == res[1][:2] and res[0][1] > 0
        assert np.array_equal(res[0][2], res[1][2]) and np.array_equal(res[0][3], res[1][3])
    assert states[0][6:12].min() > 1000  # the counts at the extremes add up over both chunks (~625 each)
    cols[1][1234] = np.nan
    states = [_fresh_state(), _fresh_state()]
    for mod, st in zip((c, r), states):
        mod.scan_chunk(t, *cols, None, st, None)
    assert states[0][13] == states[1][13] == 0.0 and states[0][12] == states[1][12]


def _records(n: int, fs: float, kind: str, rng, aux: bool = True) -> np.ndarray:
    """A structured record: t float64 and three channels of ``kind``; with f4 channels and no aux a row is
    20 bytes, so most rows' t sits at an address that is not a multiple of 8."""
    fields = [("t", "<f8"), ("ax", kind), ("ay", kind), ("az", kind)] + ([("temp", "<f4")] if aux else [])
    rec = np.zeros(n, dtype=fields)
    rec["t"] = 1.7e9 + np.arange(n) / fs
    posture = np.repeat(rng.normal(size=(n // 300 + 1, 3)), 300, axis=0)[:n]
    for c, name in enumerate(("ax", "ay", "az")):
        rec[name] = 0.5 + 0.25 * posture[:, c] + 0.002 * rng.standard_normal(n)
    return rec


@pytest.mark.parametrize("kind, aux", [("<f4", False), ("<f4", True), ("<f8", False)])
@pytest.mark.parametrize("block_n", [1, 3, 10])
def test_block_pass_is_its_reference_bit_for_bit(kind, aux, block_n):
    c, r = pair("gravcal.core._blockkernels")
    rng = np.random.default_rng(block_n)
    fs, nb = 100.0, 1001  # an odd number of blocks: the kernel's pairs and its last block alone
    rec = _records(nb * block_n, fs, kind, rng, aux)
    assert rec.dtype.itemsize == {("<f4", False): 20, ("<f4", True): 24, ("<f8", False): 32}[(kind, aux)]
    rec["ay"][77] = np.nan
    rec["t"][500:] += 0.013  # a step too long
    a = np.column_stack([rec["t"] - 1.7e9, rec["ax"].astype(float)]) if aux else None
    outs = []
    for mod in (c, r):
        o = (np.full((3, nb), np.nan), np.full((6, nb), np.nan, np.float32), np.full((0 if a is None else 2, nb), np.nan),
             np.zeros(nb, bool))
        half = (nb // 2) * block_n  # two chunks: the second with the time before it
        mod.block_pass(rec["ax"][:half], rec["ay"][:half], rec["az"][:half], rec["t"][:half],
                       None if a is None else a[:half], block_n, 0, 1.5 / fs, *o)
        mod.block_pass(rec["ax"][half:], rec["ay"][half:], rec["az"][half:], rec["t"][half - 1:],
                       None if a is None else a[half:], block_n, nb // 2, 1.5 / fs, *o)
        outs.append(o)
    for g, w in zip(*outs):
        assert np.array_equal(g, w, equal_nan=True)
    assert 0 < outs[0][3].sum() < nb


@pytest.fixture(scope="module")
def blocks():
    from gravcal.core import fastdetect
    from gravcal.core.calibration import Calibration
    from gravcal.core.samples import raw_triad
    from gravcal.core.simulate import simulate

    sim = simulate("daily_living", seed=4, duration=1800.0)
    t, raw = sim.samples["t"], raw_triad(sim.samples).copy()
    raw[15_000:15_040, 1] = np.nan
    raw[:35, 0] = np.nan
    bs = fastdetect.block_stats(t, lambda ch, i, j: raw[i:j, ch], raw.shape[0], 100.0)
    return bs, Calibration.from_dict(sim.truth["calibration"])


@pytest.mark.parametrize("window_b", [1, 10, 25])
def test_variance_chain_and_window_sums_are_their_reference_bit_for_bit(blocks, window_b):
    c, r = pair("gravcal.core._blockkernels")
    bs, truth = blocks
    kinv = np.linalg.inv(truth.sensitivity)
    ref = np.ascontiguousarray(bs.mean[:, int(np.argmax(bs.usable))])
    res = []
    for mod in (c, r):
        still, trace = np.zeros(len(bs), bool), np.full((3, len(bs)), np.nan)
        mod.variance_chain(bs.mean, bs.usable, bs.scatter, ref, kinv, window_b, bs.block_n, 0.02 ** 2, still, trace)
        res.append((still, trace))
    assert np.array_equal(res[0][0], res[1][0]) and np.array_equal(res[0][1], res[1][1], equal_nan=True)
    assert 0.1 < res[0][0].mean() < 0.95
    rng = np.random.default_rng(window_b)
    ps = np.sort(rng.integers(200, len(bs) - 700, 200)).astype(np.int64)
    pe = ps + rng.integers(1, 600, 200)
    aux = np.ascontiguousarray(np.vstack([np.linspace(20, 30, len(bs)), np.cos(np.arange(len(bs)))]))
    sums = []
    for mod in (c, r):
        out = (np.empty((3, 200)), np.empty((6, 200)), np.empty((2, 200)))
        mod.window_sums(bs.mean, bs.scatter, aux, ps, pe, bs.block_n, *out)
        sums.append(out)
    for g, w in zip(*sums):  # NaN where a window holds the NaN blocks, in both
        assert np.array_equal(g, w, equal_nan=True) and np.isfinite(g).mean() > 0.5


# ---- to a derived bound --------------------------------------------------------------------------

@pytest.mark.parametrize("sections", [1, 2, 3])
def test_sosfilt_is_its_reference_to_the_rounding_bound(sections):
    c, r = pair("gravcal.core._blockkernels")
    rng = np.random.default_rng(sections)
    sos = np.ascontiguousarray(np.vstack([butter_sos(2, 0.05 * (s + 1), "lowpass", 1.0) for s in range(sections)]))
    x = rng.normal(size=(3, 5000))
    zi = rng.normal(size=(3, sections, 2))
    got, zc = x.copy(), zi.copy()
    c.sosfilt(sos, got, zc)
    want, zr = x.copy(), zi.copy()
    r.sosfilt(sos, want, zr)
    bound = sosfilt_difference_bound(sos, np.abs(x).max(), np.abs(zi).max())
    assert 0 < bound < 1e-10  # tight enough to catch a wrong coefficient or order of sections
    assert np.abs(got - want).max() <= bound
    assert np.abs(zc - zr).max() <= bound * (1 + np.abs(sos).max())


@pytest.mark.parametrize("order, chans", [(2, 4), (2, 1), (4, 4)])
def test_lotters_chain_is_its_reference_to_the_rounding_bound(blocks, order, chans):
    c, r = pair("gravcal.core._blockkernels")
    bs, truth = blocks
    fs_b = bs.fs / bs.block_n
    hp, lp = butter_sos(order, 0.5, "highpass", fs_b), butter_sos(order, 0.5, "lowpass", fs_b)
    rest = np.ascontiguousarray(sos_rest_state(hp))
    o, kinv = np.asarray(truth.offset, float), np.linalg.inv(truth.sensitivity)
    b0 = int(np.argmax(bs.usable))
    res = []
    for mod in (c, r):
        still, trace = np.zeros(len(bs), bool), np.full((7, len(bs)), np.nan)
        mod.lotters_chain(bs.mean, bs.usable, bs.scatter, o, kinv, hp, lp, rest, chans, 0.02, 0.02 ** 2 * bs.block_n,
                          b0, still, trace)
        res.append((still, trace))
    (s_c, t_c), (s_r, t_r) = res
    # the inputs (|a| and the axes in g) agree bit for bit; the high-pass's rounding reaches the low-pass
    # through the rectifier (1-Lipschitz) and the low-pass's input gain
    u_max = 2.0  # |a| and each axis in g of a body-worn recording stay below 2 g
    hp_bound = sosfilt_difference_bound(hp, u_max, u_max * np.abs(rest).max())
    hp_out = u_max * (1 + cascade_gains(hp)[0])
    bound = hp_bound * cascade_gains(lp)[0] + sosfilt_difference_bound(lp, hp_out, 0.0)
    assert bound < 1e-3 * 0.02  # a thousandth of the threshold: the decisions are compared almost everywhere
    diff = np.abs(t_c[:chans, b0:] - t_r[:chans, b0:])
    assert diff.max() <= bound
    usable = bs.usable[b0:]
    assert np.array_equal(t_c[4:, b0:][:, usable], t_r[4:, b0:][:, usable])  # the gate: the same operations
    clear = (np.abs(t_r[:chans, b0:] - 0.02) > bound).all(axis=0)  # decisions away from the threshold
    assert np.array_equal(s_c[b0:][clear], s_r[b0:][clear]) and clear.mean() > 0.99
    assert 0.1 < s_c.mean() < 0.95


@pytest.mark.parametrize("M, P", [(0, 3), (5, 2), (1001, 9), (333, 15)])
def test_extended_jacobian_is_its_reference_bit_for_bit(M, P):
    c, r = pair("gravcal.core.estimators._jacobians")
    rng = np.random.default_rng(M + P)
    Kc, oc, p, dK, do, raw = _sensor_like(rng, M, P)
    full = np.concatenate([dK.reshape(M, P, 9), do], axis=2)
    rows = np.zeros((P, 12))
    rows[:, 4] = 0.3  # constant entries
    entries = np.array([(q, e) for q in range(P) for e in range(12) if e != 4], dtype=float)
    values = np.ascontiguousarray(full[:, entries[:, 0].astype(int), entries[:, 1].astype(int)])
    outs = []
    for mod in (c, r):
        a, J = np.full((M, 3), np.nan), np.full((M, 3, P), np.nan)
        mod.extended_accel_jacobian(Kc, oc, p, rows, entries, values, raw, a, J, M, P, len(entries))
        outs.append((a, J))
    assert np.array_equal(outs[0][0], outs[1][0]) and np.array_equal(outs[0][1], outs[1][1])


@pytest.mark.parametrize("M, P", [(2, 3), (17, 6), (3000, 12)])
def test_linear_jacobian_is_its_reference_to_the_rounding_bound(M, P):
    """The kernel adds each three-term product as one fused chain (OpenBLAS's order), the reference rounds
    every product and sum: each three-term sum differs by at most 2 · 3u · Σ|terms|; what follows (the norm,
    the projection, the quadratic form) is the same operations on inputs that differ by that much."""
    c, r = pair("gravcal.core.estimators._jacobians")
    rng = np.random.default_rng(P)
    Ki = np.linalg.inv(0.04 * (np.eye(3) + 0.01 * rng.standard_normal((3, 3))))
    o = 0.5 + 0.01 * rng.standard_normal(3)
    G = rng.standard_normal((P, 3, 3)) * 10.0 ** rng.integers(-3, 1, size=(P, 1, 1))
    C = rng.standard_normal((3, P))
    u = rng.standard_normal((M, 3))
    raw = (u / np.linalg.norm(u, axis=1, keepdims=True)) @ np.linalg.inv(Ki).T + o
    L = rng.standard_normal((M, 3, 3)) * 1e-4
    cov = L @ L.transpose(0, 2, 1)
    outs = []
    for mod in (c, r):
        h, B, a, v = np.empty(M), np.empty((M, P)), np.empty((M, 3)), np.empty(M)
        mod.linear_norm_jacobian(Ki, o, G, C, raw, cov, h, B, a, v, M, P)
        outs.append((h, B, a, v))
    (h1, B1, a1, v1), (h2, B2, a2, v2) = outs
    d = np.abs(raw - o)
    a_mag = d @ np.abs(Ki).T
    eps_a = 6 * U * a_mag  # per component
    assert np.all(np.abs(a1 - a2) <= eps_a)
    # h = |a|: 1-Lipschitz in a, plus its own few roundings (on both sides)
    assert np.all(np.abs(h1 - h2) <= np.linalg.norm(eps_a, axis=1) + 8 * U * h2)
    # B = Σ_i (a_i / h) J_i with J_i = -(G_i a + C_i): differences of a and h carried through the magnitudes
    rel_a = np.linalg.norm(eps_a, axis=1)[:, None] / h2[:, None]
    Jm = np.stack([(np.abs(G[:, i, :]) @ np.abs(a2).T).T + np.abs(C[i]) for i in range(3)], axis=1)  # (M, 3, P)
    uabs = np.abs(a2) / h2[:, None]
    B_mag = np.einsum("mi,mip->mp", uabs, Jm)
    J_err = np.stack([(np.abs(G[:, i, :]) @ eps_a.T).T for i in range(3)], axis=1) + 6 * U * Jm
    B_bound = np.einsum("mi,mip->mp", uabs, J_err) + 4 * rel_a * B_mag + 16 * U * B_mag
    assert np.all(np.abs(B1 - B2) <= B_bound)
    g_mag = uabs @ np.abs(Ki)
    v_mag = np.einsum("mi,mij,mj->m", g_mag, np.abs(cov), g_mag)
    assert np.all(np.abs(v1 - v2) <= (4 * rel_a[:, 0] + 6 * U) * 2 * v_mag + 20 * U * v_mag)
    if M >= 1000:  # the orders differ somewhere: the bound is what is tested
        assert np.any(a1 != a2) or np.any(B1 != B2) or np.any(v1 != v2)


def test_populate_and_its_reference_leave_the_memory_as_it_was():
    import mmap

    c, r = pair("gravcal.io._pages")
    mm = mmap.mmap(-1, 64 * mmap.PAGESIZE, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    mm[:4] = b"abcd"
    assert c.populate(mm, 0, len(mm)) == r.populate(mm, 0, len(mm))
    assert mm[:4] == b"abcd" and mm[4:8] == b"\0\0\0\0"
    with pytest.raises(ValueError, match="outside the buffer"):
        r.populate(mm, 10, len(mm))
