"""Diagnosis when effects interact, are small, or are not in the catalogue at all.

Sessions: core/diagnosis/synthetic.py (an hour, 200 quasi-static windows, 24-34 °C, supply 3.05-3.3 V,
1 mg quasi-static floor); diagnose_windows on all registered window-mean terms, without the nested
held-out gain (the selection and its magnitudes are what is judged here; the nested gain is tested in
test_diagnose_hidden.py and test_diagnose.py).

Rates: a claimed rate p over n sessions is asserted as "count >= binom.ppf(RISK, n, p)" (detections) or
"count <= binom.ppf(1 - RISK, n, p)" (false findings): a true rate at the claim fails the assertion with
probability below RISK; seeds are fixed, so the runs are deterministic.
Magnitudes: |estimate - truth| <= 4 reported std + 15 % of the truth (linearisation at the reference, 1 %
start error); an estimate at half the truth fails it whenever the std is below 9 % of the truth.
"""
from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.stats import binom

from gravcal.core.diagnosis import diagnose_windows
from gravcal.core.diagnosis.synthetic import PLANT, window_session
from gravcal.core.model import datasheet as DS
from gravcal.core.model.spec import CROSS_PAIRS
from gravcal.core.model.terms import CALIBRATION_TERMS
from gravcal.core.samples import TRIAD
from seed_pool import pmap

RISK = 0.02
# planted parameter and its factor from report units to the model's units, per catalogue effect
PARAM = {"temperature_offset": ("coef_g_per_c", 1e-3), "temperature_sensitivity": ("coef_per_c", 1e-2),
         "offset_drift": ("rate_g_per_h", 1e-3), "sensitivity_drift": ("rate_per_h", 1e-2),
         "nonlinearity": ("c2", 1.0), "supply_offset": ("coef_g_per_v", 1e-3)}
# docs/measured-data.md, "The magnitude floor": fraction of PLANT detected in >= 90 % of one-hour sessions
FLOOR = {"misalignment": 0.25, "nonlinearity": 0.5, "temperature_offset": 0.125, "temperature_sensitivity": 0.25,
         "offset_drift": 0.5, "sensitivity_drift": 0.5}
# datasheet values (core/model/datasheet.py) as planting scales (per channel: 1-2 x the scale, random sign)
DATASHEET = {"temperature_offset": DS.TEMP_OFFSET_G_PER_C, "temperature_sensitivity": DS.TEMP_SENS_PER_C,
             "nonlinearity": DS.NONLIN_PCT_FS / 100 * DS.RANGE_G / DS.RANGE_G ** 2,  # 0.2 % of 10 g at 10 g
             "offset_drift": DS.OFFSET_RATE_G_PER_H, "sensitivity_drift": DS.SENS_RATE_PER_H,
             "supply_offset": DS.SUPPLY_OFFSET_G_PER_V, "misalignment": np.deg2rad(DS.ALIGN_DEG)}


def min_count(n: int, p: float) -> int:
    return int(binom.ppf(RISK, n, p))


def max_count(n: int, p: float) -> int:
    return int(binom.ppf(1 - RISK, n, p))


def diagnose_session(s):
    return diagnose_windows(s.ws, s.start, has_temp=True, candidates=CALIBRATION_TERMS, simulate=False, nested=False)


def planted_result(seed: int, planted: dict[str, float]) -> tuple[list[str], list[str]]:
    """A session with the ``planted`` effects (effect -> scale): the names found and the magnitude errors of the
    planted ones (plain values: computed in a worker process)."""
    s = window_session(seed, planted)
    d = diagnose_session(s)
    errors = [e for f in d.findings if f["effect"] in planted for e in magnitude_errors(f, truth_of(s, f["effect"]))]
    return [f["effect"] for f in d.findings], errors


def misalignment_truth(s) -> dict[str, float]:
    """90° minus the angle between each pair of the planted channel axes [deg] (rotation-free: what the norm sees)."""
    term = next(t for t in s.model.terms if t.name == "misalignment")
    u = term.matrix[list(TRIAD)]
    return {"xyz"[i] + "xyz"[j]: 90.0 - float(np.degrees(np.arccos(u[i] @ u[j]))) for i, j in CROSS_PAIRS}


def truth_of(s, effect: str) -> dict[str, float]:
    """The planted magnitude in report units, per reported key."""
    if effect == "misalignment":
        return misalignment_truth(s)
    key, unit = PARAM[effect]
    return dict(zip("xyz", (np.asarray(s.planted[effect][key])[:3] / unit).tolist()))


