"""Window times gathered from a memory-mapped t (core.fastdetect._take_released): the same values as
from memory, and the pages they fault in are released as the gather goes (a week's window edges
otherwise left 0.6x the file resident)."""
from __future__ import annotations

import numpy as np

from gravcal.core import fastdetect


def _mapped_t(tmp_path, n=400_000):
    rec = np.zeros(n, dtype=[("t", "<f8"), ("ax", "<f4"), ("ay", "<f4"), ("az", "<f4")])
    rec["t"] = 5.0 + np.arange(n) / 100.0 + 1e-7 * np.sin(np.arange(n))
    np.save(tmp_path / "r.npy", rec)
    return np.load(tmp_path / "r.npy", mmap_mode="r")["t"], rec["t"]


def test_gathered_times_equal_and_released(tmp_path, monkeypatch):
    mapped, plain = _mapped_t(tmp_path)
    rng = np.random.default_rng(3)
    idx = np.sort(rng.choice(mapped.shape[0], 5000, replace=False))
    released = []
    real = fastdetect.release_mapped
    monkeypatch.setattr(fastdetect, "release_mapped", lambda a, lo, hi: (released.append((lo, hi)), real(a, lo, hi)))
    monkeypatch.setattr(fastdetect, "GATHER_PIECE", 700)
    got = fastdetect._take_released(mapped, idx)
    np.testing.assert_array_equal(got, plain[idx])
    assert len(released) == -(-idx.shape[0] // 700)
    # every gathered row lies inside a released range
    assert all(any(lo <= i < hi for lo, hi in released) for i in idx[::97])
    # from memory: nothing to release, the same values
    released.clear()
    np.testing.assert_array_equal(fastdetect._take_released(np.ascontiguousarray(plain), idx), plain[idx])
    assert released == []
