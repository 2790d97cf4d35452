"""Unplug/replug under a running gravcald: every gap flagged, nothing lost beyond the outage."""
from __future__ import annotations

import time

import numpy as np
from gravcal.core.samples import FLAG_GAP_BEFORE, FLAG_RECONNECT

from .gravcald_process import GravcaldProcess, cpu_s, overrun_events, rss_kb


def run_replug(bus: str = "serial", cycles: int = 5, *, speed: float = 10.0, fs: float = 100.0,
               first_s: float = 30.0, up_s: float = 8.0, down_s: float = 3.0) -> dict:
    """gravcald --emulate --bus BUS with ``cycles`` disconnects of ``down_s`` sensor seconds every
    ``up_s + down_s``; one raw watcher from before the first unplug to after the last replug.
    Judged per gap: the last sample before it is the one sent just before the unplug, the first
    after it carries FLAG_RECONNECT|FLAG_GAP_BEFORE and comes within the reconnect backoff of the
    replug, and the stream between gaps has no missing seq."""
    plan = [(first_s + i * (up_s + down_s), down_s) for i in range(cycles)]
    end_s = plan[-1][0] + down_s + up_s
    args = ["--bus", bus, "--scenario", "static", "--speed", str(speed), "--duration", str(end_s + 60)]
    for start, dur in plan:
        args += ["--disconnect-at", f"{start}:{dur}"]
    d = GravcaldProcess(None, *args, fs=fs)
    t0 = time.monotonic()
    seq: list[int] = []
    flags: list[int] = []
    try:
        d.wait_serving()
        with d.client() as c:
            c.set_watch(enable=True, rate=0, raw=True)
            deadline = time.monotonic() + end_s / speed * 3 + 60
            while not seq or seq[-1] / fs < end_s:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"stream stalled at sensor time {seq[-1] / fs if seq else None}:\n{d.log()[-3000:]}")
                m = c.read_message(timeout=30)
                if m["class"] == "IMU":
                    seq.append(m["seq"])
                    flags.append(m["flags"])
            st = c.status()
        rss = rss_kb(d.proc.pid)
        cpu = cpu_s(d.proc.pid)
    finally:
        code = d.stop()
    wall_s = time.monotonic() - t0
    s, f = np.asarray(seq), np.asarray(flags)
    steps = np.diff(s)
    gaps = np.flatnonzero(steps != 1) + 1
    backoff_sensor_s = 1.0 * speed  # the driver's reconnect backoff is at most 1 s of wall time
    matched, late, flagged, lost_before, unexpected = 0, [], 0, [], []
    seen = [p for p in plan if p[0] > s[0] / fs]  # unplugs after the watcher started
    for k in gaps:
        before, after = s[k - 1] / fs, s[k] / fs
        hit = [p for p in seen if abs(before - p[0]) < 1.0]
        if hit:
            matched += 1
            start, dur = hit[0]
            lost_before.append(start - before)
            late.append(after - (start + dur))
            flagged += bool(f[k] & FLAG_RECONNECT and f[k] & FLAG_GAP_BEFORE)
        else:  # what the gap looked like, to tell a lost stretch from a stray or a bad unwrap
            near = min(plan, key=lambda p: abs(before - p[0]))
            unexpected.append({"seq_before": int(s[k - 1]), "seq_after": int(s[k]), "flags_after": int(f[k]),
                               "nearest_unplug_s": near[0], "before_minus_unplug_s": round(before - near[0], 3)})
    return {
        "bus": bus, "cycles": cycles, "speed": speed, "fs_hz": fs,
        "unplugs_seen_by_client": len(seen),
        "gaps": int(gaps.size),
        "gaps_matching_unplugs": matched,
        "gaps_flagged_reconnect": flagged,
        "unexpected_gaps": int(gaps.size - matched),
        "unexpected_gap_details": unexpected[:20],
        # gaps the emulator reports as its link's overruns (the host read too late; flagged, and a matter of load)
        "emulator_overruns": len(overrun_events(st)),
        "unexpected_gaps_flagged": sum(bool(g["flags_after"] & FLAG_GAP_BEFORE) for g in unexpected),
        "backwards_steps": int((steps <= 0).sum()),
        "samples_received": int(s.size),
        "max_lost_before_unplug_s": round(float(max(lost_before)), 3) if lost_before else None,
        "max_replug_to_first_sample_s": round(float(max(late)), 3) if late else None,
        "replug_bound_s": backoff_sensor_s + 1.0,
        "daemon_reconnects": st["device"].get("reconnects"),
        "daemon_read_errors": st["device"].get("read_errors"),
        "daemon_device_counters": {k: v for k, v in st["device"].items() if k in (
            "gaps", "missing", "duplicates", "strays", "strays_delivered", "crc_errors", "garbled_lines",
            "orphan_frames", "partial", "bad_frames", "foreign_frames", "disconnects", "reconnect_failures")},
        "daemon_exit_code": code,
        "daemon_rss_kb": rss,
        "daemon_cpu_percent": round(100 * cpu / wall_s, 1),
        "wall_s": round(wall_s, 1),
    }
