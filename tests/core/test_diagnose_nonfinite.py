"""The diagnosis of windows some of which carry no temperature (NaN: the channel read no value) although the
recording has a temperature column: the temperature terms are untestable with a note giving the count, and
everything else is the diagnosis without a temperature, instead of a NaN regressor reaching LAPACK's least
squares (raises "SVD did not converge" on some systems, loops forever on others). Run in a child process,
so a hang fails by timeout."""
from __future__ import annotations

import json
import textwrap

from tests.support.child import run_child

CHILD = textwrap.dedent("""
    import json
    import numpy as np
    from gravcal.core.diagnosis.procedure import diagnose_windows
    from gravcal.core.diagnosis.synthetic import PLANT, window_session
    from gravcal.core.model.terms import CALIBRATION_TERMS, calibration_view

    supply = next(t for t in CALIBRATION_TERMS if calibration_view(t).covariate == "vsupply")
    s = window_session(2, {supply: PLANT[supply]})
    kw = dict(replicas=4, folds=3)
    without = diagnose_windows(s.ws, s.start, has_temp=False, **kw)
    s.ws.aux[::9, 0] = np.nan
    d = diagnose_windows(s.ws, s.start, has_temp=True, **kw)
    summary = lambda x: {"findings": [[f["effect"], f["magnitude"]] for f in x.findings],
                         "untestable": x.untestable, "baseline": x.baseline_cal.offset.tolist()}
    print(json.dumps({"n_bad": len(range(0, len(s.ws), 9)), "n": len(s.ws), "notes": d.notes, "supply": supply,
                      "got": summary(d), "want": summary(without)}, default=float))
""")


def test_windows_without_a_temperature_make_the_temperature_terms_untestable_and_change_nothing_else():
    stdout = run_child(CHILD, timeout=300, what="diagnose_windows on windows with a NaN temperature")
    r = json.loads(stdout)
    note = f"{r['n_bad']} of {r['n']} windows carry no temperature"
    assert any(note in n for n in r["notes"]), r["notes"]
    assert r["got"] == r["want"]
    assert r["supply"] in [f[0] for f in r["got"]["findings"]]  # the planted term is still found
    assert any(u["effect"].startswith("temperature") for u in r["got"]["untestable"])
