"""numpy reference of core/_blockkernels.c (the offline block detector's loops, core/fastdetect.py).

block_pass, variance_chain and window_sums do the kernel's float64 operations in its order (each running sum
left to right, elementwise over the blocks or windows), so the two agree bit for bit. sosfilt and the
Lötters chain's filters are scipy.signal.sosfilt, which the kernel's cascade reproduces: the two agree to
the rounding of the filters' recursions (tests/core/test_fastdetect_kernels.py derives the bound).
"""
from __future__ import annotations

import numpy as np

I6 = np.array([0, 1, 2, 0, 0, 1])
J6 = np.array([0, 1, 2, 1, 2, 2])


def block_pass(x0, x1, x2, t, aux, block_n, b0, max_step, mean, scatter, aux_mean, usable) -> None:
    """Block statistics of one chunk (core.fastdetect.block_stats) written to blocks [b0, b0 + m): per block
    of B samples, with d = x - x[first], mean = x[first] + Σd · (1/B), scatter = Σ d_i d_j - Σd_i · (Σd_j / B)
    (as float32), the aux means, usable when every step into a sample lies in (0, max_step] and the sums are
    finite. t holds the chunk's times, or one more before them (else the first step counts as good)."""
    xs = [np.asarray(x) for x in (x0, x1, x2)]
    L, B = xs[0].shape[0], int(block_n)
    if B < 1 or L % B:
        raise ValueError(f"block_n must be >= 1 and divide the chunk length {L}, got {B}")
    m, nb = L // B, usable.shape[0]
    if not 0 <= b0 <= nb - m:
        raise ValueError(f"blocks [{b0}, {b0 + m}) lie outside the {nb} output blocks")
    if m == 0:
        return
    v = [x.astype(np.float64).reshape(m, B) for x in xs]
    t = np.asarray(t, dtype=np.float64)
    before = t[0] - 0.5 * max_step if t.shape[0] == L else t[0]
    tt = t[t.shape[0] - L:]
    with np.errstate(invalid="ignore", over="ignore"):
        dt = np.diff(tt, prepend=before)
        ok = ((dt > 0.0) & (dt <= max_step)).reshape(m, B).all(axis=1)
        r = [c[:, 0] for c in v]
        a = [np.zeros(m) for _ in range(3)]
        q = [np.zeros(m) for _ in range(6)]
        for k in range(B):
            d = [v[c][:, k] - r[c] for c in range(3)]
            for c in range(3):
                a[c] += d[c]
            for p in range(6):
                q[p] += d[I6[p]] * d[J6[p]]
        inv_B = 1.0 / float(B)
        mb = [a[c] * inv_B for c in range(3)]
        w = [q[p] - a[I6[p]] * mb[J6[p]] for p in range(6)]
        mo = mean.reshape(3, nb)
        so = scatter.reshape(6, nb)
        for c in range(3):
            mo[c, b0:b0 + m] = r[c] + mb[c]
        total = mo[0, b0:b0 + m] + mo[1, b0:b0 + m]
        total += mo[2, b0:b0 + m]
        for p in range(6):
            so[p, b0:b0 + m] = w[p].astype(np.float32)
            total += w[p]
        use = ok & (total * 0.0 == 0.0)
        if aux is not None:
            ax = np.asarray(aux, dtype=np.float64).reshape(L, -1)
            k_aux = ax.shape[1]
            am = aux_mean.reshape(k_aux, nb)
            for j in range(k_aux):
                col = ax[:, j].reshape(m, B)
                s = np.zeros(m)
                for k in range(B):
                    s += col[:, k]
                am[j, b0:b0 + m] = s / float(B)
                use &= np.isfinite(am[j, b0:b0 + m])
    usable[b0:b0 + m] = use


def _in_g(mean: np.ndarray, o: np.ndarray, K: np.ndarray) -> np.ndarray:
    """K (mean - o) for channel-major rows (3, n): g_i = Σ_j K_ij d_j from 0.0 in j order."""
    g = np.zeros((3, mean.shape[1]))
    for j in range(3):
        d = mean[j] - o[j]
        for i in range(3):
            g[i] += K[i, j] * d
    return g


