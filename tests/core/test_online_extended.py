"""The online path (OnlineCalibrator, and so gravcald) uses the extended terms.

Sessions are window-level simulations (core.estimators.remount.session_windows: the loetters scenario of
core.scenarios, rendered at 2 Hz, window means from the sensor model's linear part, core.model.defaults
triad_truth) of a sensor with the model's temperature_offset term planted (default_model(seed,
temperature_offset=True), ~1-3 mg/°C) and a temperature ramp 22 -> 32 °C; controls are the same sensors
without the term. The start is a previous calibration (offsets 10 mg, sensitivities 1 % off) with the
datasheet's held uncertainty.

Statistics: the coefficient check pools 3 seeds x 3 axes = 9 z-scores; |z| < 4 fails a consistent
estimator with probability 9 x 6.3e-5 < 1e-3. Controls: 0 selections in 5 seeds (a selection rate above
45 % would show at least one with probability > 95 %); bench/bench_soak.py --controls N measures the rate
with more seeds (measured: see docs/twelve-parameters.md, "Online").
"""
from __future__ import annotations

import numpy as np
import pytest
from gravcal.core.estimators.extended import apply_extended
from gravcal.core.samples import SAMPLE_DTYPE
from support.temperature_sessions import (
    EXT,
    previous_calibration,
    run,
    session,
)
from seed_pool import pmap

K_SIGMA = 4.0


def true_coefficient(info) -> np.ndarray:
    return info["truth"](26.0).offset - info["truth"](25.0).offset  # [raw/°C], exact: the term is linear


def planted_summary(seed: int) -> dict:
    """The online run over a planted session, as plain values (computed in a worker process)."""
    ws, info = session(seed, True)
    oc = run(ws, previous_calibration(info))
    cal = oc.calibration
    ext = cal.metadata.get("extended", {})
    return {"model": oc.model, "reason": oc.reason, "extended_status": oc.extended_status,
            "observable": cal.observable, "converged": cal.converged,
            "est": [cal.metadata["params"].get(f"oT_{a}") for a in "xyz"], "std": [cal.std.get(f"oT_{a}") for a in "xyz"],
            "truth": true_coefficient(info).tolist(), "terms": ext.get("terms"), "t_ref_c": ext.get("t_ref_c"),
            "magnitude_axes": sorted(ext.get("magnitudes", {}).get("temperature_offset", {}).get("value", {}))}


def test_planted_temperature_offset_is_selected_and_recovered_within_its_std():
    z = []
    for seed, r in zip((0, 1, 2), pmap(planted_summary, [(0,), (1,), (2,)])):
        assert r["model"] == EXT, (seed, r["reason"], r["extended_status"])
        assert r["observable"] and r["converged"]
        assert r["extended_status"][EXT]["status"] == "chosen" and "held-out" in r["extended_status"][EXT]["reason"]
        z += ((np.array(r["est"]) - np.array(r["truth"])) / np.array(r["std"])).tolist()
        # what apply_extended needs is in the calibration
        assert r["terms"] == ["temperature_offset"] and r["t_ref_c"] == 25.0
        assert r["magnitude_axes"] == ["x", "y", "z"]
    z = np.array(z)
    assert np.all(np.abs(z) < K_SIGMA), z
    # the std is not inflated either: the mean z^2 of 9 draws is chi2_9 / 9 (99.9 % quantile 3.1)
    assert np.mean(z * z) < 3.1, z


def later_rms(seed: int, terms: tuple[str, ...]) -> tuple[str, float]:
    """The model fitted on the first 75 % of a planted session's windows (with ``terms``), and its rms error of
    |a| - 1 g [g] on the remaining (warmer) windows."""
    ws, info = session(seed, True)
    first = int(len(ws) * 0.75)
    later = ws.subset(np.arange(first, len(ws)))
    cal = run(ws, previous_calibration(info), terms=terms, upto=first).calibration
    a = apply_extended(cal, later.mean, temp=later.aux[:, 0]) if terms else cal.apply(later.mean)
    return cal.model, float(np.sqrt(np.mean((np.linalg.norm(a, axis=1) - 1) ** 2)))


def test_the_temperature_term_lowers_the_error_on_later_windows_than_order_6():
    runs = [(seed, terms) for seed in (0, 1) for terms in (("temperature_offset",), ())]
    res = dict(zip(runs, pmap(later_rms, runs)))
    for seed in (0, 1):
        (ext_model, rms_ext), (six_model, rms_six) = res[seed, ("temperature_offset",)], res[seed, ()]
        assert ext_model == EXT and six_model == "6", (ext_model, six_model)
        # the later windows are warmer than any the fits saw (the ramp): the term must extrapolate
        assert rms_ext < 0.5 * rms_six, (seed, rms_ext, rms_six)


def control_summary(seed: int) -> tuple[str, dict]:
    ws, info = session(seed, False)
    oc = run(ws, previous_calibration(info))
    return oc.model, oc.extended_status


def test_controls_without_the_term_never_select_it():
    chosen = []
    for seed, (model, status) in zip(range(10, 15), pmap(control_summary, [(s,) for s in range(10, 15)])):
        assert model in ("6", "offsets"), (seed, model)
        if model == "6":
            assert status[EXT]["status"] in ("not warranted", "not observable"), status
        chosen.append(model == EXT)
    assert sum(chosen) == 0


