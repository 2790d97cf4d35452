"""`gravcal calibrate DIR --out results.csv --report DIR`: the study's QC page, opened in a real headless
browser (Debian's chromium; skipped without it, a failure where GRAVCAL_REQUIRE_CHROMIUM=1 as in CI): every
plot loads, is titled and captioned, the table has one row per file with the row's numbers and working
links; the plots themselves have titles, labelled axes with units, and legends clear of the data."""
from __future__ import annotations

import csv
import warnings
import shutil
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from gravcal.cli.main import main
from gravcal.core.calibration import Calibration
from gravcal.io import study_report
from support.inputs import skip_or_fail

N_OK = 3  # six-position sessions: calibrated


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """A small study run in-process with a nominal start (so every calibrated file has a 'before')."""
    d = tmp_path_factory.mktemp("study")
    rec = d / "recordings"
    rec.mkdir()
    for seed in range(N_OK):
        assert main(["simulate", "--scenario", "six_position", "--seed", str(seed), "--duration", "240",
                     "--out", str(rec / f"six{seed}.npy")]) == 0
    assert main(["simulate", "--scenario", "static", "--seed", "9", "--duration", "60", "--out", str(rec / "still.npy")]) == 0
    (rec / "broken.csv").write_text("garbage\n")
    start = d / "nominal.json"
    start.write_text(Calibration.nominal(np.full(3, 0.5), 0.04).to_json())
    out, report = d / "results.csv", d / "qc"
    # the exit status is the study's (an error row may make it non-zero): the page is written either way
    main(["calibrate", str(rec), "--out", str(out), "--workers", "0", "--quiet", "--start", str(start),
          "--report", str(report)])
    assert (report / "index.html").is_file()
    with open(out, newline="") as f:
        rows = list(csv.DictReader(f))
    return out, report, rows


class Page(HTMLParser):
    """The rendered DOM's images (with their figure's caption), table rows and links."""

    def __init__(self) -> None:
        super().__init__()
        self.images: list[dict[str, str]] = []
        self.captions: list[str] = []
        self.rows: list[list[str]] = []
        self.links: list[str] = []
        self.title = ""
        self._in: str | None = None
        self._cells: list[str] | None = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.images.append(a)
        elif tag == "a":
            self.links.append(a.get("href", ""))
        elif tag == "tr" and a.get("class") == "file":
            self._cells = []
        elif tag in ("figcaption", "title") or (tag == "td" and self._cells is not None):
            self._in = tag
            if tag == "td":
                self._cells.append("")
            elif tag == "figcaption":
                self.captions.append("")

    def handle_endtag(self, tag):
        if tag == "tr" and self._cells is not None:
            self.rows.append(self._cells)
            self._cells = None
        if tag == self._in:
            self._in = None

    def handle_data(self, data):
        if self._in == "td":
            self._cells[-1] += data
        elif self._in == "figcaption":
            self.captions[-1] += data
        elif self._in == "title":
            self.title += data


