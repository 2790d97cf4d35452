"""diagnose --report: plots with titles, labelled axes and one colour per model / axis; a page of numbers."""
from __future__ import annotations

import re

import pytest

matplotlib = pytest.importorskip("matplotlib")
from matplotlib.colors import to_hex  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from gravcal.core.diagnosis import diagnose  # noqa: E402
from gravcal.core.samples import raw_triad  # noqa: E402
from gravcal.core.simulate import simulate  # noqa: E402
from gravcal.io import report  # noqa: E402


@pytest.fixture(scope="module")
def page_and_figures(tmp_path_factory):
    sim = simulate("six_position", seed=3, duration=300.0)
    d = diagnose(sim.samples["t"], raw_triad(sim.samples), temp=sim.samples["temp"], replicas=3)
    figures = []
    real_savefig = Figure.savefig

    def record(fig, *args, **kw):
        figures.append(fig)
        return real_savefig(fig, *args, **kw)

    mp = pytest.MonkeyPatch()
    mp.setattr(Figure, "savefig", record)
    try:
        page = report.write_report(d, tmp_path_factory.mktemp("rep"), source="six_position").read_text()
    finally:
        mp.undo()
    return d, page, figures


def _title(fig) -> str:
    sup = fig._suptitle.get_text() if fig._suptitle is not None else ""
    return sup or " ".join(ax.get_title() for ax in fig.axes)


def test_every_plot_has_a_title_and_labelled_axes(page_and_figures):
    d, page, figures = page_and_figures
    assert len(figures) >= 4  # orientation, temperature, time, distribution (+ Allan with a long stretch)
    for fig in figures:
        assert _title(fig).strip(), "untitled plot"
        assert _title(fig) in page  # the page names each plot by its title
        for ax in fig.axes:
            assert ax.get_xlabel().strip() and "[" in ax.get_xlabel(), ("x axis without label/unit", _title(fig))
        assert any(ax.get_ylabel().strip() for ax in fig.axes), ("y axis without label", _title(fig))


def test_one_colour_per_model_and_per_axis_on_every_plot(page_and_figures):
    _, _, figures = page_and_figures
    seen: dict[str, set[str]] = {}
    for fig in figures:
        for ax in fig.axes:
            for line in ax.get_lines():
                lab = line.get_label()
                key = next((k for k in ("baseline", "extended") if lab.startswith(k)), None)
                if key is None and lab.startswith(("measured ", "white noise only ")):
                    key = "axis " + lab[-1]  # an axis' measured curve and its white-noise line alike
                if key:
                    seen.setdefault(key, set()).add(to_hex(line.get_color()))
    assert {"baseline", "extended"} <= set(seen)
    assert all(len(c) == 1 for c in seen.values()), seen
    model_colours = seen["baseline"] | seen["extended"]
    assert len(model_colours) == 2  # and the two models differ


def test_page_shows_numbers_not_python_dicts(page_and_figures):
    d, page, _ = page_and_figures
    assert not re.search(r"\{'|': |np\.float64", page), [ln for ln in page.splitlines() if "{'" in ln or "': " in ln]
    assert "distinct postures" in page and "| statistic | measured |" in page
    assert report.num(d.heldout_gain_mg) in page or d.heldout_gain_mg is None


def test_findings_are_a_table_of_numbers(tmp_path):
    from gravcal.core.diagnosis import diagnose_windows
    from gravcal.core.diagnosis.synthetic import PLANT, window_session
    from gravcal.core.model.terms import CALIBRATION_TERMS

    effect = CALIBRATION_TERMS[0]  # misalignment: three pairs, each with value ± std and a raw-unit value
    s = window_session(5, {effect: PLANT[effect]})
    d = diagnose_windows(s.ws, s.start, has_temp=True, replicas=3, nested=False)
    assert [f["effect"] for f in d.findings] == [effect]
    page = report.write_report(d, tmp_path, source="session").read_text()
    mag = d.findings[0]["magnitude"]
    for k, v in mag["value"].items():
        unit = report.unit_text(mag["unit"])
        assert f"| {effect} | {k} | {report.num(v)} ± {report.num(mag['std'][k])} | {unit} |" in page
    assert "_per_" not in page and "_from_" not in page  # units as a reader writes them, not the JSON's names
    assert f"convention: {mag['convention']}" in page
    assert not re.search(r"\{'|': |np\.float64", page)


def test_units_read_as_units():
    assert [report.unit_text(u) for u in ("mg_per_C", "pct_per_h", "mg_per_V", "c2_per_g", "deg_from_orthogonal")] == [
        "mg/°C", "%/h", "mg/V", "c2/g", "° from orthogonal"]
