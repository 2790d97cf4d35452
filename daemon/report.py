"""``gravcal diagnose --report DIR``: the Markdown page a user reads first, with PNG plots.

Plots (matplotlib, optional: without it the page says so and keeps the numbers): residual vs
orientation, vs temperature, vs time; measured vs simulated norm-error distributions; Allan
deviation of static stretches against the white-noise line the baseline simulation predicts.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np


def _have_matplotlib() -> bool:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def _plots(d: Any, out: Path) -> list[tuple[str, str]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ws = d.windows
    rb, re_ = d.resid_baseline_g * 1e3, d.resid_extended_g * 1e3
    a = d.baseline_cal.apply(ws.mean)
    u = a / np.linalg.norm(a, axis=1, keepdims=True)
    made: list[tuple[str, str]] = []

    def save(fig, name: str, title: str) -> None:
        fig.tight_layout()
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        made.append((name, title))

    fig, ax = plt.subplots(1, 3, figsize=(11, 3.2), sharey=True)
    for k, lab in enumerate("xyz"):
        ax[k].plot(u[:, k], rb, ".", ms=3, label="baseline")
        ax[k].plot(u[:, k], re_, ".", ms=3, label="extended")
        ax[k].set_xlabel(f"direction u_{lab}")
    ax[0].set_ylabel("1 g - |a| [mg]")
    ax[0].legend()
    save(fig, "residual_vs_orientation.png", "Norm residual vs orientation")
    if d.has_temp:
        fig, ax = plt.subplots(figsize=(6, 3.2))
        ax.plot(ws.aux[:, 0], rb, ".", ms=3, label="baseline")
        ax.plot(ws.aux[:, 0], re_, ".", ms=3, label="extended")
        ax.set_xlabel("temperature [°C]")
        ax.set_ylabel("1 g - |a| [mg]")
        ax.legend()
        save(fig, "residual_vs_temperature.png", "Norm residual vs temperature")
    fig, ax = plt.subplots(figsize=(6, 3.2))
    ax.plot(ws.t / 60, rb, ".", ms=3, label="baseline")
    ax.plot(ws.t / 60, re_, ".", ms=3, label="extended")
    ax.set_xlabel("time [min]")
    ax.set_ylabel("1 g - |a| [mg]")
    ax.legend()
    save(fig, "residual_vs_time.png", "Norm residual vs time")
    if d.compare_baseline is not None:
        fig, ax = plt.subplots(figsize=(6, 3.2))
        bins = np.linspace(min(rb.min(), -1e-3), max(rb.max(), 1e-3), 40)
        ax.hist(rb, bins=bins, density=True, alpha=0.6, label="measured (baseline fit)")
        ax.hist(d.compare_baseline.sim_residuals_g * 1e3, bins=bins, density=True, alpha=0.6,
                label="simulated with the baseline")
        if d.compare_extended is not None and d.compare_extended is not d.compare_baseline:
            ax.hist(d.compare_extended.sim_residuals_g * 1e3, bins=bins, density=True, histtype="step",
                    label="simulated with the extended model")
        ax.set_xlabel("1 g - |a| [mg]")
        ax.legend(fontsize=7)
        save(fig, "distribution_measured_vs_simulated.png", "Window norm errors: measured vs simulated")
    if d.allan is not None:
        fig, ax = plt.subplots(figsize=(6, 3.5))
        for k, lab in enumerate("xyz"):
            ax.loglog(d.allan.tau_s, d.allan.adev_g[:, k] * 1e3, "o-", ms=3, label=f"measured {lab}")
            ax.loglog(d.allan.tau_s, d.allan.white_g[k] * 1e3 / np.sqrt(d.allan.tau_s / d.allan.tau_s[0]), "--",
                      lw=0.8, label=f"white only {lab}")
        ax.set_xlabel("tau [s]")
        ax.set_ylabel("Allan deviation [mg]")
        ax.legend(fontsize=7)
        save(fig, "allan_deviation.png", "Allan deviation of static stretches vs white noise")
    return made


def write_report(d: Any, out_dir: str | Path, *, source: str = "") -> Path:
    """Write out_dir/report.md (+ PNGs when matplotlib is present); returns the page's path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    j = d.to_json_dict()
    b, e = j["baseline"], j["extended"]
    f = lambda x: "n/a" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.3f}"  # noqa: E731
    L = [f"# gravcal diagnose: {source}", "",
         f"{j['n_windows']} quasi-static windows; coverage: {j['coverage']}.", "",
         "## Summary", "",
         "| | model | held-out RMS 1 g - |a| [mg] | in-sample [mg] |", "|---|---|---|---|",
         f"| baseline | {b['model']} | {f(b['heldout_rms_mg'])} | {f(b['insample_rms_mg'])} |",
         f"| extended | {e['model']} | {f(e['heldout_rms_mg'])} | {f(e['insample_rms_mg'])} |", "",
         f"Held-out gain: **{f(e['heldout_gain_mg'])} mg**.", "", "## Findings", ""]
    if j["findings"]:
        for x in j["findings"]:
            L.append(f"- **{x['effect']}**: {x['magnitude'].get('value')} [{x['magnitude'].get('unit', '')}]; "
                     f"ΔBIC {x['evidence'].get('delta_bic')}")
    else:
        L.append("No significant effect (rule: observable, ΔBIC > 10 and lower held-out error).")
    L += ["", "## What the baseline simulation gets wrong", ""]
    for name, sim in (("baseline", b.get("simulation")), ("extended", e.get("simulation"))):
        if not sim:
            continue
        L.append(f"- {name}: disagrees on {', '.join(sim['disagree']) or 'nothing'} "
                 f"(measured RMS {sim['measured']['rms_mg']:.3f} mg, simulated {sim['simulated_mean']['rms_mg']:.3f} mg; "
                 f"p-values {sim['p_value']}, KS p {sim['ks_p_value']})")
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
