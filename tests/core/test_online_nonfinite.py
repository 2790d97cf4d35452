"""The online policy fed windows holding NaN/inf (a mean, a covariance, a time) screens them before the seed
pool, the re-mount detector and the recursion see them: it publishes exactly what it publishes for the same
stream without those windows, and a NaN window after an acceptance keeps the accepted calibration. One such
window in the seed pool made every bootstrap fit refuse the pool. Run in a child process, so a hang in a
linear-algebra call fails by timeout instead of hanging the suite."""
from __future__ import annotations

import json
import textwrap

import pytest

from tests.support.child import run_child

CHILD = textwrap.dedent("""
    import json, sys
    import numpy as np
    from gravcal.core.diagnosis.synthetic import window_session
    from gravcal.core.estimators.online import OnlineCalibrator
    from gravcal.core.windows import Window

    where, seed = sys.argv[1], int(sys.argv[2])
    s = window_session(seed, {}, n_windows=120)
    ws = s.ws
    clean = [Window(int(ws.start[i]), int(ws.end[i]), float(ws.t[i]) - 1.0, float(ws.t[i]) + 1.0, ws.mean[i].copy(),
                    ws.cov[i].copy(), ws.aux[i].copy()) for i in range(len(ws))]

    def poisoned(w):
        mean, cov, t0 = w.mean.copy(), w.cov.copy(), w.t_start
        if where == "mean":
            mean[1] = np.nan
        elif where == "inf":
            mean[2] = np.inf
        elif where == "cov":
            cov[0, 0] = np.nan
        else:
            t0 = np.nan
        return Window(w.start, w.end, t0, w.t_end, mean, cov, w.aux_mean)

    def run(windows):
        oc = OnlineCalibrator.for_service(s.start, model="6", min_windows=6, fs=100.0)
        out = []
        for w in windows:
            st = oc.feed(w)
            if st.calibration is not None:
                c = st.calibration
                out.append([bool(st.accepted), c.model, c.offset.tolist(), c.sensitivity.ravel().tolist()])
        return oc, out

    oc0, want = run(clean)
    mixed = []
    for i, w in enumerate(clean):  # a bad window before the first good one, then every fifth
        if i % 5 == 0:
            mixed.append(poisoned(w))
        mixed.append(w)
    oc, got = run(mixed)
    applied, screened = oc.policy.applied, oc.policy.windows_screened
    after = [oc.feed(poisoned(clean[-1])) for _ in range(3)]
    print(json.dumps({"want": want, "got": got, "screened": screened, "n_bad": len(mixed) - len(clean),
                      "screened_clean": oc0.policy.windows_screened,
                      "after_published": [a.calibration is not None for a in after],
                      "after_screened": [a.screened for a in after], "applied_same": oc.policy.applied is applied,
                      "seeded": [oc0.policy.seeded, oc.policy.seeded]}))
""")


@pytest.mark.parametrize("where", ["mean", "inf", "cov", "time"])
def test_nonfinite_windows_change_nothing_the_policy_publishes(where):
    stdout = run_child(CHILD, where, "0", timeout=240, what=f"the online policy on windows with a non-finite {where}")
    r = json.loads(stdout)
    assert r["want"] and any(acc for acc, *_ in r["want"]), "the clean stream reaches an accepted calibration"
    assert r["got"] == r["want"]  # same revisions, verdicts and parameters, bit for bit
    assert r["screened"] == r["screened_clean"] + r["n_bad"] and r["n_bad"] > 0
    assert r["seeded"] == [True, True]  # the seed fit ran on the pooled windows
    assert r["after_screened"] == [True] * 3 and r["after_published"] == [False] * 3 and r["applied_same"]


