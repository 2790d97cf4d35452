"""``gravcal calibrate DIR --out results.csv --report DIR``: a study's QC page, DIR/index.html.

Read from the study's results.csv (io/study.py), so it can be (re)drawn at any time, also of an
interrupted study: the calibration error per file before (no calibration: the start, where one
exists) and after (held-out, contiguous folds), as distributions and file by file, the model orders chosen, the statuses with the
refusals, and a table with one row per file linked to a page of that file's row (every column; any
value naming an existing file is a link to it). A file calibrated again (a retried error) keeps its
last row. Plots are PNGs (matplotlib, optional: without it the page says so and keeps the tables);
each has a title, labelled axes with units, and its legend outside the axes, clear of the data.
"""
from __future__ import annotations

import csv
import html
import math
import re
from collections import Counter
from pathlib import Path
from typing import Any

from ..errors import InputError

BEFORE, AFTER = "uncalibrated_rms_mg", "heldout_rms_mg"
ERROR_LABEL = "RMS of |a| − 1 g over the windows [mg]"
STATUS_ORDER = ("ok", "partial", "not_improved", "unreliable", "refused", "error")
STATUS_COLORS = {"ok": "tab:green", "partial": "tab:olive", "not_improved": "tab:orange",
                 "unreliable": "tab:red", "refused": "tab:purple", "error": "tab:gray"}
STATUS_MEANING = {"ok": "ok", "partial": "partial (offsets only)", "not_improved": "not improved (start returned)",
                  "unreliable": "unreliable", "refused": "refused (nothing determined)", "error": "error (not read)"}
NO_CALIBRATION = ("refused", "error")  # a refused row's model is the start it returns: nothing was fitted
BEFORE_COLOR, AFTER_COLOR = "tab:blue", "tab:orange"
# Marks each image with whether it decoded, so a headless browser's DOM says what rendered.
IMG_CHECK = ("<script>for (const im of document.images) { const mark = () => { im.dataset.loaded = "
             "im.naturalWidth > 0 ? 'yes' : 'no'; im.dataset.naturalWidth = im.naturalWidth; "
             "im.dataset.shownWidth = Math.round(im.getBoundingClientRect().width); }; "
             "if (im.complete) mark(); else { im.addEventListener('load', mark); im.addEventListener('error', mark); } }"
             "</script>")


def read_results(path: Path) -> list[dict[str, str]]:
    """The study's rows, one per file (the last row of a file calibrated more than once)."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            rows = [r for r in reader]
    except FileNotFoundError:
        raise InputError(f"{path}: no such results file (--report draws a study's results.csv)") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{path}: not a gravcal results file ({type(exc).__name__})") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the results ({exc.strerror})") from None
    if not reader.fieldnames or "file" not in reader.fieldnames or "status" not in reader.fieldnames:
        raise InputError(f"{path}: not a gravcal results file (no 'file' and 'status' columns)")
    last: dict[str, dict[str, str]] = {}
    for r in rows:
        if r.get("file") and r.get("status"):  # a row torn by a kill has no status yet: not a result
            last.pop(r["file"], None)  # a later row replaces the earlier one, in the later row's place
            last[r["file"]] = {k: (v or "") for k, v in r.items() if k is not None}
    return list(last.values())


def number(value: str | None) -> float | None:
    """A results cell as a finite float, or None (empty, n/a, not finite)."""
    try:
        x = float(value or "")
    except ValueError:
        return None
    return x if math.isfinite(x) else None


def have_matplotlib() -> bool:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def _figure(width_in: float, height_in: float) -> Any:
    """A figure on its own Agg canvas: no pyplot, no global state, safe beside other threads."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _legend_outside(ax: Any, empty: str, has_data: bool | None = None) -> Any:
    """The legend to the right of the axes: it never covers a bar or a point. No data: ``empty`` says so."""
    if not (bool(ax.patches) if has_data is None else has_data):
        ax.text(0.5, 0.5, empty, transform=ax.transAxes, ha="center", va="center")
        ax.set_xticks([])
        ax.set_yticks([])
    if not ax.get_legend_handles_labels()[0]:
        return None
    return ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0, frameon=False)


