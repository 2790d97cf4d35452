"""The benchmarks page (docs/benchmarks.md) from run_all.py's report: one section per part."""
from __future__ import annotations

from typing import Any


def _n(x: Any, fmt: str = "{:.2f}") -> str:
    if x is None:
        return "—"
    if isinstance(x, (bool, int)):
        return str(x)
    if isinstance(x, float):
        return fmt.format(x)
    return str(x)


def _table(header: list[str], rows: list[list[Any]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for r in rows:
        out.append("| " + " | ".join(str(c).replace("|", "/").replace("\n", " ") for c in r) + " |")
    return out


def _cell(m: dict[str, Any]) -> str:
    from bench_accuracy import method_cell

    return method_cell(m)


def render_accuracy(d: dict[str, Any]) -> list[str]:
    out: list[str] = []
    recs = d.get("recordings", {})
    out.append("Held-out RMS of | |a| − 1 g | [mg] over the SAME quasi-static windows (gravcal's detector, defined once "
               "per recording). *blocks*: 5 contiguous time blocks, each the test part once; *halves*: fit first half / "
               "test second and the reverse; *insample*: fit and score on everything (not held out). A method that "
               "declines a fold (its own criteria) is marked; *as used* scores it with the data it hands back "
               "(uncalibrated). Lower is better.")
    if d.get("peer_input") == "windows":
        out.append("")
        out.append("The peers here get the SAME windows as gravcal (the fit part's evaluation windows: means in nominal g "
                   "and their temperatures), and their own full model is fitted on them and applied to the held-out "
                   "windows (bench/peers_windows.py): *skdh* is scikit-digital-health's closest-point fit, GGIR's "
                   "g.calibrate (van Hees 2014) as skdh ports it: the GGIR-style fit, offset, scale and temperature "
                   "per axis; *actipy* is actipy's calibrate_gravity on those windows (its minimum-count and cube gates "
                   "opened, its fixed 10 mg post-fit gate kept). A gate of the tool that cannot be opened still "
                   "declines: skdh's ±0.3 g sphere test inside its fit, actipy's 10 mg. imucal needs its annotated "
                   "Ferraris sections, not windows: it is in the run on the raw samples only.")
    for name, e in recs.items():
        out.append("")
        if "error" in e and "heldout" not in e:
            out.append(f"**{name}**: {e['error']}")
            continue
        out.append(f"**{name}** — {e['hours']:.2f} h at {e['fs']:g} Hz, {e['windows']} evaluation windows; {e['note']}"
                   + ("; with temperature" if e.get("temperature") else ""))
        out.append("")
        schemes = list(e["heldout"])
        methods = list(e["heldout"][schemes[0]]["methods"])
        rows = [[m] + [_cell(e["heldout"][s]["methods"][m]) for s in schemes] for m in methods]
        out += _table(["method"] + schemes, rows)
        reasons = []
        for m in methods:
            dec = [x for s in schemes for x in e["heldout"][s]["methods"][m]["declined"]]
            if dec:
                reasons.append(f"- {m} declined {len(dec)} fold(s), e.g.: {dec[0].split(': ', 1)[-1][:220]}")
        if reasons:
            out.append("")
            out += reasons
        if "parameters" in e:
            out.append("")
            out.append("Against the truth (full-recording fit, at the median still temperature): offsets [mg], "
                       "sensitivities [%], norm error over the whole sphere [mg].")
            out.append("")
            rows = []
            for m, p in e["parameters"].items():
                if p["ok"]:
                    rows.append([m, _n(p["max_offset_err_mg"]), _n(p["max_sens_err_pct"], "{:.3f}"),
                                 _n(p["sphere_norm_rms_mg"]),
                                 ", ".join(f"{x:+.2f}" for x in p["offset_err_mg"]),
                                 ", ".join(f"{x:+.3f}" for x in p["sens_err_pct"])])
                else:
                    rows.append([m, "declined", "", "", p["message"][:160], ""])
            out += _table(["method", "max offset err mg", "max sens err %", "sphere norm RMS mg", "offset err x,y,z mg",
                           "sens err x,y,z %"], rows)
    verdict = accuracy_verdict(d)
    if verdict:
        out += ["", "**Goal (gravcal lower than every peer on every recording)**, scored on the folds both "
                "calibrated (the same held-out windows). *open*: a peer calibrated folds that gravcal declined; "
                "a refusal is gravcal's verdict that the fold's data do not determine a calibration (its predicted "
                "error over all orientations exceeds its limit), not an error of some size: those folds are shown "
                "(the peer's held-out error there, the uncalibrated one, gravcal's reason), not scored.", ""] + verdict
    return out


def _pooled(m: dict[str, Any], folds: set[int], windows: list[int]) -> float:
    """The RMS [mg] over the held-out windows of ``folds`` from the per-fold RMS and window counts."""
    n = sum(windows[i] for i in folds)
    return (sum(windows[i] * m["fold_rms_mg"][i] ** 2 for i in folds) / n) ** 0.5


def _two(a: float, b: float) -> tuple[str, str]:
    """Two errors at 2 decimals, or 4 where 2 would print them equal."""
    fmt = "{:.2f}" if f"{a:.2f}" != f"{b:.2f}" else "{:.4f}"
    return fmt.format(a), fmt.format(b)


def accuracy_verdict(d: dict[str, Any]) -> list[str]:
    """Per recording and held-out scheme: gravcal against each peer that calibrated, scored on the folds
    both calibrated (the same held-out windows; gravcal's best variant there). A fold that only the peer
    calibrated is not scored either way: gravcal declined it (its predicted error over all orientations
    exceeds its limit: the fold's data do not determine the calibration), a verdict rather than an error of
    some size. Such a cell is *open* and shows what each side did there: the peer's held-out and the
    uncalibrated error on those folds, and gravcal's reason."""
    lines = []
    for name, e in d.get("recordings", {}).items():
        if "heldout" not in e:
            continue
        for s in ("blocks", "halves", "insample"):
            if s not in e["heldout"]:
                continue
            sch = e["heldout"][s]
            ms, windows = sch.get("methods", {}), sch.get("test_windows", [])
            fitted = {m: {i for i, x in enumerate(r.get("fold_rms_mg", [])) if x is not None} for m, r in ms.items()}
            gs = [m for m in ms if m.startswith("gravcal") and fitted[m]]
            ps = [m for m in ms if not m.startswith(("gravcal", "nominal")) and fitted[m]]
            tag = " (in-sample, not held out)" if s == "insample" else ""
            if not ps:
                if s == "insample":
                    continue
                full = [m for m in gs if ms[m]["folds_fitted"] == ms[m]["folds"]]
                if full:
                    b = min(full, key=lambda m: ms[m]["heldout_rms_mg"])
                    who = f"gravcal {ms[b]['heldout_rms_mg']:.2f} mg ({b}, every fold)"
                elif gs:
                    b = min(gs, key=lambda m: ms[m]["heldout_rms_mg"])
                    who = (f"gravcal calibrated {ms[b]['folds_fitted']}/{ms[b]['folds']} folds ({b} "
                           f"{ms[b]['heldout_rms_mg']:.2f} mg) and declined the others")
                else:
                    who = "gravcal declined every fold too"
                lines.append(f"- {name} / {s}: no peer calibrated (all declined every fold); {who}")
                continue
            nominal = next((m for m in ms if m.startswith("nominal")), None)
            anyg = set().union(*(fitted[g] for g in gs)) if gs else set()
            words, labels = [], []
            for p in ps:
                pairs = [(g, fitted[g] & fitted[p]) for g in gs if fitted[g] & fitted[p]]
                said = []
                if pairs:
                    most = max(len(c) for _, c in pairs)
                    g, c = min(((g, c) for g, c in pairs if len(c) == most), key=lambda gc: _pooled(ms[gc[0]], gc[1], windows))
                    eg, ep = _pooled(ms[g], c, windows), _pooled(ms[p], c, windows)
                    labels.append("met" if eg < ep else "not met")
                    a, b = _two(eg, ep)
                    said.append(f"{g} {a} mg vs {p} {b} mg on the {len(c)}/{ms[p]['folds']} fold(s) both calibrated")
                only = fitted[p] - anyg
                if only:
                    labels.append("open")
                    why = next((x.split(": ", 1)[1] for g in ["gravcal auto", *gs] if g in ms
                                for x in ms[g]["declined"] if x.startswith(f"fold {min(only)}: ")), "")
                    there = (f", uncalibrated {_pooled(ms[nominal], only, windows):.2f} mg" if nominal else "")
                    said.append(f"{len(only)} fold(s) that {p} calibrated ({_pooled(ms[p], only, windows):.2f} mg there"
                                f"{there}) and every gravcal variant declined, e.g. fold {min(only)}: "
                                f"{' '.join(why.split())[:150]}")
                words.append("; ".join(said))
            label = ("**not met**" if "not met" in labels else "**open**" if "open" in labels else "met")
            lines.append(f"- {name} / {s}{tag}: {label} — " + " | ".join(words))
    return lines


def render_speed(j: dict[str, Any]) -> list[str]:
    """gravcal calibrate vs the peers on the same simulated days (bench_calibrate.py's JSON)."""
    out = ["Simulated daily living at 100 Hz (cached .npy, 20 B/sample); each method a child process on the same "
           "file, right after gravcal (ratios peer / gravcal hold under load). *read* and *calibrate* are "
           "separate; peak RSS from os.wait4. A peer's time to decline is a lower bound on a fit.", ""]
    mb = 1 / 2 ** 20
    peers = (j.get("peers") or {}).get("rows", [])
    rows = []
    for g in j.get("rows", []):
        days = g.get("days")
        rows.append([days, "gravcal", _n(g.get("read_s")), _n(g.get("calibrate_s")), _n(g.get("wall_s")), "1", "1",
                     _n(g.get("peak_rss_bytes", 0) * mb, "{:.0f}"), _n(g.get("rss_ratio")),
                     _n(g.get("truth_err_mg")), f"model {g.get('model')}, {g.get('windows')} windows, held-out "
                     f"{_n(g.get('heldout_rms_mg'))} mg"])
        for r in (x for x in peers if x.get("days") == days):
            rows.append([days, f"{r.get('peer')} ({r.get('form')})", _n(r.get("read_s")), _n(r.get("calibrate_s")),
                         _n(r.get("wall_s")), _n(r.get("calibrate_x_gravcal")), _n(r.get("wall_x_gravcal")),
                         _n(r.get("peak_rss_bytes", 0) * mb, "{:.0f}"), _n(r.get("rss_ratio")),
                         _n(r.get("truth_err_mg")),
                         ("TIMEOUT" if r.get("timed_out") else "calibrated" if r.get("ok") else "DECLINED: ")
                         + ("" if r.get("ok") else str(r.get("message", ""))[:120])])
    out += _table(["days", "method", "read s", "calibrate s", "wall s", "calibrate x", "wall x", "peak RSS MB",
                   "RSS / input", "truth err mg", "result"], rows)
    out.append("")
    na = (j.get("peers") or {}).get("not_applicable") or {}
    missing = (j.get("peers") or {}).get("missing") or {}
    out += [f"- {k}: {v}" for k, v in {**na, **missing}.items()]
    growth = j.get("growth") or {}
    if growth:
        out.append(f"- gravcal growth {growth.get('from_days')} → {growth.get('to_days')} days "
                   f"({_n(growth.get('samples_x'))}x samples): calibrate {_n(growth.get('calibrate_s_x'))}x, "
                   f"read {_n(growth.get('read_s_x'))}x, peak RSS {_n(growth.get('peak_rss_x'))}x")
    for name, g in ((j.get("peers") or {}).get("growth") or {}).items():
        if name != "gravcal" and isinstance(g, dict):
            out.append(f"- {name} growth: calibrate {_n(g.get('calibrate_s'))}x, read {_n(g.get('read_s'))}x, "
                       f"peak RSS {_n(g.get('peak_rss_bytes'))}x")
    t, met = j.get("targets") or {}, j.get("targets_met") or {}
    if t:
        out.append(f"- targets: calibration ≤ {t.get('calibrate_s_7d')} s for 7 days, peak RSS ≤ {t.get('rss_ratio')}x "
                   f"the input; met: {met}")
    return out


def render_daemon(steps: list[dict[str, Any]]) -> list[str]:
    out: list[str] = []
    lat = [s for s in steps if s.get("status") == "ok" and s.get("json", {}).get("what") == "latency"]
    if lat:
        rows = []
        for s in lat:
            j = s["json"]
            every = j["watch_rate_hz"] == 0  # decimated watching: the latency of a kept sample is not frame-in -> out
            lat = [_n(j["read_to_client_ms"]["p50"]), _n(j["read_to_client_ms"]["p99"]), _n(j["wire_to_client_ms"]["p50"]),
                   _n(j["wire_to_client_ms"]["p99"])] if every else ["—"] * 4
            rows.append([s["label"], j["clients"], _n(j["samples_per_s"], "{:.0f}"), *lat, _n(j["cpu_percent_one_core"]),
                         "every sample" if every else f"{j['watch_rate_hz']:g} Hz"])
        out.append("Live: `gravcald --emulate --bus serial --fs 200 --speed 1` (emulator on a pty), clients watching with raw "
                   "fields. *read→client*: driver read returned → line received by the client (acquisition, processing, "
                   "socket); *wire→client* adds the serial driver's batching (16 frames per read = 80 ms at 200 Hz). CPU: "
                   "the gravcald process, % of one core.")
        out.append("")
        out += _table(["run", "clients", "lines/s to the measuring client", "read→client p50 ms", "p99 ms", "wire→client p50 ms", "p99 ms",
                       "CPU % of a core", "watch rate"], rows)
    thr = [s for s in steps if s.get("status") == "ok" and s["script"] == "bench_server.py"]
    if thr:
        rows = []
        for s in thr:
            j = s["json"]
            rows.append([j["clients"], f"{j['samples']:,}", _n(j["daemon_samples_per_s"], "{:,.0f}"),
                         _n(j["end_to_end_samples_per_s"], "{:,.0f}"), _n(j["cpu_s_per_1e5_samples"], "{:.3f}"),
                         j["dropped_messages"], j["ring_overwritten"]])
        out.append("")
        out.append("Replay (as fast as processing takes it; every client watches every sample):")
        out.append("")
        out += _table(["clients", "samples", "daemon samples/s", "end-to-end samples/s", "CPU-s per 1e5 samples",
                       "dropped", "ring overwritten"], rows)
    mem = [s for s in steps if s.get("status") == "ok" and s.get("json", {}).get("what") == "memory"]
    for s in mem:
        j = s["json"]
        out.append("")
        steps_mb = j.get("rss_steps_mb") or []
        out.append(f"Memory: RSS over {j['samples']:,} samples ({j['sensor_hours_at_200hz']:.1f} h at 200 Hz, replay at "
                   f"{j['samples_per_s']:,.0f} samples/s, one watcher at 10 Hz): {j['rss_mb_series'][0][1]:.1f} → "
                   f"{j['rss_mb_end']:.1f} MB (max {j.get('rss_mb_max', j['rss_mb_end']):.1f}); least-squares slope after "
                   f"warm-up {j['slope_mb_per_1e6'] * 1e3:+.2f} kB per 1e6 samples"
                   + (f" → {j['extrapolated_growth_mb_per_1e8']:+.2f} MB over 1e8 samples (extrapolated)" if j["extrapolated"]
                      else f" ({j['extrapolated_growth_mb_per_1e8']:+.2f} MB per 1e8)")
                   + (f"; second half slope {j['slope_second_half_mb_per_1e6'] * 1e3:+.2f} kB per 1e6" if
                      j.get("slope_second_half_mb_per_1e6") is not None else "")
                   + ("; steps > 2 MB at " + ", ".join(f"{a / 1e6:.0f} M samples (+{b:.1f} MB)" for a, b in steps_mb)
                      if steps_mb else "; no step > 2 MB")
                   + ". RSS sampled every 1e6 samples.")
        out.append("")
        out += _table(["samples (M)", "RSS MB"], [[f"{a / 1e6:.0f}", f"{b:.1f}"] for a, b in
                                                  j["rss_mb_series"][:: max(1, len(j["rss_mb_series"]) // 12)]])
    return out


def render_efficiency(j: dict[str, Any]) -> list[str]:
    out = [f"Window level: {j['windows']} windows × {j['samples_per_window']} samples, {j['noise_g'] * 1e3:g} mg/sample, "
           f"model {j['model']}, {j['seeds']} seeds. Efficiency = tr(CRLB)/tr(MSE) (1 = efficient; goal batch ≥ 0.9, "
           "recursive ≥ 0.8); in brackets P/mean(eᵀFe)."]
    out.append("")
    rows = []
    for name, r in j.get("scenarios", {}).items():
        rows.append([name, _n(r["crlb_accel_rms_mg"], "{:.3f}")] + [
            f"{r[k + '_eff']:.3f} ± {r[k + '_eff_se']:.3f} ({1 / r[k + '_whitened']:.3f})" for k in ("batch", "recursive", "ordered")])
    out += _table(["scenario", "CRLB accel mg", "batch", "recursive (IEKF, one pass)", "online (OnlineCalibrator)"], rows)
    if j.get("drift"):
        out.append("")
        out += _table(["start error (% of 1 g)", "recursive", "online", "batch"],
                      [[f"{float(k) * 100:.1f}", f"{r['recursive_eff']:.3f} ± {r['recursive_eff_se']:.3f}",
                        f"{r['ordered_eff']:.3f} ± {r['ordered_eff_se']:.3f}", f"{r['batch_eff']:.3f}"]
                       for k, r in j["drift"].items()])
    if j.get("timing"):
        out.append("")
        out += _table(["cost per window", "µs"], [[k, _n(v, "{:.1f}")] for k, v in j["timing"].items()])
    ts = j.get("time_series")
    if ts:
        out.append("")
        out.append(f"Time series (daily_living 2 h, misaligned sensor): {ts['windows']} windows, order chosen "
                   f"{ts['order_chosen']!r}.")
        out.append("")
        out.append("(Models forced beyond the order chosen are not determined by these windows: their figures show "
                   "why the order rule refuses them.)")
        out.append("")
        out += _table(["model forced", "observable", "eᵀFe/P", "CRLB accel mg", "true error over the sphere mg"],
                      [[m, r.get("observable"), _n(r.get("whitened")), _n(r.get("crlb_accel_mg"), "{:.3f}"),
                        _n(r.get("sphere_error_rms_mg"))]
                       if "error" not in r else [m, r["error"], "", "", ""] for m, r in ts["models"].items()])
    return out


def render_tables(j: Any) -> list[str]:
    """Other helpers' JSON: each list of flat records (dicts) as a table of its own, the rest as figure/value rows."""
    out: list[str] = []
    rest = dict(j) if isinstance(j, dict) else {"value": j}
    for k, v in list(rest.items()):
        if isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            cols: list[str] = []
            for x in v:
                cols += [c for c in x if c not in cols and not isinstance(x[c], (dict, list))]
            if cols:
                out += [f"*{k}* ({len(v)} rows)", ""]
                out += _table(cols, [[_n(x.get(c), "{:.4g}") if isinstance(x.get(c), float) else _n(x.get(c))
                                      for c in cols] for x in v])
                out.append("")
                nested = [{c: x[c] for c in x if isinstance(x[c], (dict, list))} for x in v]
                if any(nested):
                    rest[k] = nested
                else:
                    del rest[k]
    for k, v in list(rest.items()):  # a group of campaigns / sub-benches: one table each
        if isinstance(v, dict) and sum(isinstance(x, dict) for x in v.values()) >= 2:
            for sub, x in v.items():
                out += [f"*{k}: {sub}*", ""] + render_tables(x if isinstance(x, dict) else {sub: x}) + [""]
            del rest[k]
    rows = render_generic(rest)
    if rows:
        out += _table(["figure", "value"], rows[:200])
        if len(rows) > 200:
            out.append(f"({len(rows) - 200} more figures in benchmarks.json)")
    return out


def render_generic(j: Any, prefix: str = "") -> list[list[str]]:
    """Flatten any JSON into (key, value) rows (other helpers' parts: schema not known here)."""
    rows: list[list[str]] = []
    if isinstance(j, dict):
        for k, v in j.items():
            rows += render_generic(v, f"{prefix}.{k}" if prefix else str(k))
    elif isinstance(j, list) and j and all(isinstance(x, (int, float)) for x in j) and len(j) <= 8:
        rows.append([prefix, ", ".join(_n(x, "{:.4g}") for x in j)])
    elif isinstance(j, list):
        if len(j) > 20:
            rows.append([prefix, f"[{len(j)} items]"])
        else:
            for i, v in enumerate(j):
                rows += render_generic(v, f"{prefix}[{i}]")
    else:
        rows.append([prefix, _n(j, "{:.4g}") if isinstance(j, float) else str(j)])
    return rows


def render_part(name: str, part: dict[str, Any]) -> list[str]:
    out = [f"## {name}", ""]
    for s in part["steps"]:
        if s["status"] != "ok":
            out.append(f"- **{s['label']}: {s['status'].upper()}** — {s.get('error', '')}  ")
            out.append(f"  command: `{s['command']}`")
    failed = any(s["status"] != "ok" for s in part["steps"])
    if failed:
        out.append("")
    ok = [s for s in part["steps"] if s["status"] == "ok"]
    if not ok:
        return out
    out.append("Command(s): " + "; ".join(f"`{s['command']}` ({s['seconds']:.0f} s)" for s in ok))
    out.append("")
    try:
        if name == "accuracy":
            for s in ok:
                if len(ok) > 1:
                    out += [f"*{s['label']}*", ""]
                out += render_accuracy(s["json"]) + [""]
        elif name == "daemon":
            out += render_daemon(ok)
        elif name == "efficiency":
            out += render_efficiency(ok[0]["json"])
        elif name == "speed":
            out += render_speed(ok[0]["json"])
        else:
            for s in ok:
                if "json" in s:
                    if len(ok) > 1:
                        out.append(f"*{s['label']}*")
                        out.append("")
                    out += render_tables(s["json"])
                else:
                    out += ["```", s.get("stdout", "").strip()[-6000:], "```"]
    except Exception as exc:  # a schema this page does not know: raw output rather than nothing
        out += [f"(could not render the table: {type(exc).__name__}: {exc}; raw output below)", "", "```",
                "\n".join(s.get("stdout", "").strip()[-4000:] for s in ok), "```"]
    return out


def render_page(report: dict[str, Any]) -> str:
    m, v = report["machine"], report["versions"]
    lines = ["# Benchmarks", "",
             f"Generated by `{report['command']}` on {report['date']} ({'quick' if report['quick'] else 'full'} mode, "
             f"{report['seconds'] / 60:.1f} min)" + (f"; parts not re-run kept from `{report['merged_from'][0]}` of "
                                                    f"{report['merged_from'][1]}" if report.get("merged_from") else "")
             + ". Raw figures: `benchmarks.json` next to this page.", "",
             "## Machine and versions", ""]
    load = m.get("load_avg_at_start")
    lines += _table(["", ""], [["CPU", m["cpu"]], ["cores", m["cores"]], ["RAM", _n(m["ram_gb"], "{:.1f} GB")],
                               ["OS", m["os"]], ["Python", m["python"]], ["Java", report.get("java") or "not found"],
                               ["load average at start", ", ".join(f"{x:.2f}" for x in load) if load else "—"]]
                        + [[k, x or "not installed"] for k, x in v.items()])
    lines += ["", "Peers: " + "; ".join(f"{k}: {'available' if why is None else why}" for k, why in report["peers"].items()),
              ""]
    summary = [[name, p["status"], ", ".join(f"{s['seconds']:.0f} s" for s in p["steps"] if "seconds" in s) or "—"]
               for name, p in report["parts"].items()]
    lines += ["## Parts", ""] + _table(["part", "status", "time"], summary) + [""]
    for name, p in report["parts"].items():
        if p["status"] == "skipped":
            continue
        lines += render_part(name, p) + [""]
    return "\n".join(lines).rstrip() + "\n"
