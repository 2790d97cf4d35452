"""The misalignment angles and the magnitudes' std: exact geometry and first-order propagation checked by hand."""
from __future__ import annotations

import math

import numpy as np

from gravcal.core.estimators.extended import axis_misalignment_deg, extended_class


def _axes_at(angle_xy_deg: float, angle_xz_deg: float, angle_yz_deg: float) -> np.ndarray:
    """Unit rows with the given pairwise angles (Cholesky of their Gram matrix: any frame)."""
    c = np.cos(np.radians([angle_xy_deg, angle_xz_deg, angle_yz_deg]))
    G = np.array([[1, c[0], c[1]], [c[0], 1, c[2]], [c[1], c[2], 1]])
    return np.linalg.cholesky(G)


def test_angles_are_the_angles_between_the_rows_at_any_gain_and_frame():
    rng = np.random.default_rng(5)
    U = _axes_at(84.0, 93.0, 88.5)  # far from small: 6° off, where 2 m / sqrt(s s) is visibly off
    K = np.diag([310.0, 350.0, 290.0]) @ U
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    for KK in (K, K @ q.T):  # the frame K carries does not change the angles between its rows
        assert np.allclose(axis_misalignment_deg(KK), [6.0, -3.0, 1.5], atol=1e-9)
    S = np.linalg.cholesky(K @ K.T)  # any factor with the same K K^T
    assert np.allclose(axis_misalignment_deg(S), [6.0, -3.0, 1.5], atol=1e-9)


def test_misalignment_magnitude_matches_the_exact_angle_of_the_fitted_k():
    par = extended_class("6+misalignment")(np.diag([330.0, 330.0, 330.0]), np.zeros(3))
    p = np.array([320.0, 340.0, 335.0, 1.0, -2.0, 3.0, 8.0, -5.0, 12.0])
    K, _ = par.unpack(p)
    mag = par.magnitudes(p)["misalignment"]
    assert np.allclose([mag["value"][k] for k in ("xy", "xz", "yz")], axis_misalignment_deg(K), atol=1e-12)
    small = 2 * np.degrees(8.0) / math.sqrt(320 * 340)  # the small-angle form differs at these gains and sizes
    assert abs(mag["value"]["xy"] - small) > 1e-3


def test_offset_term_std_propagates_the_gain_uncertainty_and_its_correlation():
    par = extended_class("6+temperature_offset")(np.diag([330.0, 330.0, 330.0]), np.zeros(3))
    p = np.array([320.0, 340.0, 335.0, 1.0, -2.0, 3.0, 0.8, -0.5, 1.2])  # oT [raw/°C]
    cov = np.diag(np.full(9, 1e-4))
    cov[0, 0], cov[6, 6], cov[0, 6] = 4.0, 1e-3, 0.03  # s_x and oT_x uncertain and correlated
    cov[6, 0] = cov[0, 6]
    mag = par.magnitudes(p, cov=cov)["temperature_offset"]
    s, c = 320.0, 0.8  # value = 1e3 c / s: gradient (1e3 / s, -1e3 c / s²)
    g = np.array([-1e3 * c / s**2, 1e3 / s])
    C = np.array([[cov[0, 0], cov[0, 6]], [cov[6, 0], cov[6, 6]]])
    assert math.isclose(mag["value"]["x"], 1e3 * c / s, rel_tol=1e-12)
    assert math.isclose(mag["std"]["x"], math.sqrt(g @ C @ g), rel_tol=1e-6)
    only_std = par.magnitudes(p, np.sqrt(np.diag(cov)))["temperature_offset"]["std"]["x"]  # taken as independent
    assert math.isclose(only_std, math.sqrt(g**2 @ np.diag(C)), rel_tol=1e-6)
