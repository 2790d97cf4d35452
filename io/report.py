"""``gravcal diagnose --report DIR``: the Markdown page a user reads first, with PNG plots.

Plots (matplotlib, optional: without it the page says so and keeps the numbers): residual vs
orientation, vs temperature, vs time; measured vs simulated norm-error distributions; Allan
deviation of static stretches against the white-noise line. Every plot has a title and labelled
axes; the baseline and the extended model keep one colour each on every plot, and each axis x/y/z
one colour (measured and its white-noise line alike). The page shows numbers and tables, never a
Python dict.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

BASELINE_COLOR, EXTENDED_COLOR, SIMULATED_COLOR = "tab:blue", "tab:orange", "tab:gray"
AXIS_COLORS = {"x": "tab:red", "y": "tab:green", "z": "tab:purple"}
NORM_LABEL = "1 g − |a| [mg]"


def unit_text(name: str) -> str:
    """A term's unit name (core/estimators/extended.py magnitudes, the JSON's) as a reader writes it:
    mg_per_C -> mg/°C, pct_per_h -> %/h, deg_from_orthogonal -> ° from orthogonal."""
    num, _, den = name.partition("_per_")
    num = {"pct": "%", "deg_from_orthogonal": "° from orthogonal"}.get(num, num)
    return f"{num}/{'°C' if den == 'C' else den}" if den else num


def _have_matplotlib() -> bool:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def num(x: Any, digits: int = 3) -> str:
    """A number for the page: 3 significant digits, n/a for None / non-finite."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "n/a"
    if isinstance(x, (int, np.integer)) and not isinstance(x, bool):
        return str(int(x))
    return f"{float(x):.{digits}g}"


