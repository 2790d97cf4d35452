"""gravcald's start path stays light: no SciPy extension module in the serving daemon, and the filters
that replace scipy.signal's compute what scipy.signal computes."""
from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from gravcal.core import fastdetect
from gravcal.core.detectors import QuasiStaticDetector
from gravcal.core.gyro.conditioning import HighPassInverse, highpass_ba
from support.umockdev import require_umockdev
from tests.support.gravcald_process import GravcaldProcess

# no SciPy extension in the serving daemon: its filters run in gravcal's own kernel (core/_blockkernels.c)
HEAVY = ("/scipy/",)


def _mapped(pid: int) -> set[str]:
    return {line.split()[-1] for line in Path(f"/proc/{pid}/maps").read_text().splitlines() if "/" in line}


def _heavy_mapped(pid: int) -> list[str]:
    return sorted(p for p in _mapped(pid) if any(h in p for h in HEAVY))


def _children(pid: int) -> list[int]:
    return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]


@pytest.mark.parametrize("bus", ["serial", "i2c"])
def test_serving_daemon_maps_no_heavy_scipy_module(bus):
    """After start, with samples flowing to a client through the detector and the estimator, no
    extension module of scipy.signal/stats/optimize/spatial/linalg is mapped into gravcald (the emulated
    logger runs in a child process: on a pty, or behind /dev/i2c-1 through umockdev). The emulator's child
    runs the sensor model without SciPy too: its filters are the same compiled kernel."""
    if bus == "i2c":
        require_umockdev()
    d = GravcaldProcess(None, "--bus", bus, "--scenario", "six_position", "--speed", "1", fs=200.0)
    try:
        d.wait_serving()
        with d.client() as c:
            got = list(itertools.islice(c.watch(raw=True, timeout=30), 400))
        assert sum(m.get("class") == "IMU" for m in got) >= 300
        heavy = _heavy_mapped(d.proc.pid)
        # the scan itself must see extension modules: the filter kernel the detector runs is mapped
        assert any("/core/_blockkernels" in p for p in _mapped(d.proc.pid))
        assert heavy == [], f"gravcald loaded {sorted({p.split('/scipy/')[1].split('/')[0] for p in heavy})}"
        children = _children(d.proc.pid)
        assert children, "the emulated bus has no child process"
        for child in children:
            assert any("/core/_blockkernels" in p for p in _mapped(child))
            assert _heavy_mapped(child) == [], Path(f"/proc/{child}/cmdline").read_bytes()
    finally:
        d.stop()


@pytest.mark.parametrize("fs,hp,lp", [(200.0, 0.5, 0.5), (100.0, 0.5, 0.5), (200.0, 0.2, 3.0), (1000.0, 5.0, 0.5)])
def test_daemon_detector_filters_equal_scipy_signal(fs, hp, lp):
    det = QuasiStaticDetector(fs, hp_hz=hp, lp_hz=lp)
    ref_hp = signal.butter(2, hp, "highpass", fs=fs, output="sos")
    ref_lp = signal.butter(2, lp, "lowpass", fs=fs, output="sos")
    np.testing.assert_allclose(det.sos_hp, ref_hp, rtol=0, atol=1e-14)
    np.testing.assert_allclose(det.sos_lp, ref_lp, rtol=0, atol=1e-14)
    np.testing.assert_allclose(det._zi_hp_unit[0], signal.sosfilt_zi(ref_hp), rtol=1e-9, atol=1e-12)
    # the block detector's coefficients, bit for bit: the daemon and `gravcal calibrate` filter alike
    assert np.array_equal(det.sos_hp, fastdetect.butter_sos(2, hp, "highpass", fs))
    assert np.array_equal(det.sos_lp, fastdetect.butter_sos(2, lp, "lowpass", fs))

    def settle(sos, final, corner):  # samples until the step response stays within 1 %, via scipy.signal
        y = signal.sosfilt(sos, np.ones(int(round(20.0 / corner * fs))))
        return int(np.flatnonzero(np.abs(y - final) > 0.01)[-1] + 1)

    assert det.settle_n == settle(ref_hp, 0.0, hp) + settle(ref_lp, 1.0, lp)


@pytest.mark.parametrize("fs,hp", [(100.0, 0.3), (200.0, 0.3), (200.0, 5.0)])
def test_gyro_highpass_and_inverse_equal_scipy_signal(fs, hp):
    b, a = highpass_ba(hp, fs)
    rb, ra = signal.butter(1, hp, "highpass", fs=fs)
    np.testing.assert_allclose(b, rb, rtol=0, atol=1e-15)
    np.testing.assert_allclose(a, ra, rtol=0, atol=1e-15)
    rng = np.random.default_rng(int(fs + 10 * hp))
    for shape in ((700,), (700, 1), (700, 3)):
        y = rng.normal(0.0, 50.0, shape)
        y0 = y.copy()
        inv = HighPassInverse(hp, fs)
        got = np.concatenate([inv.update(y[:250]), inv.update(y[250:])])  # state carried across blocks
        ref, _ = signal.lfilter(inv.b, inv.a, y, axis=0, zi=np.zeros((1,) + y.shape[1:]))
        assert np.array_equal(y, y0), "the inverse changed its input"
        assert got.shape == y.shape
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-9)