def error_figure(rows: list[dict[str, str]]) -> Any:
    """Histogram of the per-file error before (the start) and after (held-out) calibration, log bins."""
    import numpy as np

    before = [x for x in (number(r.get(BEFORE)) for r in rows) if x is not None and x > 0]
    after = [x for x in (number(r.get(AFTER)) for r in rows) if x is not None and x > 0]
    fig = _figure(9.0, 4.0)
    ax = fig.add_subplot()
    both = before + after
    if both:
        lo, hi = math.log10(min(both)), math.log10(max(both))
        edges = np.logspace(lo - 0.05, hi + 0.05, max(8, min(30, 2 * int(math.sqrt(len(both))) + 4)))
        if before:
            ax.hist(before, bins=edges, color=BEFORE_COLOR, alpha=0.6,
                    label=f"before: the start, {_files(len(before))}")
        if after:
            ax.hist(after, bins=edges, color=AFTER_COLOR, alpha=0.6,
                    label=f"after: held-out, {_files(len(after))}")
        ax.set_xscale("log")
    n_without = len(rows) - len(before)
    if n_without:  # an entry without a patch: says why files are missing from "before"
        ax.plot([], [], " ", label=f"no 'before' for {_files(n_without)}:\nno start to score, or refused")
    ax.set_title("Calibration error per file, before and after")
    ax.set_xlabel(ERROR_LABEL + " (log scale)")
    ax.set_ylabel("files")
    ax.yaxis.get_major_locator().set_params(integer=True)
    _legend_outside(ax, "no file has an error in mg: each was refused or unreadable")
    return fig


def paired_figure(rows: list[dict[str, str]]) -> Any:
    """Each file's error after against before: below the diagonal the calibration helped."""
    fig = _figure(8.0, 4.4)
    ax = fig.add_subplot()
    pairs = [(number(r.get(BEFORE)), number(r.get(AFTER)), r["status"]) for r in rows]
    pairs = [(b, a, s) for b, a, s in pairs if b is not None and a is not None and b > 0 and a > 0]
    if pairs:
        lo = min(min(b, a) for b, a, _ in pairs) / 1.5
        hi = max(max(b, a) for b, a, _ in pairs) * 1.5
        ax.plot([lo, hi], [lo, hi], color="black", linewidth=0.8, label="after = before (no gain)")
        for status in [s for s in STATUS_ORDER if any(p[2] == s for p in pairs)] + \
                sorted({p[2] for p in pairs} - set(STATUS_ORDER)):
            mine = [p for p in pairs if p[2] == status]
            ax.scatter([p[0] for p in mine], [p[1] for p in mine], color=STATUS_COLORS.get(status, "black"),
                       label=f"{STATUS_MEANING.get(status, status)}: {_files(len(mine))}", zorder=3)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlim(lo, hi)
        ax.set_ylim(lo, hi)
    ax.set_title(f"Error per file, after against before ({_files(len(pairs))} with both)")
    ax.set_xlabel("before: the start [mg] (log scale)")
    ax.set_ylabel("after: held-out [mg] (log scale)")
    _legend_outside(ax, "no file has both a 'before' and an 'after'", has_data=bool(pairs))
    return fig


def _status_bars(ax: Any, categories: list[str], rows_of: dict[str, list[dict[str, str]]], empty: str) -> None:
    """Bars per category, stacked by status, one colour per status."""
    bottom = [0] * len(categories)
    for status in [s for s in STATUS_ORDER if any(r["status"] == s for rs in rows_of.values() for r in rs)] + \
            sorted({r["status"] for rs in rows_of.values() for r in rs} - set(STATUS_ORDER)):
        heights = [sum(r["status"] == status for r in rows_of[c]) for c in categories]
        ax.bar(categories, heights, bottom=bottom, color=STATUS_COLORS.get(status, "black"),
               label=STATUS_MEANING.get(status, status))
        bottom = [b + h for b, h in zip(bottom, heights)]
    ax.set_ylabel("files")
    ax.yaxis.get_major_locator().set_params(integer=True)
    _legend_outside(ax, empty)