@pytest.mark.parametrize("kind", ["no channel", "no spread"])
def test_without_temperature_the_term_is_reported_untestable(kind):
    kw = {"temperature": False} if kind == "no channel" else {"temp_c": lambda t: 30.0}
    ws, info = session(0, True, **kw)
    oc = run(ws, previous_calibration(info))
    assert oc.model == "6", oc.reason  # never chosen; the constant term is part of the offsets here
    st = oc.extended_status[EXT]
    assert st["status"] == "untestable"
    assert ("no temperature" in st["reason"]) if kind == "no channel" else ("no temperature spread" in st["reason"])
    assert oc.calibration.metadata["extended_terms"][EXT]["status"] == "untestable"


# -- through the daemon's Processor ---------------------------------------------------------------
FS = 50.0
TRUE_OFFSET = np.array([0.51, 0.49, 0.505])
TRUE_SENS = np.array([0.042, 0.038, 0.0415])
TRUE_COEF = np.array([1.2e-4, -0.9e-4, 0.8e-4])  # duty per °C (~3 mg/°C)


def board_blocks(n_poses: int, seed: int = 0, hold_s: float = 4.0, block: int = 100):
    """A board held in random still poses (movement in the first 0.8 s of each), temperature ramping
    22 -> 34 °C, raw = diag(s) a + o + c_T (T - 25) as T1/T2 counts."""
    rng = np.random.default_rng(seed)
    r = rng.normal(size=(n_poses, 3))
    poses = r / np.linalg.norm(r, axis=1)[:, None]
    n_total = int(n_poses * hold_s * FS)
    for i0 in range(0, n_total, block):
        idx = np.arange(i0, min(i0 + block, n_total))
        t = idx / FS
        pose = poses[(t // hold_s).astype(int)]
        phase = t % hold_s
        bump = np.where((phase < 0.8)[:, None], 0.5 * np.sin(2 * np.pi * 2.5 * phase)[:, None] * pose, 0.0)
        a = pose + bump + rng.normal(scale=0.002, size=(len(idx), 3))
        temp = 22.0 + 12.0 * idx / n_total
        raw = a * TRUE_SENS + TRUE_OFFSET + (temp - 25.0)[:, None] * TRUE_COEF
        s = np.zeros(len(idx), dtype=SAMPLE_DTYPE)
        s["t"], s["seq"], s["t2"] = t, idx, 20000
        s["t1"][:, :3] = np.round(raw * 20000)
        s["t1"][:, 3] = s["t1"][:, 0]
        s["temp"], s["vsupply"] = temp, 3.3
        yield s


def test_processor_selects_and_applies_the_temperature_term():
    from gravcal.daemon.config import load_config
    from gravcal.daemon.persistence import CalibrationState
    from gravcal.daemon.processing import Processor, nominal_calibration
    from gravcal.daemon.protocol import STANDARD_GRAVITY

    cfg = load_config(None, {"device.fs_hz": FS})
    assert "temperature_offset" in cfg.estimator.extended_terms.split(",")  # in the default
    p = Processor(cfg, CalibrationState(nominal_calibration(), 0, None, False, {}), resumed=False)
    blocks = list(board_blocks(500))
    for b in blocks:
        p.process(b)
    st = p.state
    assert st.accepted and st.model == EXT, (st.model, p.online.reason, p.online.extended_status)
    extra = p.calib_extra()
    assert extra["extended"]["model"] == EXT and extra["extended"]["param_names"] == st.calibration.param_names
    vals = dict(zip(extra["extended"]["param_names"], extra["extended"]["values"]))
    std = st.calibration.std
    for i, a in enumerate("xyz"):
        assert abs(vals[f"oT_{a}"] - TRUE_COEF[i]) < K_SIGMA * std[f"oT_{a}"] + 1e-7, (a, vals[f"oT_{a}"], std[f"oT_{a}"])
    # the published samples are corrected at their temperature: still samples of the last (warmest) poses
    # read 1 g; with the plain K, o (the term dropped) they would be off by c_T (T - 25)
    tail = np.concatenate(blocks[-60:])
    acc, _, static = p.correct(tail)
    phase = (tail["seq"] / FS) % 4.0
    still = phase > 1.5
    norm_err = np.abs(np.linalg.norm(acc[still], axis=1) / STANDARD_GRAVITY - 1.0)
    assert np.median(norm_err) < 0.003, np.median(norm_err)
    cal = st.calibration
    plain = np.abs(np.linalg.norm(cal.apply_reference(np.column_stack([tail["t1"][still, i] / 20000.0 for i in range(3)])),
                                  axis=1) - 1.0)
    assert np.median(plain) > 3 * np.median(norm_err)
    # equal to apply_extended (the fast path is the same formula)
    ref = apply_extended(cal, np.column_stack([tail["t1"][:, i] / 20000.0 for i in range(3)]),
                         temp=tail["temp"].astype(float)) * STANDARD_GRAVITY
    np.testing.assert_allclose(acc, ref, rtol=1e-9, atol=1e-9)
    # a resumed daemon restores the extended parameters
    from gravcal.daemon.persistence import CalibrationState as CS

    saved = CS.from_dict(st.to_dict())
    q = Processor(cfg, saved, resumed=True)
    assert q.online.model == EXT and q.online.calibration.metadata["params"] == pytest.approx(cal.metadata["params"])
    np.testing.assert_allclose(q.correct(tail)[0], acc, rtol=0, atol=1e-12) if q.applied.model == EXT else None
    q.applied = saved.calibration
    np.testing.assert_allclose(q.correct(tail)[0], acc, rtol=0, atol=1e-12)