def _axis_scatter(scatter: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Per-axis within-block scatter in g² (3, n): Σ_p c_ip W_p from 0.0, c_ip = K_iI K_iJ (twice off the diagonal)."""
    w = np.zeros((3, scatter.shape[1]))
    for i in range(3):
        for p in range(6):
            w[i] += K[i, I6[p]] * K[i, J6[p]] * (1.0 if I6[p] == J6[p] else 2.0) * scatter[p].astype(np.float64)
    return w


def lotters_chain(mean, usable, scatter, o, kinv, sos_hp, sos_lp, rest_hp, channels, threshold, var_limit, b0, still,
                  trace=None, first=0, gate=True, vector=True) -> None:
    """Still blocks from b0 on by Lötters' detector (core.fastdetect.lotters_still): K⁻¹ (mean - o), an
    unusable block held at the last usable one, (|a|, x, y, z) channels [first, channels) high-passed from
    rest on block b0, rectified, low-passed, each below threshold; usable; with gate, every axis's
    within-block scatter below var_limit. trace (7, nb): the channels' signals and the per-axis scatters."""
    from scipy import signal  # noqa: PLC0415 (only this reference needs scipy.signal)

    if not 1 <= channels <= 4:
        raise ValueError(f"channels must be 1 (the norm) to 4 (norm and axes), got {channels}")
    nb = usable.shape[0]
    if not 0 <= b0 <= nb:
        raise ValueError(f"first block {b0} outside the {nb} blocks")
    if b0 == nb:
        return
    K = np.asarray(kinv, dtype=np.float64).reshape(3, 3)
    mean = np.asarray(mean, dtype=np.float64).reshape(3, nb)
    ok = np.asarray(usable, dtype=bool)[b0:]
    n = nb - b0
    keep = ok.copy()
    keep[0] = True  # block b0 starts the hold whether usable or not
    held = np.maximum.accumulate(np.where(keep, np.arange(n), 0))
    with np.errstate(invalid="ignore", over="ignore"):
        g = _in_g(mean[:, b0:], np.asarray(o, dtype=np.float64), K)[:, held]
        norm = g[0] * g[0]
        norm += g[1] * g[1]
        norm += g[2] * g[2]
        u = np.vstack([np.sqrt(norm), g])[first:channels]
        decide = ok.copy()
        if gate:
            w = _axis_scatter(np.asarray(scatter, dtype=np.float32).reshape(6, nb)[:, b0:], K)
            decide &= (w < var_limit).all(axis=0)
            if trace is not None:
                trace.reshape(7, nb)[4:, b0:] = w
        hp, lp = np.asarray(sos_hp, dtype=np.float64), np.asarray(sos_lp, dtype=np.float64)
        zi = np.asarray(rest_hp, dtype=np.float64).reshape(-1, 2)[:, None, :] * u[None, :, 0, None]
        y, _ = signal.sosfilt(hp, u, axis=1, zi=zi)
        y, _ = signal.sosfilt(lp, np.abs(y), axis=1, zi=np.zeros((lp.shape[0], u.shape[0], 2)))
        decide &= (y < threshold).all(axis=0)
    if trace is not None:
        trace.reshape(7, nb)[first:channels, b0:] = y
    still[b0:] = decide


def chain_lanes() -> bool:
    """True: one lotters_chain call on the four channels beats two half calls on two threads (here, as in the
    kernel's vector lanes: the halves would share one interpreter lock)."""
    return True


def variance_chain(mean, usable, scatter, ref, kinv, window_blocks, block_n, threshold2, still, trace=None) -> None:
    """Still blocks by the per-axis moving variance (core.fastdetect.variance_still): a = K⁻¹ (mean - ref)
    and the per-axis scatter w in g² (0 for an unusable block), their trailing sums over window_blocks blocks
    as differences of running sums, the window's variance (s_w + B (s_aa - s_a s_a / wb)) / (wb B - 1)
    clipped at 0, below threshold2 on every axis with no unusable block. trace (3, nb): the variances."""
    wb, B = int(window_blocks), int(block_n)
    if wb < 1 or wb >= 4097 or B < 1:
        raise ValueError(f"window of {wb} blocks of {B} samples: need 1 to 4096 blocks")
    nb = usable.shape[0]
    ok = np.asarray(usable, dtype=bool)
    K = np.asarray(kinv, dtype=np.float64).reshape(3, 3)
    x = np.zeros((9, nb + 1))  # column 0: the running sums' start
    with np.errstate(invalid="ignore", over="ignore"):
        a = _in_g(np.asarray(mean, dtype=np.float64).reshape(3, nb), np.asarray(ref, dtype=np.float64), K)
        w = _axis_scatter(np.asarray(scatter, dtype=np.float32).reshape(6, nb), K)
        x[0:3, 1:] = np.where(ok, a, 0.0)
        x[3:6, 1:] = np.where(ok, a * a, 0.0)
        x[6:9, 1:] = np.where(ok, w, 0.0)
        c = np.add.accumulate(x, axis=1)  # left to right, as the kernel's running sums
        bad = np.concatenate([[0], np.cumsum(~ok)])
        out = np.zeros(nb, dtype=bool)
        if nb >= wb:
            at, fr = np.arange(wb, nb + 1), np.arange(0, nb + 1 - wb)
            s = c[:, at] - c[:, fr]
            var = (s[6:9] + float(B) * (s[3:6] - s[0:3] * s[0:3] / float(wb))) / float(wb * B - 1)
            var = np.where(var < 0.0, 0.0, var)
            out[wb - 1:] = (var < threshold2).all(axis=0) & (bad[at] - bad[fr] == 0)
            if trace is not None:
                trace.reshape(3, nb)[:, wb - 1:] = var
    still[:] = out


def sosfilt(sos, x, zi) -> None:
    """x (signals, n) and zi (signals, sections, 2) float64, filtered in place as scipy's sosfilt."""
    from scipy import signal  # noqa: PLC0415 (only this reference needs scipy.signal)

    if x.ndim != 2:
        raise ValueError(f"x must be 2-D (signals, samples), got {x.ndim}-D")
    sos = np.asarray(sos, dtype=np.float64).reshape(-1, 6)
    z = zi.reshape(x.shape[0], sos.shape[0], 2)
    if x.shape[1] == 0:
        return
    y, zf = signal.sosfilt(sos, x, axis=1, zi=np.moveaxis(z, 1, 0))
    x[:] = y
    z[:] = np.moveaxis(zf, 0, 1)


def window_sums(mean, scatter, aux, ps, pe, block_n, window_mean, window_scatter, window_aux) -> None:
    """Mean (3, m), scatter (6, m) and aux means (k, m) of the samples of block ranges [ps, pe): with d the
    block means minus the window's first, mean = r + Σd / n, scatter = Σ W + B (Σ d_i d_j - Σd_i Σd_j / n),
    aux Σ aux / n; every sum left to right over the window's blocks."""
    mean = np.asarray(mean, dtype=np.float64)
    nb = mean.shape[1]
    so = np.asarray(scatter, dtype=np.float32).reshape(6, nb)
    ao = np.asarray(aux, dtype=np.float64).reshape(-1, nb)
    ps, pe = np.asarray(ps, dtype=np.int64), np.asarray(pe, dtype=np.int64)
    bad = ~((0 <= ps) & (ps < pe) & (pe <= nb))
    if bad.any():
        w = int(np.flatnonzero(bad)[0])
        raise ValueError(f"window {w}: blocks [{ps[w]}, {pe[w]}) are not a non-empty range of the {nb} blocks")
    m, k = ps.shape[0], ao.shape[0]
    wm, ws, wa = window_mean.reshape(3, m), window_scatter.reshape(6, m), window_aux.reshape(k, m)
    for w in range(m):
        lo, hi = int(ps[w]), int(pe[w])
        n = float(hi - lo)
        r = mean[:, lo]
        d = mean[:, lo:hi] - r[:, None]
        rows = np.concatenate([d, d[I6] * d[J6], so[:, lo:hi].astype(np.float64), ao[:, lo:hi]])
        s = np.add.accumulate(rows, axis=1)[:, -1]  # left to right
        a, q, W, sa = s[0:3], s[3:9], s[9:15], s[15:]
        wm[:, w] = r + a / n
        ws[:, w] = W + float(block_n) * (q - a[I6] * a[J6] / n)
        wa[:, w] = sa / n