def _plots(d: Any, out: Path) -> list[tuple[str, str]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ws = d.windows
    rb, re_ = d.resid_baseline_g * 1e3, d.resid_extended_g * 1e3
    a = d.baseline_cal.apply(ws.mean)
    u = a / np.linalg.norm(a, axis=1, keepdims=True)
    made: list[tuple[str, str]] = []
    base_lab, ext_lab = f"baseline ({d.base_model})", f"extended ({d.extended_model})"

    def save(fig, name: str, title: str) -> None:
        fig.suptitle(title) if len(fig.axes) > 1 else fig.axes[0].set_title(title)
        fig.tight_layout()
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        made.append((name, title))

    def residuals(ax, x) -> None:
        ax.plot(x, rb, ".", ms=3, color=BASELINE_COLOR, label=base_lab)
        ax.plot(x, re_, ".", ms=3, color=EXTENDED_COLOR, label=ext_lab)
        ax.axhline(0.0, color="k", lw=0.5)

    fig, ax = plt.subplots(1, 3, figsize=(11, 3.4), sharey=True)
    for k, lab in enumerate("xyz"):
        residuals(ax[k], u[:, k])
        ax[k].set_xlabel(f"gravity direction component u_{lab} [-]")
    ax[0].set_ylabel(NORM_LABEL)
    ax[0].legend(fontsize=7)
    save(fig, "residual_vs_orientation.png", "Window norm residual vs orientation")
    if d.has_temp:
        fig, ax = plt.subplots(figsize=(6, 3.4))
        residuals(ax, ws.aux[:, 0])
        ax.set_xlabel("temperature [°C]")
        ax.set_ylabel(NORM_LABEL)
        ax.legend(fontsize=7)
        save(fig, "residual_vs_temperature.png", "Window norm residual vs temperature")
    fig, ax = plt.subplots(figsize=(6, 3.4))
    residuals(ax, ws.t / 60)
    ax.set_xlabel("time [min]")
    ax.set_ylabel(NORM_LABEL)
    ax.legend(fontsize=7)
    save(fig, "residual_vs_time.png", "Window norm residual vs time")
    present = [x for x in (d.verdict or {}).get("structure", []) if x["present"]]
    if present and present[0]["covariate"] in (d.structure_curves or {}):
        x_s = present[0]
        c, fitted = d.structure_curves[x_s["covariate"]]
        scale, unit = (1 / 60, "min") if x_s["covariate"] == "time" else (1.0, {"temperature": "°C", "temperature rate": "°C/h", "supply": "V"}[
            x_s["covariate"]])
        fig, ax = plt.subplots(figsize=(6, 3.4))
        ax.plot(c * scale, re_, ".", ms=3, color=EXTENDED_COLOR, label=f"residual, {ext_lab}")
        ax.plot(c * scale, fitted * 1e3, "x", ms=3, color="k", label=f"structure left ({x_s['structure_rms_mg']:.3g} mg RMS)")
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_xlabel(f"{x_s['covariate']} [{unit}]")
        ax.set_ylabel(NORM_LABEL)
        ax.legend(fontsize=7)
        save(fig, "residual_structure.png", f"What the model leaves: residual vs {x_s['covariate']}")
    if d.compare_baseline is not None:
        fig, ax = plt.subplots(figsize=(6, 3.4))
        bins = np.linspace(min(rb.min(), -1e-3), max(rb.max(), 1e-3), 40)
        ax.hist(rb, bins=bins, density=True, alpha=0.6, color=BASELINE_COLOR, label=f"measured, {base_lab} fit")
        ax.hist(d.compare_baseline.sim_residuals_g * 1e3, bins=bins, density=True, alpha=0.5, color=SIMULATED_COLOR,
                label=f"simulated with the {base_lab}")
        if d.compare_extended is not None and d.compare_extended is not d.compare_baseline:
            ax.hist(d.compare_extended.sim_residuals_g * 1e3, bins=bins, density=True, histtype="step", lw=1.5,
                    color=EXTENDED_COLOR, label=f"simulated with the {ext_lab}")
        ax.set_xlabel(NORM_LABEL)
        ax.set_ylabel("density [1/mg]")
        ax.legend(fontsize=7)
        save(fig, "distribution_measured_vs_simulated.png", "Window norm errors: measured vs simulated")
    if d.allan is not None:
        fig, ax = plt.subplots(figsize=(6, 3.6))
        for k, lab in enumerate("xyz"):
            c = AXIS_COLORS[lab]
            ax.loglog(d.allan.tau_s, d.allan.adev_g[:, k] * 1e3, "o-", ms=3, color=c, label=f"measured {lab}")
            ax.loglog(d.allan.tau_s, d.allan.white_g[k] * 1e3 / np.sqrt(d.allan.tau_s / d.allan.tau_s[0]), "--",
                      lw=0.8, color=c, label=f"white noise only {lab}")
        ax.set_xlabel("averaging time tau [s]")
        ax.set_ylabel("Allan deviation [mg]")
        ax.legend(fontsize=7, ncol=2)
        save(fig, "allan_deviation.png", "Allan deviation of static stretches vs white noise")
    return made


def _finding_rows(x: dict[str, Any]) -> list[str]:
    """One table row per reported axis: value ± std [unit], raw-unit value, or why it is undetermined."""
    mag = x["magnitude"]
    und = mag.get("undetermined", {})
    rows = []
    for k, v in mag.get("value", {}).items():
        sd = mag.get("std", {}).get(k)
        raw, raw_sd = mag.get("raw_value", {}).get(k), mag.get("raw_std", {}).get(k)
        if v is None:
            rows.append(f"| {x['effect']} | {k} | undetermined: {und.get(k, 'not estimated')} | | |")
            continue
        raw_s = "" if raw is None else f"{num(raw)} ± {num(raw_sd)} {mag.get('raw_unit', '')}"
        rows.append(f"| {x['effect']} | {k} | {num(v)} ± {num(sd)} | {unit_text(mag.get('unit', ''))} | {raw_s} |")
    return rows


def _verdict(j: dict[str, Any]) -> list[str]:
    """The verdict first: unexplained (with the structure left), what was withdrawn and why, what is undetermined."""
    v = j.get("verdict") or {}
    L = []
    if v.get("status") == "unexplained":
        L += [f"**Unexplained.** {v['text'][len('unexplained: '):]}", ""]
        if j.get("partial"):
            L += ["Terms that explain part of the residual (not named as its cause; their values are the best fit of an "
                  "effect the catalogue does not describe): " + ", ".join(x["effect"] for x in j["partial"]), ""]
    elif v.get("text"):
        L += [f"Residual of the extended model: {v['text']}.", ""]
    if v.get("structure"):
        L += ["| residual vs | shape | ΔBIC | held-out gain [mg] | RMS [mg] | present |", "|---|---|---|---|---|---|"]
        L += [f"| {x['covariate']} | {x['shape']} (degree {x['degree']}) | {num(x['delta_bic'], 4)} | "
              f"{num(x['heldout_gain_mg'])} | {num(x['structure_rms_mg'])} | {'yes' if x['present'] else 'no'} |"
              for x in v["structure"]]
        L.append("")
    for w in v.get("withdrawn", []):
        L.append(f"- not named **{w['effect']}**: {w['why']}")
    for q, why in (j.get("undetermined") or {}).items():
        L.append(f"- undetermined {q}: {why}")
    return L


def _findings(j: dict[str, Any]) -> list[str]:
    if not j["findings"]:
        return ["No cause named (rule: observable, ΔBIC > 10, lower held-out error, and a positive gain on folds "
                "the selection never saw)."]
    L = []
    for x in j["findings"]:
        if x.get("group"):
            L.append(f"- **{x['group']['text']}**; the table gives {x['magnitude']['conditional']}")
    L += ["", "| effect | axis | value ± std | unit | raw units |", "|---|---|---|---|---|"]
    for x in j["findings"]:
        L += _finding_rows(x)
    L.append("")
    for x in j["findings"]:
        mag, ev = x["magnitude"], x["evidence"]
        if ev.get("delta_bic") is None and "heldout_gain_mg" in ev:  # one pose: tested on each channel's reading
            L.append(f"- **{x['effect']}**: {ev['test']}; held-out RMS per channel {num(ev['heldout_rms_mg_without'])}"
                     f" → {num(ev['heldout_rms_mg_with'])} mg ({ev['heldout_scheme']}); chi² {num(ev['chi2'], 4)}")
        else:
            L.append(f"- **{x['effect']}**: ΔBIC {num(ev.get('delta_bic'), 4)} "
                     f"(threshold {num(ev.get('delta_bic_threshold'))}); "
                     f"held-out RMS {num(ev.get('heldout_rms_mg_without'))} → {num(ev.get('heldout_rms_mg_with'))} mg; "
                     f"gain on folds the selection never saw {num(ev.get('nested_heldout_gain_mg'))} mg")
        for note in mag.get("notes", []):
            L.append(f"  - {note}")
        if mag.get("convention"):
            L.append(f"  - convention: {mag['convention']}")
        if mag.get("held"):
            L.append(f"  - std includes what the fit held: {'; '.join(mag['held'])}")
        if mag.get("confounded_with"):
            L.append(f"  - cannot be told apart from {', '.join(mag['confounded_with'])} on this recording")
        slopes = mag.get("raw_channel_slopes")
        if slopes:
            L.append("  - raw channel slopes (independent least squares): " + ", ".join(
                f"{a} {num(slopes['value'][a])} ± {num(slopes['std'][a])}" for a in "xyz") + f" {slopes['unit']}")
    return L


def _simulation(name: str, sim: dict[str, Any]) -> list[str]:
    keys = list(sim["measured"])
    L = [f"**{name}** — disagrees on: {', '.join(sim['disagree']) or 'nothing'}; KS p = {num(sim['ks_p_value'])}", "",
         "| statistic | measured | simulated mean | simulated 95 % | p |", "|---|---|---|---|---|"]
    for k in keys:
        L.append(f"| {k} | {num(sim['measured'].get(k))} | {num(sim['simulated_mean'].get(k))} | "
                 f"{num(sim['simulated_p95'].get(k))} | {num(sim['p_value'].get(k))} |")
    return L + [""]


def write_report(d: Any, out_dir: str | Path, *, source: str = "") -> Path:
    """Write out_dir/report.md (+ PNGs when matplotlib is present); returns the page's path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    j = d.to_json_dict()
    b, e = j["baseline"], j["extended"]
    cov = j["coverage"] or {}
    cov_s = (f"{num(cov.get('distinct_postures'))} distinct postures, spread {num(cov.get('spread_deg'))}°, scatter "
             f"eigenvalues {', '.join(num(v) for v in cov.get('scatter_eig', []))}")
    L = [f"# gravcal diagnose: {source}", "",
         f"{j['n_windows']} quasi-static windows; coverage: {cov_s}.", "",
         "## Summary", "",
         "| | model | held-out RMS 1 g − \\|a\\| [mg] | in-sample [mg] |", "|---|---|---|---|",
         f"| baseline | {b['model']} | {num(b['heldout_rms_mg'])} | {num(b['insample_rms_mg'])} |",
         f"| extended | {e['model']} | {num(e['heldout_rms_mg'])} | {num(e['insample_rms_mg'])} |", "",
         f"Held-out gain: **{num(e['heldout_gain_mg'])} mg** (folds the selection never saw: contiguous time blocks).",
         "", "## Verdict", ""]
    L += _verdict(j)
    L += ["", "## Findings", ""]
    L += _findings(j)
    L += ["", "## What the baseline simulation gets wrong", ""]
    for name, sim in (("baseline", b.get("simulation")), ("extended", e.get("simulation"))):
        if sim:
            L += _simulation(name, sim)
    L += ["", "## Untestable", ""]
    L += [f"- {u['effect']}: {u['why']}" for u in j["untestable"]] or ["(none)"]
    L += ["", "## Tested, not found", ""]
    L += [f"- {u['effect']}: {u['why']}" for u in j["not_found"]] or ["(none)"]
    if j["notes"]:
        L += ["", "## Notes", ""] + [f"- {n}" for n in j["notes"]]
    L += ["", "## Plots", ""]
    if _have_matplotlib() and d.windows is not None:
        for name, title in _plots(d, out):
            L += [f"### {title}", "", f"![{title}]({name})", ""]
    else:
        L.append("matplotlib is not installed: no plots (pip install 'gravcal[figures]'); the numbers above are complete.")
    page = out / "report.md"
    page.write_text("\n".join(L) + "\n", encoding="utf-8")
    return page