def model_figure(rows: list[dict[str, str]]) -> Any:
    """Model orders returned (files with a calibration), stacked by status."""
    fitted = [r for r in rows if r.get("model") and r["status"] not in NO_CALIBRATION]
    models = sorted({r["model"] for r in fitted}, key=_model_key)
    fig = _figure(8.0, 3.6)
    ax = fig.add_subplot()
    _status_bars(ax, models, {m: [r for r in fitted if r["model"] == m] for m in models}, "no file has a calibration")
    ax.set_title(f"Model order returned ({len(fitted)} of {len(rows)} files have a calibration)")
    ax.set_xlabel("model order (parameters estimated)")
    return fig


def status_figure(rows: list[dict[str, str]]) -> Any:
    """Verdicts, refusals and errors: files per status."""
    statuses = [s for s in STATUS_ORDER if any(r["status"] == s for r in rows)]
    statuses += sorted({r["status"] for r in rows} - set(statuses))
    fig = _figure(8.0, 3.6)
    ax = fig.add_subplot()
    _status_bars(ax, statuses, {s: [r for r in rows if r["status"] == s] for s in statuses}, "no files")
    ax.set_title("Verdict per file: calibrated, refused, errors")
    ax.set_xlabel("status (exit 0: ok, partial; the others exit 3 for one file)")
    return fig


def _model_key(model: str) -> tuple[int, str]:
    base = model.split("+", 1)[0]
    return ({"offsets": 0, "6": 1, "9": 2, "12": 3}.get(base, 4), model)


FIGURES = (("error.png", error_figure,
            "Calibration error per file: before (the start scored on every window) and after (held-out on "
            "contiguous folds the fit never saw)."),
           ("paired.png", paired_figure,
            "Each file's error after calibration against before: below the diagonal the calibration helped."),
           ("models.png", model_figure, "Model order each file's calibration uses, by status."),
           ("status.png", status_figure, "Status of every file: the verdict, refusals and unreadable files."))


def figures(rows: list[dict[str, str]]) -> list[tuple[str, Any, str]]:
    """(file name, matplotlib Figure, caption) of every plot of the page."""
    return [(name, make(rows), caption) for name, make, caption in FIGURES]


def _files(n: int) -> str:
    return f"{n} file" + ("" if n == 1 else "s")


def _fmt(x: float | None, spec: str = ".3g") -> str:
    return "n/a" if x is None else format(x, spec)


def _slug(i: int, file: str) -> str:
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", Path(file).name)[:60]
    return f"{i + 1:04d}-{stem}.html"


def _existing(value: str, bases: list[Path]) -> Path | None:
    """The file a cell names, if it exists (relative names against the results' folder, then the cwd)."""
    if not value or len(value) > 4096 or "\n" in value or number(value) is not None:
        return None
    p = Path(value)
    for q in ([p] if p.is_absolute() else [b / p for b in bases]):
        try:
            if q.is_file():
                return q.resolve()
        except OSError:
            return None
    return None


def _file_page(row: dict[str, str], bases: list[Path]) -> str:
    cells = []
    for key, value in row.items():
        target = _existing(value, bases)
        shown = html.escape(value) if value else "<i>empty</i>"
        if target is not None:
            shown = f'<a href="{html.escape(target.as_uri())}">{shown}</a>'
        cells.append(f"<tr><th>{html.escape(key)}</th><td>{shown}</td></tr>")
    name = html.escape(Path(row["file"]).name)
    return (f"<!doctype html><html><head><meta charset='utf-8'><title>{name}: {html.escape(row['status'])}</title>"
            f"{STYLE}</head><body><p><a href='../index.html'>study report</a></p><h1>{name}</h1>"
            f"<table class='row'>{''.join(cells)}</table>"
            f"<p>offset [raw], sensitivity [raw per g]: a [g] = sensitivity<sup>−1</sup> (raw − offset); "
            f"errors in mg of |a| − 1 g.</p></body></html>\n")