def chromium_dom(page: Path, tmp_path: Path) -> str:
    """The DOM of ``page`` after Chromium loaded it (and its images) and ran its scripts."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        skip_or_fail("no headless browser: install Debian's chromium (apt-get install chromium)",
                     "GRAVCAL_REQUIRE_CHROMIUM")
    run = subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                          "--disable-component-update", "--disable-sync", "--no-first-run",
                          f"--user-data-dir={tmp_path / 'chromium-profile'}", "--virtual-time-budget=5000",
                          "--dump-dom", page.resolve().as_uri()],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    return run.stdout


def parsed(text: str) -> Page:
    p = Page()
    p.feed(text)
    return p


def test_the_page_renders_in_chromium(study, tmp_path):
    out, report, rows = study
    assert len(rows) == N_OK + 2
    page = parsed(chromium_dom(report / "index.html", tmp_path))
    assert page.title.startswith("gravcal study report")
    # every plot: present, decoded by the browser, titled, captioned
    names = [name for name, _, _ in study_report.FIGURES]
    assert [im["src"] for im in page.images] == names
    for im, caption in zip(page.images, page.captions):
        assert im.get("data-loaded") == "yes" and int(im["data-natural-width"]) > 300, im
        assert int(im["data-shown-width"]) > 300, im  # laid out on the page, not hidden or squeezed
        assert im["alt"] and im["title"] == im["alt"] and len(caption) > 20
    # one row per file, with the results' own numbers, and each row's link opens that file's page
    by_file = {r["file"]: r for r in rows}
    assert sorted(cells[1] for cells in page.rows) == sorted(by_file)
    for cells in page.rows:
        r = by_file[cells[1]]
        assert cells[2] == r["status"]
        for shown, col in ((cells[4], "uncalibrated_rms_mg"), (cells[5], "heldout_rms_mg")):
            assert shown == (format(float(r[col]), ".3g") if r[col] else "n/a")
    statuses = sorted(r["status"] for r in rows)
    assert statuses.count("error") == 1 and statuses.count("refused") == 1
    calibrated = [r for r in rows if r["status"] not in ("refused", "error")]
    assert len(calibrated) == N_OK and all(float(r["uncalibrated_rms_mg"]) > float(r["heldout_rms_mg"]) for r in calibrated)
    file_links = [h for h in page.links if h.startswith("files/")]
    assert len(file_links) == len(rows) and all((report / h).is_file() for h in file_links)
    ok_row = next(i for i, cells in enumerate(page.rows) if by_file[cells[1]]["status"] == "ok")
    detail = parsed(chromium_dom(report / file_links[ok_row], tmp_path))
    assert "../index.html" in detail.links
    text = (report / file_links[ok_row]).read_text()
    assert text.count("<tr>") == len(rows[0])  # every column of the row
    recording = Path(page.rows[ok_row][1]).resolve().as_uri()
    assert recording in detail.links  # the row's file is a link to the recording


def test_every_plot_is_titled_labelled_with_its_legend_clear_of_the_data(study):
    pytest.importorskip("matplotlib")
    out, _, _ = study
    rows = study_report.read_results(out)
    for name, fig, _ in study_report.figures(rows):
        fig.canvas.draw()  # an Agg canvas: the layout and the extents in display pixels
        renderer = fig.canvas.get_renderer()
        (ax,) = fig.axes
        assert ax.get_title() and ax.get_xlabel() and ax.get_ylabel(), name
        legend = ax.get_legend()
        assert legend is not None and legend.get_texts(), name
        box = legend.get_window_extent(renderer)
        data = [a for a in [*ax.patches, *ax.lines, *ax.collections] if a.get_visible()]
        boxes = [a.get_window_extent(renderer) for a in data]
        boxes = [b for b in boxes if b.width > 0 and b.height > 0]
        assert boxes, name  # the plot shows data
        assert not any(box.overlaps(b) for b in boxes), f"{name}: the legend covers data"
        saved = fig.get_tightbbox(renderer)  # what savefig(bbox_inches="tight") keeps, in inches
        assert saved.x1 * fig.dpi >= box.x1 - 1 and saved.y0 * fig.dpi <= box.y0 + 1, f"{name}: legend cut off"
    error_ax = study_report.error_figure(rows).axes[0]
    assert "[mg]" in error_ax.get_xlabel()
    # the histograms count every file with a number: the calibrated ones, before and after
    n = sum(1 for r in rows if r["status"] not in ("refused", "error"))
    heights = sum(p.get_height() for p in error_ax.patches)
    assert heights == 2 * n


def test_without_matplotlib_the_page_keeps_the_table(study, tmp_path, monkeypatch):
    out, _, rows = study
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib raises ImportError
    page = study_report.write_report(out, tmp_path / "plain")
    text = page.read_text()
    assert "matplotlib is not installed" in text and "<img" not in text
    assert text.count("<tr class='file'>") == len(rows)
    assert not list((tmp_path / "plain").glob("*.png"))


def test_a_retried_file_keeps_its_last_row_and_bad_input_is_named(study, tmp_path):
    out, _, rows = study
    again = tmp_path / "results.csv"
    error = next(r for r in rows if r["status"] == "error")
    with open(again, "w", newline="") as f:  # the error row, then the same file's retry appended later
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows + [{**error, "status": "refused", "message": "retried"}])
    got = study_report.read_results(again)
    assert len(got) == len(rows) and got[-1]["file"] == error["file"]
    assert got[-1]["status"] == "refused" and got[-1]["message"] == "retried"
    with open(again, "a") as f:
        f.write(f"{tmp_path / 'torn.npy'}")  # a row cut short by a kill: no status, not a result
    assert [r["file"] for r in study_report.read_results(again)] == [r["file"] for r in got]
    with pytest.raises(ValueError, match="cannot read the results"):
        study_report.write_report(tmp_path, tmp_path / "r")  # a folder, not a file
    with pytest.raises(ValueError, match="no such results file"):
        study_report.write_report(tmp_path / "missing.csv", tmp_path / "r")
    (tmp_path / "other.csv").write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match="not a gravcal results file"):
        study_report.write_report(tmp_path / "other.csv", tmp_path / "r")
    assert main(["calibrate", str(rows[0]["file"]), "--report", str(tmp_path / "r")]) == 2


def test_a_study_with_nothing_calibrated_says_so_on_each_plot(tmp_path):
    pytest.importorskip("matplotlib")
    from gravcal.io.study import FIELDS

    results = tmp_path / "results.csv"
    with open(results, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=FIELDS, extrasaction="ignore")
        writer.writeheader()
        writer.writerow({"file": "a.csv", "status": "error", "message": "a.csv: missing columns t"})
        writer.writerow({"file": "b.npy", "status": "refused", "model": "nominal", "message": "nothing determined"})
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no empty legend, no matplotlib complaint
        page = study_report.write_report(results, tmp_path / "qc")
    assert page.read_text().count("<tr class='file'>") == 2 and len(list(page.parent.glob("*.png"))) == len(study_report.FIGURES)
    (page.parent / "files" / "0099-old.npy.html").write_text("a row of an earlier drawing")
    study_report.write_report(results, tmp_path / "qc")  # drawn again: only this drawing's rows have pages
    assert sorted(p.name for p in (page.parent / "files").iterdir()) == ["0001-a.csv.html", "0002-b.npy.html"]
    rows = study_report.read_results(results)
    model_ax = study_report.model_figure(rows).axes[0]
    assert not model_ax.patches and "no file has a calibration" in [t.get_text() for t in model_ax.texts]
    assert "0 of 2 files" in model_ax.get_title()