def magnitude_errors(finding: dict, truth: dict[str, float]) -> list[str]:
    """Determined axes outside 4 std + 15 % of the truth, and any zero magnitude (a finding never has one)."""
    mag, bad = finding["magnitude"], []
    vals = {k: v for k, v in mag["value"].items() if v is not None}
    if not vals or any(v == 0 for v in vals.values()):
        bad.append(f"{finding['effect']}: zero or no magnitude {mag['value']}")
    for k, v in vals.items():
        if abs(v - truth[k]) > 4 * mag["std"][k] + 0.15 * abs(truth[k]):
            bad.append(f"{finding['effect']} {k}: {v:.4g} vs planted {truth[k]:.4g} (std {mag['std'][k]:.2g})")
    return bad


def test_misalignment_is_the_deviation_from_orthogonality():
    """The stated convention (JSON and docs/sensor-model.md) is the one measured: 90° minus the angle between axes."""
    for seed in range(3):
        s = window_session(31_000 + seed, {"misalignment": PLANT["misalignment"]})
        d = diagnose_session(s)
        assert [f["effect"] for f in d.findings] == ["misalignment"]
        mag = d.findings[0]["magnitude"]
        assert mag["unit"] == "deg_from_orthogonal" and "90° minus the angle between" in mag["convention"]
        truth = misalignment_truth(s)
        assert max(abs(v) for v in truth.values()) > 0.3  # a test of the scale needs angles well above the std
        assert magnitude_errors(d.findings[0], truth) == []
        for k, v in mag["value"].items():  # tighter than the generic rule: no 15 % allowance on an angle
            assert abs(v - truth[k]) <= 4 * mag["std"][k] + 0.02, (seed, k, v, truth[k], mag["std"][k])


@pytest.mark.slow
def test_every_pair_of_catalogue_effects():
    """Two planted effects: both named, nothing else, each magnitude right given the other."""
    pairs = list(itertools.combinations(sorted(PLANT), 2))
    exact, errors = 0, []
    results = pmap(planted_result, [(71_000 + k, {e: PLANT[e] for e in pair}) for k, pair in enumerate(pairs)])
    for pair, (names, errs) in zip(pairs, results):
        exact += sorted(names) == sorted(pair)
        errors += errs
    n = len(pairs)
    assert exact >= min_count(n, 0.95), f"both and only the pair named in {exact}/{n}"
    assert len(errors) <= max_count(2 * n, 0.02), errors  # per finding: outside the tolerance in <= 2 %


@pytest.mark.slow
def test_smallest_documented_magnitudes_are_found():
    """The floor docs/measured-data.md claims for an hour (>= 90 % detection), with magnitudes."""
    n, errors = 6, []
    runs = [(81_000 + 100 * CALIBRATION_TERMS.index(effect) + seed, {effect: frac * PLANT[effect]})
            for effect, frac in FLOOR.items() for seed in range(n)]
    results = pmap(planted_result, runs)
    for i, (effect, frac) in enumerate(FLOOR.items()):
        found = 0
        for names, errs in results[i * n:(i + 1) * n]:
            found += effect in names
            errors += errs
        assert found >= min_count(n, 0.9), f"{effect} at {frac} x PLANT: found in {found}/{n}"
    assert len(errors) <= max_count(n * len(FLOOR), 0.02), errors


def datasheet_result(seed: int, planted: dict[str, float]):
    """planted_result, or the start of the reason when diagnose refuses the session with a ValueError."""
    try:
        return (*planted_result(seed, planted), None)
    except ValueError as e:
        return [], [], str(e)[:80]


@pytest.mark.slow
def test_datasheet_scale_effects():
    """Each effect at its datasheet value: found when the documented floor is below it, and never replaced by
    another term (an effect too small to resolve must give no finding rather than a wrong one)."""
    n, wrong, errors, refused = 3, [], [], []
    runs = [(91_000 + 100 * CALIBRATION_TERMS.index(effect) + seed, {effect: scale})
            for effect, scale in DATASHEET.items() for seed in range(n)]
    results = pmap(datasheet_result, runs)
    for i, (effect, scale) in enumerate(DATASHEET.items()):
        above_floor = scale >= FLOOR.get(effect, 1.0) * PLANT[effect]
        found = 0
        for seed, (names, errs, reason) in enumerate(results[i * n:(i + 1) * n]):
            if reason is not None:  # refused with a reason (a baseline that does not converge): no wrong finding
                refused.append((effect, seed, reason))
                continue
            found += effect in names
            wrong += [(effect, seed, x) for x in names if x != effect]
            errors += errs
        if above_floor:
            assert found >= min_count(n, 0.9), f"{effect} at the datasheet value: found in {found}/{n} ({refused})"
    total = n * len(DATASHEET)
    assert len(wrong) <= max_count(total, 0.02), f"another term named in {len(wrong)}/{total}: {wrong}"
    assert len(errors) <= max_count(total, 0.02), errors
    assert len(refused) <= max_count(total, 0.02), refused


