"""The online calibrator (order by observability + re-seeded recursion) and the one observability rule."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gravcal.core.calibration import Calibration
from gravcal.core.crlb import cap_directions, crlb, daily_living_directions, windows_on_ellipsoid
from gravcal.core.estimators.lotters import LottersBatch
from gravcal.core.estimators.online import OnlineCalibrator, WindowStore
from gravcal.core.estimators.order import select_order
from gravcal.core.estimators.parameterization import NineParameter
from seed_pool import pmap

NOISE_G, N = 0.005, 300
D = np.diag([0.125, 0.131, 0.118])
O = np.array([0.502, 0.493, 0.508])
K_MIS = D @ np.array([[1, 0.004, 0.0], [-0.003, 1, 0.0], [0.018, -0.015, 1]]) @ \
    Rotation.from_rotvec([0.02, -0.03, 0.01]).as_matrix()  # second chip tilted (+-2 %) and a frame rotation
TRUTH = Calibration("truth", O, K_MIS)
NOMINAL = Calibration("nominal", [0.5, 0.5, 0.5], np.eye(3) * 0.125)
MOUNT2 = Rotation.align_vectors([[1, 1, 1]], [[0, 0, 1.0]])[0].as_matrix()


def feed(oc: OnlineCalibrator, ws) -> list[str]:
    models = []
    for i in range(len(ws)):
        oc.update(ws.subset(np.arange(i, i + 1)))
        models.append(oc.model)
    return models


@pytest.mark.parametrize("theta", [45, 60, 75])
def test_batch_observable_flag_follows_the_order_rule(theta):
    # postures within theta of upright: the sensitivities' per-parameter std is small (< 0.5 % of 1 g: the old
    # std rule said observable), but the geometry amplifies per-window model error (order.is_observable): auto
    # chooses offsets, and LottersBatch("6") must not call its sensitivities observable
    rng = np.random.default_rng(theta)
    ws = windows_on_ellipsoid(Calibration("t", O, D), cap_directions((0, 0, 1), theta, 300, rng), noise_g=NOISE_G, n=N,
                              rng=rng)
    assert select_order(ws, start=NOMINAL, compare=False).model == "offsets"
    c6 = LottersBatch("6").fit(ws, NOMINAL)
    assert max(c6.std[n] for n in ("s_x", "s_y", "s_z")) / 0.125 < 0.005  # what the std rule alone looked at
    assert not c6.observable and "sensitivities not observable" in c6.message and "predicted error" in c6.message
    assert "use --model offsets" in c6.message
    assert LottersBatch("offsets").fit(ws, Calibration("s", NOMINAL.offset, D)).observable
    assert LottersBatch("6", tol_g=math.inf).fit(ws, NOMINAL).observable  # the rule switched off: std rule only


def test_orders_grow_with_the_postures_and_say_why():
    rng = np.random.default_rng(6)
    oc = OnlineCalibrator(NOMINAL)
    assert oc.model == "none" and not oc.calibration.observable and "nothing is determined" in oc.calibration.message
    standing = windows_on_ellipsoid(TRUTH, cap_directions((0, 0, 1), 30, 60, rng), noise_g=NOISE_G, n=N, rng=rng)
    models = feed(oc, standing)
    assert models[0] == "none" and models[-1] == "offsets", oc.reason
    cal = oc.calibration
    assert cal.model == "offsets" and cal.param_names == ["o_x", "o_y", "o_z"]
    np.testing.assert_array_equal(cal.sensitivity, NOMINAL.sensitivity)  # never sensitivities from standing
    assert "not observable: 6: predicted error" in oc.reason and cal.metadata["order"]["model"] == "offsets"
    night = windows_on_ellipsoid(TRUTH, cap_directions((0, 0, -1), 120, 140, rng), noise_g=NOISE_G, n=N, rng=rng)
    models = feed(oc, night)
    assert models[-1] == "9" and oc.comparison.startswith("cross-axis terms chosen (BIC 9"), oc.reason
    st = oc.stats()
    assert st["n_reseeds"] >= 2 and st["n_compares"] >= 1 and st["stored"] == 200


def test_store_is_bounded_and_keeps_rare_postures():
    rng = np.random.default_rng(7)
    store = WindowStore(capacity=50)
    lying = cap_directions((1, 0, 0), 5, 5, rng)
    upright = cap_directions((0, 0, 1), 5, 500, rng)
    for k, u in enumerate(np.vstack([lying, upright])):
        store.add(u * 0.125 + 0.5, np.eye(3) * 1e-6, 100.0, float(k), np.zeros(1), u)
    assert len(store) == 50 and store.evicted == 455
    ws = store.windowset()
    assert np.sum(ws.mean[:, 0] > 0.6) == 5  # every lying window survived 500 upright ones
    assert np.all(np.diff(ws.t) > 0) and ws.t[-1] == 504.0  # arrival order, the newest kept


def test_resume_recurses_on_the_saved_order_from_the_first_window():
    rng = np.random.default_rng(8)
    ws = windows_on_ellipsoid(TRUTH, cap_directions((1, 1, 1), 150, 120, rng), noise_g=NOISE_G, n=N, rng=rng)
    saved = LottersBatch("9").fit(ws.subset(np.arange(80)), NOMINAL)
    oc = OnlineCalibrator(saved, resume=True)
    assert oc.model == "9"
    cal = oc.update(ws.subset(np.arange(80, 83)))
    assert cal.model == "9" and oc.n_updates == 3 and cal.observable
    p = NineParameter(K_MIS, O)
    e = p.pack(cal.sensitivity, cal.offset) - p.pack(K_MIS, O)
    assert e @ np.linalg.solve(cal.covariance, e) < 27.9  # chi2_9 0.999 quantile


def online_daily_living_errors(seed: int, M: int = 150) -> tuple[str, str, float, float, float]:
    """One daily-living session fed to the online calibrator: its model and reason, the whitened error
    e^T F e / 9, |e|^2 and tr(CRLB) (plain values: computed in a worker process)."""
    par = NineParameter(K_MIS, O)
    rng = np.random.default_rng(seed)
    ws = windows_on_ellipsoid(TRUTH, daily_living_directions(M, rng, MOUNT2), noise_g=NOISE_G, n=N, rng=rng)
    F = crlb(ws, TRUTH, "9").fisher
    start = Calibration("s", O + rng.normal(0, 0.01, 3) * 0.125, K_MIS @ (np.eye(3) + np.diag(rng.normal(0, 0.01, 3))))
    # systematic_g=0: this simulation has no per-window model error, the observability rule's systematic term
    # would otherwise (correctly) keep the cross-axis terms of 150 daily-living windows at the 10 mg edge
    oc = OnlineCalibrator(start, systematic_g=0.0)
    feed(oc, ws)
    c = oc.calibration
    e = par.pack(c.sensitivity, c.offset) - par.pack(K_MIS, O)
    return oc.model, str(oc.reason), float(e @ F @ e / 9), float(e @ e), float(np.trace(np.linalg.inv(F)))


@pytest.mark.slow
def test_online_efficiency_on_daily_living():
    """Efficiency tr(CRLB)/tr(MSE) >= 0.8 (issue 3's goal for the recursive estimator) on daily living
    (orientation 2 mount, misaligned sensor, start after a 1 % drift), where the plain recursion fails.

    Statistic: the whitened error w = e^T F e / P (F: the windows' Fisher information at the truth); an
    efficient estimator has E w = 1, efficiency ~ 1 / E w. Over S seeds the mean has standard error
    se = std(w)/sqrt(S) (measured, ~0.08 for S = 32); we require mean + 2 se <= 1/0.8, i.e. efficiency >= 0.8
    at ~97.5 % one-sided confidence."""
    S = 32
    w_online, tr_crlb, sq = [], [], []
    results = pmap(online_daily_living_errors, [(1000 + seed,) for seed in range(S)])
    for model, reason, w_seed, sq_seed, tr_seed in results:
        assert model == "9", reason
        w_online.append(w_seed)
        sq.append(sq_seed)
        tr_crlb.append(tr_seed)
    w = np.array(w_online)
    se = w.std(ddof=1) / math.sqrt(S)
    assert w.mean() + 2 * se <= 1 / 0.8, (w.mean(), se)
    assert np.mean(tr_crlb) / np.mean(sq) > 0.8 - 3 * se  # the trace form of the same goal (looser: heavier tails)