STYLE = ("<style>body{font-family:sans-serif;margin:1.5em;max-width:75em}table{border-collapse:collapse}"
         "td,th{border:1px solid #ccc;padding:.2em .5em;text-align:left;vertical-align:top}"
         "td.num{text-align:right}figure{margin:1em 0}img{max-width:100%}</style>")


def _summary(rows: list[dict[str, str]]) -> str:
    import statistics

    counts = Counter(r["status"] for r in rows)
    parts = ", ".join(f"{counts[s]} {s.replace('_', ' ')}" for s in sorted(counts, key=lambda s: (
        STATUS_ORDER.index(s) if s in STATUS_ORDER else len(STATUS_ORDER), s)))
    out = [f"<p>{_files(len(rows))}: {html.escape(parts) or 'none'}.</p>"]
    for label, col in (("before (the start, nothing fitted)", BEFORE), ("after (held-out)", AFTER)):
        xs = [x for x in (number(r.get(col)) for r in rows) if x is not None]
        if xs:
            out.append(f"<p>Median error {label}: {statistics.median(xs):.3g} mg over {_files(len(xs))}.</p>")
    return "".join(out)


def write_report(results_csv: Path, out_dir: Path) -> Path:
    """Write out_dir/index.html (+ PNGs when matplotlib is present, + one page per file); returns the page."""
    results_csv, out_dir = Path(results_csv), Path(out_dir)
    rows = read_results(results_csv)
    try:
        (out_dir / "files").mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{out_dir}: cannot create the report folder ({exc.strerror})") from None
    bases = [results_csv.resolve().parent, Path.cwd()]
    body = [f"<h1>Study report: {html.escape(results_csv.name)}</h1>", _summary(rows)]
    if not rows:
        body.append("<p>No rows yet: nothing to plot.</p>")
    elif have_matplotlib():
        for name, fig, caption in figures(rows):
            fig.savefig(out_dir / name, dpi=100, bbox_inches="tight")
            title = fig.axes[0].get_title()
            body.append(f"<figure><img src='{name}' alt='{html.escape(title)}' title='{html.escape(title)}'>"
                        f"<figcaption>{html.escape(caption)}</figcaption></figure>")
    else:
        body.append("<p>matplotlib is not installed: no plots (pip install 'gravcal[figures]'); "
                    "the table below is complete.</p>")
    head = ("<tr><th>#</th><th>file</th><th>status</th><th>model</th><th>before [mg]</th><th>held-out [mg]</th>"
            "<th>windows</th><th>reason / message</th></tr>")
    lines, written = [], set()
    for i, r in enumerate(rows):
        page = _slug(i, r["file"])
        (out_dir / "files" / page).write_text(_file_page(r, bases), encoding="utf-8")
        written.add(page)
        lines.append(f"<tr class='file'><td class='num'>{i + 1}</td><td><a href='files/{html.escape(page)}'>"
                     f"{html.escape(r['file'])}</a></td><td>{html.escape(r['status'])}</td>"
                     f"<td>{html.escape(r.get('model', ''))}</td><td class='num'>{_fmt(number(r.get(BEFORE)))}</td>"
                     f"<td class='num'>{_fmt(number(r.get(AFTER)))}</td><td class='num'>"
                     f"{html.escape(r.get('n_windows', ''))}</td><td>{html.escape(r.get('message', ''))}</td></tr>")
    body.append(f"<h2>Files</h2><table id='files'>{head}{''.join(lines)}</table>")
    for stale in (out_dir / "files").glob("[0-9][0-9][0-9][0-9]-*.html"):  # a previous drawing's rows
        if stale.name not in written:
            stale.unlink()
    page = out_dir / "index.html"
    page.write_text(f"<!doctype html><html><head><meta charset='utf-8'><title>gravcal study report: "
                    f"{html.escape(results_csv.name)}</title>{STYLE}</head><body>{''.join(body)}{IMG_CHECK}"
                    f"</body></html>\n", encoding="utf-8")
    return page