# -- misspecified controls: effects outside the catalogue, with the answer required of diagnose ----------------
def _lagged(t: np.ndarray, temp: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order lag of the window temperatures (in time order) with time constant tau_s."""
    out, order = np.empty_like(temp), np.argsort(t)
    y, tp = temp[order[0]], t[order[0]]
    for i in order:
        a = np.exp(-(t[i] - tp) / tau_s)
        y, tp = a * y + (1 - a) * temp[i], t[i]
        out[i] = y
    return out


def misspecified(kind: str, seed: int, tau_s: float = 300.0):
    """A control session plus an offset [g] the catalogue has no term for (``tau_s``: the lag's time constant);
    returns (session, offset (m, 3))."""
    s = window_session(61_000 + seed, {})
    rng = np.random.default_rng([seed, 13])
    ws, temp = s.ws, s.ws.aux[:, 0]
    c1 = np.where(rng.random(3) < 0.5, -1, 1) * DS.TEMP_OFFSET_G_PER_C / 2 * rng.uniform(1, 2, 3)
    if kind == "quadratic_temperature":  # 0.1 mg/°C² curvature: 2.5 mg at the ends of a 10 °C range
        off = np.outer(temp - 29.0, c1) + 1e-4 * (temp - 29.0)[:, None] ** 2
    elif kind == "thermal_lag":  # the die follows the temperature channel with a time constant (5 min default)
        off = np.outer(_lagged(ws.t, temp, tau_s) - 29.0, c1)
    else:  # random-walk bias at the datasheet-scale 2 mg/sqrt(h)
        dt_h = np.diff(np.r_[0.0, np.sort(ws.t)]) / 3600.0
        walk = np.cumsum(rng.normal(0, 1, (len(ws), 3)) * np.sqrt(dt_h)[:, None] * DS.OFFSET_WALK_G_PER_SQRT_H, axis=0)
        off = np.empty_like(walk)
        off[np.argsort(ws.t)] = walk
    ws.mean[:] = ws.mean + off * DS.SENS_TYP
    return s, off


def linear_temperature_slope_mg(ws, off: np.ndarray) -> dict[str, float]:
    """The best a linear temperature term can say: the least-squares slope of the planted offset on the recorded
    temperature over the windows [mg/°C]."""
    A = np.column_stack([np.ones(len(ws)), ws.aux[:, 0]])
    return dict(zip("xyz", (np.linalg.lstsq(A, off, rcond=None)[0][1] * 1e3).tolist()))


N_MISSPECIFIED = 6


def quadratic_result(seed: int) -> list[str]:
    """What departs from the required answer on a quadratic-temperature session (empty: the required answer)."""
    s, off = misspecified("quadratic_temperature", seed)
    d = diagnose_session(s)
    names, partial = [f["effect"] for f in d.findings], [f["effect"] for f in d.partial]
    bad = [] if not names and partial == ["temperature_offset"] else [f"named {names}, partial {partial}"]
    if "temperature is curved" not in d.verdict["text"]:
        bad.append(f"verdict {d.verdict['text']!r}")
    if "temperature_offset" in partial:
        found = d.partial[partial.index("temperature_offset")]
        bad += magnitude_errors(found, linear_temperature_slope_mg(s.ws, off))
    return bad


@pytest.mark.slow
def test_quadratic_temperature_dependence():
    """Required answer: unexplained, 'residual vs temperature is curved'; temperature_offset explains part of it
    (reported apart, not named as the cause) with the least-squares linear slope on the recorded temperature
    (within the magnitude tolerance), and no other term: the curvature is a remainder of the temperature
    dependence, not a supply, drift, lag or sensitivity effect."""
    ok, report = 0, []
    for seed, bad in enumerate(pmap(quadratic_result, [(seed,) for seed in range(N_MISSPECIFIED)])):
        ok += not bad
        report += [(seed, bad)] if bad else []
    assert ok >= min_count(N_MISSPECIFIED, 0.9), f"required answer in {ok}/{N_MISSPECIFIED}: {report}"


def lag_coefficients_mg(ws, off: np.ndarray, tau_s: float) -> dict[str, float]:
    """The planted coefficient per axis [mg/°C]: the planted offset on the lagged window temperature (exact)."""
    z = _lagged(ws.t, ws.aux[:, 0], tau_s) - 29.0
    A = np.column_stack([np.ones(len(ws)), z])
    return dict(zip("xyz", (np.linalg.lstsq(A, off, rcond=None)[0][1] * 1e3).tolist()))


def lag_result(seed: int, tau_s: float) -> list[str]:
    """What departs from the required answer on a thermal-lag session (empty: the required answer)."""
    s, off = misspecified("thermal_lag", seed, tau_s)
    d = diagnose_session(s)
    names = [f["effect"] for f in d.findings]
    bad = [] if names == ["thermal_lag"] else [f"named {names}"]
    if "thermal_lag" in names:
        found = d.findings[names.index("thermal_lag")]
        bad += magnitude_errors(found, lag_coefficients_mg(s.ws, off, tau_s))
        tau = found["magnitude"]["tau_s"]
        lo, hi = tau["interval_68"]
        if not (tau_s / 1.4 <= tau["value"] <= tau_s * 1.4 and lo / 1.4 <= tau_s <= hi * 1.4):
            bad.append(f"tau {tau}")
    return bad


@pytest.mark.slow
@pytest.mark.parametrize("tau_s", [300.0, 1200.0])
def test_thermal_lag_is_named_with_its_coefficient_and_time_constant(tau_s):
    """Required answer for an offset following the temperature through a 5 or 20 min lag: thermal_lag alone
    (no temperature_offset, offset_drift or supply_offset on the remainder), its coefficients within the
    magnitude tolerance, and tau within one grid step (x 1.4) of the planted one with the reported interval
    covering it to a grid step. (1200 s is not the term's default: a fixed tau would fail it.)"""
    ok, report = 0, []
    for seed, bad in enumerate(pmap(lag_result, [(seed, tau_s) for seed in range(N_MISSPECIFIED)])):
        ok += not bad
        report += [(seed, bad)] if bad else []
    assert ok >= min_count(N_MISSPECIFIED, 0.9), f"required answer in {ok}/{N_MISSPECIFIED}: {report}"


@pytest.mark.slow
def test_plain_temperature_offset_is_not_a_lag():
    """A temperature offset without lag (datasheet-scale, 2 mg/°C x U(1, 2)): named temperature_offset, never
    thermal_lag (the profiled time constant costs a parameter and a lag at the grid's short end is the same
    column)."""
    n, lag_named, missed = 6, [], 0
    planted = {"temperature_offset": DS.TEMP_OFFSET_G_PER_C}
    results = pmap(planted_result, [(41_000 + seed, planted) for seed in range(n)])
    for seed, (names, _) in enumerate(results):
        missed += "temperature_offset" not in names
        lag_named += [(seed, names)] if "thermal_lag" in names else []
    assert len(lag_named) <= max_count(n, 0.02), f"a plain temperature offset named a lag: {lag_named}"
    assert n - missed >= min_count(n, 0.9), f"temperature_offset found in {n - missed}/{n}"


def lag_not_offered(seed: int) -> dict:
    """diagnose on a 600 s lag session with the default catalogue (no thermal_lag) and the nested held-out gain."""
    s, _ = misspecified("thermal_lag", seed, 600.0)
    d = diagnose_windows(s.ws, s.start, has_temp=True, simulate=False, nested=True)
    return {"seed": seed, "findings": [f["effect"] for f in d.findings], "status": d.verdict["status"],
            "text": d.verdict["text"], "withdrawn": {w["effect"]: w["why"] for w in d.verdict["withdrawn"]},
            "replaced": [x["replaces"] for x in d.verdict["structure"] if x.get("replaces")]}


def test_lag_not_offered_names_no_cause():
    """Required answer in every one of six sessions with a 600 s lag that the catalogue has no term for: no cause
    named, "unexplained" with the residual's structure. Terms that each gain on folds the selection never saw can
    share the lag between them (a temperature offset, a drift, a supply offset following parts of it, the residual
    left flat): there the structure outside the catalogue (the temperature's rate of change, a wander in time) fits
    better in their place and they are withdrawn as stand-ins, which the text says."""
    results = pmap(lag_not_offered, [(seed,) for seed in range(N_MISSPECIFIED)])
    wrong = [(r["seed"], r["findings"], r["text"]) for r in results if r["findings"] or r["status"] != "unexplained"]
    assert not wrong, wrong
    stand_ins = [r for r in results if any("a stand-in, not a cause" in why for why in r["withdrawn"].values())]
    assert stand_ins, [r["withdrawn"] for r in results]
    for r in stand_ins:
        assert "in their place" in r["text"] or "in its place" in r["text"], r
        assert set(sum(r["replaced"], [])) <= set(r["withdrawn"]), r


def random_walk_names(seed: int) -> list[list[str]]:
    """The findings of the procedure a user gets (nested held-out: a term that does not gain on folds the
    selection never saw is withdrawn), each as the effects it names (a group when the session cannot separate
    them)."""
    s = misspecified("random_walk", seed)[0]
    d = diagnose_windows(s.ws, s.start, has_temp=True, candidates=CALIBRATION_TERMS, simulate=False, nested=True)
    return [f["group"]["effects"] if f.get("group") else [f["effect"]] for f in d.findings]


@pytest.mark.slow
def test_random_walk_bias_is_not_attributed_to_a_covariate():
    """Required answer for a 2 mg/sqrt(h) random-walk bias: nothing, or offset_drift (its trend over the hour),
    alone or in a group the session cannot separate; never a temperature, supply, sensitivity or nonlinearity
    term alone. (Seed 3 names sensitivity_drift as the group "sensitivity_drift or offset_drift", r = 1.0 over the
    session; without the nested held-out seed 1 names thermal_lag, which the delivered procedure withdraws.)"""
    wrong = []
    for seed, findings in enumerate(pmap(random_walk_names, [(seed,) for seed in range(N_MISSPECIFIED)])):
        if any("offset_drift" not in names for names in findings):
            wrong.append((seed, findings))
    assert not wrong, f"misattributed in {len(wrong)}/{N_MISSPECIFIED}: {wrong}"


def test_the_selection_rule_decides_every_term():
    """Found <=> ΔBIC > 10 and a lower held-out error, on sessions chosen (fixed seeds) where each half of the
    rule alone decides a term: a ΔBIC in (2, 10] with a held-out gain, and a ΔBIC > 10 the held-out error vetoes
    (random-walk bias sessions: slow excursions a covariate can follow in-sample)."""
    tests = [t for seed in (2, 4) for t in diagnose_session(misspecified("random_walk", seed)[0]).tests
             if t.delta_bic is not None and t.heldout_before_mg is not None and t.heldout_after_mg is not None]
    for t in tests:
        rule = t.delta_bic > 10.0 and t.heldout_after_mg < t.heldout_before_mg
        assert (t.status == "found") == rule, (t.effect, t.status, t.delta_bic, t.heldout_before_mg, t.heldout_after_mg)
    assert {t.evidence()["delta_bic_threshold"] for t in tests} == {10.0}
    assert any(2.0 < t.delta_bic <= 10.0 and t.heldout_after_mg < t.heldout_before_mg for t in tests)
    assert any(t.delta_bic > 10.0 and t.heldout_after_mg >= t.heldout_before_mg for t in tests)


@pytest.mark.xfail(strict=True, reason=(
    "measured: the simulated holds carry trunk sway (0.2-0.6 Hz, ~2 mg); the Allan deviation of the static "
    "stretches peaks at 0.3-1 s and decays as 1/tau, and the white + flicker + random-walk model takes the tail for "
    "a 0.15-0.25 mg bias instability (ΔBIC ~ 3000): motion is named as a sensor noise term"))
def test_sway_in_static_stretches_is_not_colored_sensor_noise():
    """Required answer on a sample-level control (white sensor noise, no planted effect, body sway in the holds):
    no colored_noise finding."""
    from gravcal.core.diagnosis import diagnose
    from gravcal.core.model.defaults import default_model
    from gravcal.core.samples import raw_triad
    from gravcal.core.simulate import simulate

    sim = simulate("six_position", default_model(3), seed=3, duration=1800.0, temp_profile="body", hold_s=(40.0, 60.0))
    d = diagnose(sim.samples["t"], raw_triad(sim.samples), temp=sim.samples["temp"], replicas=3, simulate=False)
    assert "colored_noise" not in [f["effect"] for f in d.findings]
