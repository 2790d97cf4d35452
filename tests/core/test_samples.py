"""Sample layout: duty-cycle ratios and the triad."""
import numpy as np

from gravcal.core.samples import FLAG_GAP_BEFORE, FLAG_SATURATED, duty_ratios, empty, flag_names, raw_triad


def test_duty_ratio_uses_each_channels_chip_period():
    s = empty(2)
    s["t1"] = [[500, 540, 460, 520], [1000, 1000, 1000, 1000]]
    s["t2"] = [[1000, 920], [2000, 0]]
    r = duty_ratios(s)
    np.testing.assert_allclose(r[0], [0.5, 0.54, 460 / 920, 520 / 920])
    np.testing.assert_allclose(r[1, :2], [0.5, 0.5])
    assert np.isnan(r[1, 2:]).all()  # missing period -> NaN, never inf
    np.testing.assert_allclose(raw_triad(s)[0], [0.5, 0.54, 0.5])


def test_flag_names():
    assert flag_names(FLAG_GAP_BEFORE | FLAG_SATURATED) == ["gap_before", "saturated"]
    assert flag_names(0) == []
