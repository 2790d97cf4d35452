"""diagnose names no wrong cause with confidence, on sessions gravcal's simulator did not shape.

Sessions: tests/support/planted_sessions.py (its own physics and random streams; an hour, 160 windows, a
triad in counts with small cross-axis terms, so ``misalignment`` is a true cause in every one of them).
Required answers:
- misspecified controls (a quadratic temperature offset 0.1-0.25 mg/°C² about 27 °C; a first-order thermal lag
  of 600 s when thermal_lag is not offered; a random-walk bias): no wrong cause named; the quadratic and the lag
  are said to be unexplained with the residual's structure;
- every named finding gains on folds the selection never saw (its nested gain > 0);
- a warm-up at a constant rate (temperature and time collinear) with a temperature offset and a drift: the group
  "temperature_offset or offset_drift", never a third term, the magnitude stated as conditional;
- thermal_lag offered on a lag session: the nested held-out error is that of the lag model (the lag built from
  every window's temperature, not each fold's training windows only);
- the extended calibration applied at each window's own temperature gives the error the fit reports.
Each session's verdict is deterministic (fixed seeds); "no wrong cause" is asserted in every session.
"""
from __future__ import annotations

import numpy as np
import pytest

from gravcal.core.diagnosis import CATALOGUE, diagnose_windows
from gravcal.core.diagnosis.held import channel_slopes
from gravcal.core.model.terms import CALIBRATION_TERMS
from seed_pool import pmap
from support import planted_sessions as P

TRUE_EVERYWHERE = {"misalignment"}  # the generator's cross-axis terms
N_CONTROL = 3  # sessions per misspecified kind


def disturbance(kind: str):
    return {"quadratic": (P.quadratic_temperature(0.1e-3, 0.25e-3), "body"),
            "lag": (P.thermal_lag(2e-3, 600.0), "cycle"),
            "random_walk": (P.random_walk(2e-3), "body"),
            "warmup": (P.temperature_and_drift(1.5e-3, 3e-3), "linear_ramp"),
            "linear": (P.linear_temperature(1.5e-3), "body")}[kind]


def run(kind: str, seed: int, offer_lag: bool = False) -> dict:
    """diagnose_windows on one planted session; plain values for the worker pool."""
    dist, temp = disturbance(kind)
    s = P.session(seed, dist, temp=temp)
    cands = CALIBRATION_TERMS if offer_lag else CATALOGUE
    d = diagnose_windows(s.ws, s.start, has_temp=True, candidates=cands, simulate=False, nested=True)
    applied = d.extended_cal.apply(s.ws.mean, temp=s.ws.aux[:, 0], t=s.ws.t, vsupply=s.ws.aux[:, 1])
    return {"kind": kind, "seed": seed, "findings": [f["effect"] for f in d.findings],
            "partial": [f["effect"] for f in d.partial], "verdict": d.verdict["status"], "text": d.verdict["text"],
            "nested_gains": [f["evidence"].get("nested_heldout_gain_mg") for f in d.findings],
            "groups": [f["group"] for f in d.findings if f.get("group")],
            "grouped_notes": [f["magnitude"].get("conditional", "") for f in d.findings if f.get("group")],
            "procedure_gain": d.heldout_gain_mg, "extended_heldout": d.extended_heldout_mg,
            "extended_insample": d.extended_insample_mg,
            "applied_rms_mg": float(np.sqrt(np.mean((1 - np.linalg.norm(applied, axis=1)) ** 2)) * 1e3)}


@pytest.fixture(scope="module")
def sessions() -> list[dict]:
    jobs = [(k, 100 + s) for k in ("quadratic", "lag", "random_walk") for s in range(N_CONTROL)]
    jobs += [("warmup", 200 + s) for s in range(2)] + [("linear", 300)]
    return pmap(run, jobs)


def of(sessions, kind):
    return [r for r in sessions if r["kind"] == kind]


def test_misspecified_controls_name_no_wrong_cause(sessions):
    allowed = {"quadratic": set(), "lag": set(), "random_walk": {"offset_drift"}}
    wrong = [(r["kind"], r["seed"], r["findings"]) for kind, ok in allowed.items() for r in of(sessions, kind)
             if set(r["findings"]) - ok - TRUE_EVERYWHERE]
    assert not wrong, wrong


def test_quadratic_and_lag_are_said_unexplained_with_their_structure(sessions):
    for r in of(sessions, "quadratic"):
        assert r["verdict"] == "unexplained" and "temperature is curved" in r["text"], r
        assert "× the window noise" in r["text"]
        assert set(r["partial"]) <= {"temperature_offset"} | TRUE_EVERYWHERE, r  # part of it, not the cause
    for r in of(sessions, "lag"):
        assert r["verdict"] == "unexplained" and "residual" in r["text"], r


def test_every_named_finding_gains_on_folds_the_selection_never_saw(sessions):
    named = [(r["kind"], r["seed"], g, r["procedure_gain"]) for r in sessions for g in r["nested_gains"]]
    assert len(named) >= 4  # the planted temperature sessions and the true misalignment name something
    assert all(g is not None and g > 0 and pg > 0 for *_, g, pg in named), named


def test_collinear_warmup_is_named_as_a_group(sessions):
    for r in of(sessions, "warmup"):
        assert set(r["findings"]) <= {"temperature_offset", "offset_drift"} | TRUE_EVERYWHERE, r
        assert len(r["groups"]) == 1, r
        g = r["groups"][0]
        assert set(g["effects"]) == {"temperature_offset", "offset_drift"}, g
        assert "not separable in this session" in g["text"] and "r = 0.99" in g["text"], g
        assert g["joint_heldout_gain_mg"] > 3.0  # planted 1.5-3 mg/°C over 12 °C and 3-6 mg/h: several mg
        assert r["grouped_notes"][0].startswith("the value if temperature_offset alone were the cause")


