"""Fault campaign: the daemon's wire, device, disk and socket faults.

    python bench/bench_faults.py [--long] [--json PATH] [--only NAME]

NAME: decoder, replug_serial, replug_can, state_kill, socket_abuse. The default (short) sizes
are the ones the CI tests (tests/*/test_fault_*.py) run; ``--long`` runs the issue's counts:
10^6 mutated frames, 100 unplug/replug cycles per bus, 1000 SIGKILLs during state writes,
10^4 bad commands, megabyte lines and 100 simultaneous connections. Prints one table (load
held, faults survived, bad inputs tried, nothing lost) and writes the raw figures as JSON.

Each campaign is a function returning a dict of figures (tests/support/faults_*.py); the tests
call the same functions at small sizes and assert on the figures.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from support.faults_decoder import run_decoder  # noqa: E402
from support.faults_replug import run_replug  # noqa: E402
from support.faults_socket import run_socket_abuse  # noqa: E402
from support.faults_state import run_state_kill  # noqa: E402

SHORT = {
    "decoder": lambda: run_decoder(20_000, p_frame=0.25, p_between=0.25),
    "replug_serial": lambda: run_replug("serial", 5),
    "replug_can": lambda: run_replug("can", 5),
    "state_kill": lambda: run_state_kill(80),
    "socket_abuse": lambda: run_socket_abuse(),
}
LONG = {
    "decoder": lambda: run_decoder(2_000_000, p_frame=0.25, p_between=0.25),
    "replug_serial": lambda: run_replug("serial", 100, up_s=5.0, down_s=2.0),
    "replug_can": lambda: run_replug("can", 100, up_s=5.0, down_s=2.0),
    "state_kill": lambda: run_state_kill(1000),
    "socket_abuse": lambda: run_socket_abuse(seconds=15.0, bad_commands=10_000, mb_lines=10, connections=100,
                                             never_read=8, garbage_bytes=8 << 20),
}


def summary_row(name: str, f: dict) -> tuple[str, str, str, str, str]:
    """(campaign, load held, faults survived, bad inputs tried, nothing lost)."""
    if name == "decoder":
        return (name, f"{f['mutated_frames_per_s']} frames/s decoded ({f['mb_per_s']} MB/s)",
                f"{f['exceptions']} exceptions",
                f"{f['frames']} frames, {f['mutations']} mutations, {f['crc_errors']} CRC + {f['length_errors']} length rejects",
                f"{f['recovered']}/{f['intact']} intact frames recovered ({f['excused_by_crc_collision']} hidden by "
                f"{f['crc_collisions']} CRC collisions); {f['extra_delivered']} foreign frames delivered of {f['foreign_inserted']}")
    if name.startswith("replug"):
        return (name, f"{f['speed']:g}x real time at {f['fs_hz']:g} Hz, {f['samples_received']} samples",
                f"{f['gaps_matching_unplugs']}/{f['unplugs_seen_by_client']} unplugs, {f['daemon_reconnects']} reconnects, "
                f"exit {f['daemon_exit_code']}",
                f"{f['cycles']} unplug/replug cycles",
                f"{f['gaps_flagged_reconnect']} gaps flagged, {f['unexpected_gaps']} unexpected gaps "
                f"({f['emulator_overruns']} emulator overruns); replug to first "
                f"sample <= {f['max_replug_to_first_sample_s']} s (sensor)")
    if name == "state_kill":
        return (name, f"{f['writes_completed']} writes completed between kills",
                f"{f['loads_ok']}/{f['kills']} loads ok ({f['loaded_old']} old, {f['loaded_new']} new)",
                f"{f['kills']} SIGKILLs, {f['temps_left_by_kills']} mid-write",
                f"{f['loads_corrupt']} corrupt, {f['revision_out_of_range']} wrong revision, "
                f"{f['temps_after_load']} temp files left after load")
    return (name, f"{f['samples_during_abuse']}/{f['expected_during_abuse']} samples during abuse; latency p99 "
                  f"{f['latency_ms_p99_before']} -> {f['latency_ms_p99_abused']} ms; RSS {f['rss_kb_before']} -> "
                  f"{f['rss_kb_abused']} kB; ?POLL p99 {f['poll_rtt_ms_p99']} ms",
            f"exit {f['daemon_exit_code']}, {f['clients_rejected']} rejected, {f['clients_stalled']} stalled dropped",
            f"{f['bad_commands']} bad commands, {f['megabyte_lines']} MB lines, {f['garbage_bytes']} garbage bytes, "
            f"{f['connections']}+{f['connections_refused']} connections ({f['crowd_told_too_many']} told 'too many "
            f"clients', {f['connections_refused']} failed in connect), {f['never_read_clients']} never-reading",
            f"{f['seq_gaps']} seq gaps, {f['inbox_overruns']} inbox overruns, {f['ring_overwritten']} ring overwrites")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--long", action="store_true", help="the issue's counts (about 15-25 minutes)")
    ap.add_argument("--json", metavar="PATH", help="write the raw figures here")
    ap.add_argument("--only", metavar="NAME", choices=sorted(SHORT), help="run one campaign")
    args = ap.parse_args(argv)
    table = LONG if args.long else SHORT
    names = [args.only] if args.only else list(table)
    out = {"machine": {"python": platform.python_version(), "platform": platform.platform(), "cpus": os.cpu_count(),
                       "numpy": np.__version__},
           "command": " ".join([os.path.basename(sys.executable), *sys.argv]), "long": args.long, "campaigns": {}}
    rows = []
    for name in names:
        t0 = time.perf_counter()
        try:
            fig = table[name]()
        except Exception as exc:  # report and go on with the others
            fig = {"error": f"{type(exc).__name__}: {exc}"}
        fig["elapsed_s"] = round(time.perf_counter() - t0, 1)
        out["campaigns"][name] = fig
        rows.append(summary_row(name, fig) if "error" not in fig else (name, "ERROR", fig["error"][:200], "", ""))
        print(f"{name}: done in {fig['elapsed_s']} s", file=sys.stderr)
    head = ("campaign", "load held", "faults survived", "bad inputs tried", "nothing lost")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        print("| " + " | ".join(r) + " |")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