@pytest.mark.parametrize("field", ["mean", "cov", "time"])
def test_the_calibrator_refuses_a_nonfinite_window_before_storing_it(field):
    """``OnlineCalibrator.update`` (the recursion alone, without the policy's screen) keeps its store to the
    windows a batch fit accepts: one with a NaN time in it would make every later re-seed refuse the store."""
    import numpy as np

    from gravcal.core.diagnosis.synthetic import window_session
    from gravcal.core.estimators.online import OnlineCalibrator
    from gravcal.core.windows import Window

    s = window_session(1, {}, n_windows=20)
    oc = OnlineCalibrator(s.start)
    for i in range(10):
        oc.update(Window(int(s.ws.start[i]), int(s.ws.end[i]), float(s.ws.t[i]), float(s.ws.t[i]), s.ws.mean[i],
                         s.ws.cov[i], s.ws.aux[i]))
    mean, cov, t = s.ws.mean[10].copy(), s.ws.cov[10].copy(), float(s.ws.t[10])
    if field == "mean":
        mean[0] = np.nan
    elif field == "cov":
        cov[1, 1] = np.inf
    else:
        t = np.nan
    with pytest.raises(ValueError, match={"mean": "mean", "cov": "covariance", "time": "time"}[field]):
        oc.update(Window(int(s.ws.start[10]), int(s.ws.end[10]), t, t, mean, cov, s.ws.aux[10]))
    assert len(oc.store) == oc.n_windows == 10


def test_a_start_with_a_nonfinite_value_is_refused_when_the_calibrator_is_built():
    """Every window would otherwise be judged under a NaN calibration (eigh on a NaN information)."""
    import numpy as np

    from gravcal.core.calibration import Calibration
    from gravcal.core.diagnosis.synthetic import window_session
    from gravcal.core.estimators.online import OnlineCalibrator

    s = window_session(0, {}, n_windows=12)
    OnlineCalibrator.for_service(s.start, model="6")  # the finite start is taken
    bad = Calibration("6", s.start.offset + np.array([0.0, np.nan, 0.0]), s.start.sensitivity)
    with pytest.raises(ValueError, match="start calibration has a NaN/inf offset or sensitivity"):
        OnlineCalibrator.for_service(bad, model="6", resumed=True)


AUX_CHILD = textwrap.dedent("""
    import json
    import numpy as np
    from gravcal.core.diagnosis.synthetic import PLANT, window_session
    from gravcal.core.estimators.online import OnlineCalibrator
    from gravcal.core.model.terms import CALIBRATION_TERMS, calibration_view
    from gravcal.core.windows import Window

    temp = next(t for t in CALIBRATION_TERMS if calibration_view(t).covariate == "temp")
    s = window_session(1, {temp: PLANT[temp]}, n_windows=300)
    ws = s.ws

    def run(nan_from):
        oc = OnlineCalibrator.for_service(s.start, model="6", extended_terms=temp, min_windows=6, fs=100.0)
        models, finite = [], True
        for i in range(len(ws)):
            aux = ws.aux[i].copy()
            if i >= nan_from and i % 7 == 3:
                aux[0] = np.nan  # the temperature channel read no value
            st = oc.feed(Window(int(ws.start[i]), int(ws.end[i]), float(ws.t[i]) - 1, float(ws.t[i]) + 1,
                                ws.mean[i], ws.cov[i], aux))
            if st.accepted:
                models.append(st.calibration.model)
                finite &= bool(np.isfinite(st.calibration.offset).all() and np.isfinite(st.calibration.covariance).all())
        return oc, models, finite

    _, clean_models, _ = run(len(ws))
    oc, models, finite = run(200)
    print(json.dumps({"temp": temp, "clean_last": clean_models[-1], "last": models[-1], "finite": finite,
                      "status": oc.extended_status["6+" + temp]}))
""")


def test_windows_without_a_temperature_leave_the_temperature_term_untestable_online():
    """The extended candidate on windows some of which carry no temperature: untestable (with the count), the
    base order stays accepted with finite values; no NaN covariate reaches the extended rule's eigh."""
    stdout = run_child(AUX_CHILD, timeout=300, what="the online calibrator on windows without a temperature")
    r = json.loads(stdout)
    assert r["clean_last"] == "6+" + r["temp"]  # with every temperature the planted term is chosen
    assert r["last"] == "6" and r["finite"]
    assert r["status"]["status"] == "untestable" and "windows carry no temperature" in r["status"]["reason"]