def test_applied_calibration_gives_the_fitted_error(sessions):
    """The extended calibration applied to the windows at their own temperature (Calibration.apply, the
    user's path) leaves the in-sample error of the fit: a reference shifted on one side shows here."""
    for r in of(sessions, "linear") + of(sessions, "warmup"):
        assert r["applied_rms_mg"] <= 1.02 * r["extended_insample"] + 0.01, r
        assert r["extended_insample"] < 1.2  # the generator's 0.8 mg floor and the noise, nothing planted left


def test_offered_lag_is_scored_with_every_windows_temperature():
    """thermal_lag offered on a 600 s lag session: named, and the nested held-out error is that of the lag
    model (within 30 % of its in-sample error; built from the training folds' temperatures alone it is 5-8x)."""
    r = run("lag", 100, offer_lag=True)
    assert set(r["findings"]) - TRUE_EVERYWHERE == {"thermal_lag"}, r
    assert r["extended_heldout"] <= 1.3 * r["extended_insample"], r


STRONG_EVIDENCE = 10.0  # 2 ln(Bayes factor) above which Kass & Raftery call the evidence strong (docs/measured-data.md)


def boundary_run(seed: int) -> dict:
    """A temperature offset at the detection boundary (0.05-0.1 mg/°C over 22 <-> 34 °C cycles: the held-out
    folds interpolate, so the evidence decides), diagnosed with the default catalogue."""
    s = P.session(seed, P.linear_temperature(0.05e-3), temp="cycle")
    d = diagnose_windows(s.ws, s.start, has_temp=True, simulate=False, nested=False)
    return {"seed": seed, "named": [(f["effect"], f["evidence"]["delta_bic"]) for f in d.findings + d.partial],
            "temperature_offset": next(t.delta_bic for t in d.tests if t.effect == "temperature_offset")}


def test_no_term_is_named_on_less_than_strong_evidence():
    """The evidence a named cause needs, judged by outcome where it decides: at the detection boundary, where
    the planted term's ΔBIC falls between 5 and 10 in a tenth of the sessions and other terms' now and then.
    Clean controls cannot show it (measured: 0 false terms in 196 independent clean sessions at the threshold
    10 and at 5, the held-out rule binds; by theory the rates are ~4e-4 and ~4e-3 a session: thousands of
    sessions to tell apart). Every named term must carry strong evidence (with the threshold halved, 8 of these
    40 sessions name a term on ΔBIC 5-10, one of them a false nonlinearity), and the planted one is named in
    about half of the sessions (measured 22 of 40)."""
    runs = pmap(boundary_run, [(900 + s,) for s in range(40)])
    weak = [(r["seed"], e, b) for r in runs for e, b in r["named"] if not b > STRONG_EVIDENCE]
    assert not weak, weak
    in_band = sum(5.0 < r["temperature_offset"] <= STRONG_EVIDENCE for r in runs)
    assert in_band >= 3, in_band  # the band where the threshold decides is populated (measured 4 of 40)
    named = sum(any(e == "temperature_offset" for e, _ in r["named"]) for r in runs)
    assert named >= 12, named


def test_single_pose_channel_slopes_std_covers_the_truth():
    """Per-channel temperature slopes in one pose (what diagnose reports there) over 120 sessions with a
    random-walk bias beside the temperature offset (errors shared by neighbouring windows): RMS of
    (estimate - truth)/std within 1 ± 3/sqrt(2n) and the share beyond 2σ within the binomial bounds."""
    from scipy.stats import binom

    def both(coef, walk):
        lt, rw = P.linear_temperature(coef), P.random_walk(walk)
        return lambda t, T, rng: lt(t, T, rng) + rw(t, T, rng)

    z = []
    for temp in ("body", "cycle"):
        for seed in range(60):
            s = P.session(seed, both(1.5e-3, 1e-3), temp=temp, pose="single")
            sl = channel_slopes(s.ws, "temp")
            coef = P.linear_temperature(1.5e-3)(np.zeros(1), np.array([28.0]), P._rng(seed, 3))[0]  # same draws
            z += [(sl["value"][a] - coef[i] * s.sens[i]) / sl["std"][a] for i, a in enumerate("xyz")]
    z = np.asarray(z)
    n = z.size
    rms = float(np.sqrt(np.mean(z * z)))
    assert abs(rms - 1) <= 3 / np.sqrt(2 * n), rms
    beyond = int(np.sum(np.abs(z) > 2))
    assert binom.ppf(0.001, n, 0.0455) <= beyond <= binom.ppf(0.999, n, 0.0455), (beyond, n)


def test_unexplained_residual_is_on_the_report_page_with_its_plot(tmp_path):
    """report.md says 'Unexplained' with the structure (table and plot) and lists what explains part of it."""
    from gravcal.cli.cmd_diagnose import summary
    from gravcal.io.report import write_report

    dist, temp = disturbance("quadratic")
    s = P.session(101, dist, temp=temp)
    d = diagnose_windows(s.ws, s.start, has_temp=True, simulate=False, nested=True)
    assert d.verdict["status"] == "unexplained"
    page = write_report(d, tmp_path, source="planted").read_text()
    assert "**Unexplained.** residual vs temperature is curved" in page
    assert "| temperature | is curved (degree 2) |" in page
    assert "Terms that explain part of the residual" in page
    assert (tmp_path / "residual_structure.png").stat().st_size > 1000
    text = summary(d.to_json_dict(), "planted")
    assert "UNEXPLAINED: residual vs temperature is curved" in text and "FOUND" not in text
