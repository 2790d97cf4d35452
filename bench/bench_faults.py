"""Fault campaign (issue 8, item 5): the daemon's wire, device, disk and socket faults.

    python bench/bench_faults.py [--long] [--json PATH] [--only NAME]

NAME: decoder, replug_serial, replug_can, state_kill, socket_abuse. The default (short) sizes
are the ones the CI tests (tests/test_fault_*.py) run; ``--long`` runs the issue's counts:
10^6 mutated frames, 100 unplug/replug cycles per bus, 1000 SIGKILLs during state writes,
10^4 bad commands, megabyte lines and 100 simultaneous connections. Prints one table (load
held, faults survived, bad inputs tried, nothing lost) and writes the raw figures as JSON.

Each campaign is a function returning a dict of figures; the tests call the same functions
at small sizes and assert on the figures.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from gravcal.core.samples import FLAG_GAP_BEFORE, FLAG_RECONNECT, SAMPLE_DTYPE
from gravcal.drivers import codec
from gravcal.drivers.codec import FRAME_LEN, SYNC, FrameDecoder, encode_frames

# ----------------------------------------------------------------------------------------
# 1. decoder fuzzing
# ----------------------------------------------------------------------------------------

FRAME_MUTATIONS = ("bitflip", "truncate", "drop", "insert_inside", "delete_inside")
BETWEEN_MUTATIONS = ("garbage", "fake_candidate", "duplicate", "partial_copy", "splice", "stray_old", "foreign")


def random_samples(n: int, rng: np.random.Generator, seq0: int = 0) -> np.ndarray:
    """Samples with every wire field random (in range), seq = seq0 + 0..n-1 (unwrapped)."""
    s = np.zeros(n, SAMPLE_DTYPE)
    s["seq"] = seq0 + np.arange(n)
    s["tick"] = rng.integers(0, 2**32, n, dtype=np.uint64)
    s["t1"] = rng.integers(0, 65536, (n, 4))
    s["t2"] = rng.integers(0, 65536, (n, 2))
    s["gyro"] = rng.integers(0, 65536, n)
    s["temp"] = rng.uniform(-40, 120, n)
    s["vsupply"] = rng.uniform(0, 7.4, n)
    return s


class MutatedStream:
    """A frame stream with mutations, and the ground truth needed to judge the decoder.

    Frame mutations damage one frame (bit flips, a truncated tail, the frame dropped, bytes
    inserted into or deleted from it); between frames come garbage, fake candidates (sync +
    the right length byte + random bytes), a duplicated frame, a partial copy of a frame, a
    splice of two frames, a stray old frame (a copy from up to 50 frames back) or a foreign
    frame (CRC-valid, random seq and payload: what a CRC collision would look like).
    ``intact`` are the indices of the frames emitted unmodified and not overlapped by any
    mutation; ``genuine_starts`` the offsets of every CRC-valid frame emitted on purpose.
    """

    def __init__(self, n_frames: int, rng: np.random.Generator, *, p_frame: float = 0.1,
                 p_between: float = 0.1, seq0: int | None = None):
        self.rng = rng
        # the decoder's unwrapped seq starts at the first genuine frame's raw value: no wrap
        # among the first frames (which mutations may destroy), so that value is seq0 + index
        seq0 = int(rng.integers(0, 65536 - 256)) if seq0 is None else seq0
        self.samples = random_samples(n_frames, rng, seq0)
        wire = encode_frames(self.samples)
        frames = [wire[i * FRAME_LEN:(i + 1) * FRAME_LEN] for i in range(n_frames)]
        out = bytearray()
        intact, intact_at, genuine = [], [], []
        counts = dict.fromkeys(FRAME_MUTATIONS + BETWEEN_MUTATIONS, 0)
        self.foreign = 0
        r_frame = rng.random(n_frames)
        r_between = rng.random(n_frames)
        kinds_f = rng.integers(0, len(FRAME_MUTATIONS), n_frames)
        kinds_b = rng.integers(0, len(BETWEEN_MUTATIONS), n_frames)
        for i in range(n_frames):
            if r_between[i] < p_between:
                kind = BETWEEN_MUTATIONS[kinds_b[i]]
                counts[kind] += 1
                piece, valid = self._between(kind, frames, i)
                if valid:
                    genuine.append(len(out))
                out += piece
            f = frames[i]
            if r_frame[i] < p_frame:
                kind = FRAME_MUTATIONS[kinds_f[i]]
                counts[kind] += 1
                out += self._damage(kind, f)
            else:
                intact.append(i)
                intact_at.append(len(out))
                genuine.append(len(out))
                out += f
        self.data = bytes(out)
        self.intact = np.asarray(intact, np.int64)
        self.intact_at = np.asarray(intact_at, np.int64)
        self.genuine_starts = set(genuine)
        self.counts = counts
        self.mutations = sum(counts.values())

    def _damage(self, kind: str, f: bytes) -> bytes:
        rng = self.rng
        if kind == "bitflip":  # 1..3 bits: CRC-16/CCITT (Hamming distance 4) detects every one
            g = bytearray(f)
            for b in rng.choice(FRAME_LEN * 8, int(rng.integers(1, 4)), replace=False):
                g[b >> 3] ^= 1 << (b & 7)
            return bytes(g)
        if kind == "truncate":
            return f[: int(rng.integers(1, FRAME_LEN))]
        if kind == "drop":
            return b""
        k = int(rng.integers(1, FRAME_LEN))
        if kind == "insert_inside":
            return f[:k] + rng.integers(0, 256, int(rng.integers(1, 8)), dtype=np.uint8).tobytes() + f[k:]
        return f[:k] + f[min(FRAME_LEN, k + int(rng.integers(1, 8))):]  # delete_inside

    def _between(self, kind: str, frames: list[bytes], i: int) -> tuple[bytes, bool]:
        """(bytes, whether they are one CRC-valid frame) to put before frame i."""
        rng = self.rng
        if kind == "garbage":
            g = bytearray(rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8).tobytes())
            if rng.random() < 0.5:  # a sync pair somewhere: a candidate the decoder must reject
                k = int(rng.integers(0, len(g)))
                g[k:k + 2] = SYNC
            return bytes(g), False
        if kind == "fake_candidate":
            body = rng.integers(0, 256, FRAME_LEN - 3, dtype=np.uint8).tobytes()
            return SYNC + bytes([codec.PAYLOAD_LEN]) + body[: int(rng.integers(1, FRAME_LEN - 2))], False
        if kind == "duplicate" and i > 0:
            return frames[i - 1], True  # the previous frame again (dropped as a duplicate when it was decoded)
        if kind == "partial_copy":
            return frames[max(0, i - 1)][: int(rng.integers(1, FRAME_LEN))], False
        if kind == "splice" and i > 1:
            k = int(rng.integers(4, FRAME_LEN - 2))  # from 4: the seq byte differs, so it is not frame i-1 itself
            return frames[i - 2][:k] + frames[i - 1][k:], False
        if kind == "stray_old" and i > 2:
            return frames[i - int(rng.integers(2, min(50, i) + 1))], True
        if kind == "foreign":
            self.foreign += 1
            s = random_samples(1, rng)
            # random seq, but not within SeqUnwrapper.STRAY_JUMP_MIN of the stream's: closer, a
            # foreign frame looks like an ordinary loss or a late frame (1 in 512 of CRC collisions)
            m = codec.SeqUnwrapper.STRAY_JUMP_MIN + 1
            s["seq"] = (int(self.samples["seq"][i]) + int(rng.integers(m, 65536 - m))) & 0xFFFF
            return encode_frames(s), True
        return b"", False


def decode_in_chunks(data: bytes, rng: np.random.Generator, max_chunk: int = 600) -> tuple[np.ndarray, dict]:
    """Feed ``data`` to one FrameDecoder in random read sizes (like a serial port)."""
    dec = FrameDecoder()
    got = []
    pos, n = 0, len(data)
    sizes = rng.integers(1, max_chunk, n // max(1, max_chunk // 2) + 16)
    k = 0
    while pos < n:
        if k == sizes.shape[0]:
            sizes = rng.integers(1, max_chunk, 1024)
            k = 0
        step = int(sizes[k])
        k += 1
        got.append(dec.feed(data[pos:pos + step]))
        pos += step
    out = np.concatenate(got) if got else np.zeros(0, SAMPLE_DTYPE)
    return out, dec.stats()


def judge_decoder(ms: MutatedStream, got: np.ndarray, stats: dict) -> dict:
    """Figures: intact frames recovered (exact fields, seq unwrapped right), extras, rejects."""
    want = codec.wire_roundtrip(ms.samples[ms.intact])
    # Real CRC collisions (random bytes that pass the CRC) are located by scanning the whole
    # stream: candidates accepted that were not emitted as frames on purpose.
    starts = codec.scan(ms.data, final=True).starts
    false_accepts = [p for p in starts if p not in ms.genuine_starts]
    excused = np.zeros(ms.intact.shape[0], bool)
    for p in false_accepts:
        excused |= np.abs(ms.intact_at - p) < FRAME_LEN
    # Every decoded sample against the original with its (unwrapped) seq: same fields or bogus.
    orig = codec.wire_roundtrip(ms.samples)
    seq0 = int(orig["seq"][0])
    k = got["seq"] - seq0
    inside = (k >= 0) & (k < orig.shape[0])
    ok = np.zeros(got.shape[0], bool)
    if inside.any():
        g, w = got[inside], orig[k[inside]]
        eq = (g["tick"] == w["tick"]) & (g["t1"] == w["t1"]).all(1) & (g["t2"] == w["t2"]).all(1)
        eq &= (g["gyro"] == w["gyro"]) & np.isclose(g["temp"], w["temp"], equal_nan=True)
        eq &= np.isclose(g["vsupply"], w["vsupply"], equal_nan=True)
        ok[inside] = eq
    recovered = np.zeros(orig.shape[0], bool)
    recovered[k[ok]] = True
    same = recovered[ms.intact]
    lost = ~same & ~excused
    seq = got["seq"]
    gapflag = (got["flags"] & FLAG_GAP_BEFORE) != 0
    steps = np.diff(seq)
    extra = int((~ok).sum())
    return {
        "frames": int(ms.samples.shape[0]),
        "bytes": len(ms.data),
        "mutations": ms.mutations,
        "mutation_counts": ms.counts,
        "intact": int(ms.intact.shape[0]),
        "recovered": int(same.sum()),
        "lost_intact": int(lost.sum()),
        "excused_by_crc_collision": int((~same & excused).sum()),
        "crc_collisions": len(false_accepts),
        "extra_delivered": int(extra),
        "foreign_inserted": ms.foreign,
        "recovered_from_copies": int(recovered.sum() - same.sum()),
        "seq_steps_backwards": int((steps <= 0).sum()),
        "gap_flags_wrong": int((gapflag[1:] != (steps != 1)).sum()),
        "strays_delivered": stats["strays_delivered"],
        "crc_errors": stats["crc_errors"],
        "length_errors": stats["length_errors"],
        "duplicates": stats["duplicates"],
        "strays": stats["strays"],
        "sync_candidates": ms.data.count(SYNC),
    }


def run_decoder(n_frames: int = 20_000, *, seed: int = 0, batch: int = 50_000, p_frame: float = 0.1,
                p_between: float = 0.1) -> dict:
    """Decoder fuzzing in batches of ``batch`` frames (each batch a fresh stream and decoder).

    Batch k draws from ``default_rng([seed, k])``, so a failing batch is replayed on its own
    with ``run_decoder_batch(seed, k, ...)``; ``failing_batches`` lists [k, lost_intact]."""
    total: dict = {"failing_batches": []}
    gen_s = dec_s = 0.0
    for k, done in enumerate(range(0, n_frames, batch)):
        rng = np.random.default_rng([seed, k])
        t0 = time.perf_counter()
        ms = MutatedStream(min(batch, n_frames - done), rng, p_frame=p_frame, p_between=p_between)
        t1 = time.perf_counter()
        try:
            got, stats = decode_in_chunks(ms.data, rng)
        except Exception as exc:  # the figure that matters: nothing may escape
            total["exceptions"] = total.get("exceptions", 0) + 1
            total["last_exception"] = f"batch {k}: {exc!r}"
            continue
        t2 = time.perf_counter()
        gen_s += t1 - t0
        dec_s += t2 - t1
        fig = judge_decoder(ms, got, stats)
        if fig["lost_intact"]:
            total["failing_batches"].append([k, fig["lost_intact"]])
        for name, v in fig.items():
            if isinstance(v, bool):
                total[name] = total.get(name, True) and v
            elif isinstance(v, dict):
                d = total.setdefault(name, {})
                for kk, vv in v.items():
                    d[kk] = d.get(kk, 0) + vv
            else:
                total[name] = total.get(name, 0) + v
    total.setdefault("exceptions", 0)
    total["decode_s"] = round(dec_s, 3)
    total["generate_s"] = round(gen_s, 3)
    total["mutated_frames_per_s"] = round(total.get("frames", 0) / dec_s) if dec_s else None
    total["mb_per_s"] = round(total.get("bytes", 0) / dec_s / 1e6, 2) if dec_s else None
    return total


def run_decoder_batch(seed: int, k: int, n_frames: int = 50_000, *, p_frame: float = 0.25,
                      p_between: float = 0.25) -> tuple[MutatedStream, np.ndarray, dict]:
    """Replay batch ``k`` of ``run_decoder(seed=seed)``: (stream, decoded samples, decoder stats)."""
    rng = np.random.default_rng([seed, k])
    ms = MutatedStream(n_frames, rng, p_frame=p_frame, p_between=p_between)
    got, stats = decode_in_chunks(ms.data, rng)
    return ms, got, stats


# ----------------------------------------------------------------------------------------
# 3. kill -9 while the calibration state is written
# ----------------------------------------------------------------------------------------


def _state(revision: int, rng: np.random.Generator):
    from gravcal.core.calibration import Calibration
    from gravcal.daemon.persistence import CalibrationState

    cal = Calibration.nominal(0.5 + 0.01 * rng.standard_normal(3), 0.04 * (1 + 0.01 * rng.standard_normal(3)), model="6")
    # a realistic size: the estimator's extra state (a 12x12 covariance and a window pool)
    extra = {"cov": rng.standard_normal((12, 12)).tolist(), "pool": rng.standard_normal((300, 4)).tolist()}
    return CalibrationState(cal, revision=revision, updated=time.time(), accepted=True, extra=extra)


def run_state_kill(kills: int = 60, *, seed: int = 0, directory: str | None = None, max_delay_s: float = 0.03) -> dict:
    """Fork a writer that saves revisions 1, 2, 3, ... through StateStore in a loop; SIGKILL it
    at a random moment; load. Every load must give a complete state whose revision is the last
    one the writer finished or the one it was writing (old or new), never a corrupt file; the
    temp file an interrupted save leaves is removed by the next load (never accumulates)."""
    from gravcal.daemon.persistence import StateStore

    rng = np.random.default_rng(seed)
    tmp = tempfile.TemporaryDirectory(prefix="gravcal-kill-") if directory is None else None
    root = Path(directory or tmp.name)
    store = StateStore(root)
    store.save(_state(1, rng))
    progress = root / "progress"  # the writer notes each revision it finished (O_APPEND, 8 bytes)
    figures = {"kills": 0, "loads_ok": 0, "loads_corrupt": 0, "loaded_old": 0, "loaded_new": 0,
               "temps_left_by_kills": 0, "max_temps_seen": 0, "temps_after_load": 0, "moved_aside": 0,
               "revision_out_of_range": 0, "writes_completed": 0}
    revision = 1
    states = [_state(r, rng) for r in range(8)]  # pre-built: the child only serialises and writes
    for k in range(kills):
        start_rev = revision + 1
        pid = os.fork()
        if pid == 0:  # the writer: never returns
            try:
                fd = os.open(progress, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
                r = start_rev
                while True:
                    st = states[r % len(states)]
                    st.revision = r
                    store.save(st)
                    os.write(fd, r.to_bytes(8, "little"))
                    r += 1
            finally:
                os._exit(1)
        time.sleep(float(rng.uniform(0, max_delay_s)))
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        figures["kills"] += 1
        done = progress.read_bytes() if progress.exists() else b""
        finished = int.from_bytes(done[-8:], "little") if len(done) >= 8 else revision
        if progress.exists():
            progress.unlink()
        figures["writes_completed"] += max(0, finished - revision)
        temps = [n for n in os.listdir(root) if n.startswith(".state.json.") and n.endswith(".tmp")]
        figures["temps_left_by_kills"] += bool(temps)
        figures["max_temps_seen"] = max(figures["max_temps_seen"], len(temps))
        res = store.load()
        if res.state is None:
            figures["loads_corrupt"] += 1
            figures["moved_aside"] += res.moved_to is not None
            store.save(_state(finished, rng))  # carry on from a good file
            revision = finished
            continue
        figures["loads_ok"] += 1
        got = res.state.revision
        # old = the last revision whose write returned; new = the one being written (its rename
        # may have happened just before the kill, after which the progress note was not written)
        if got == finished:
            figures["loaded_old"] += 1
        elif got == finished + 1:
            figures["loaded_new"] += 1
        else:
            figures["revision_out_of_range"] += 1
        revision = got
        figures["temps_after_load"] += sum(1 for n in os.listdir(root) if n.endswith(".tmp"))
    if tmp is not None:
        tmp.cleanup()
    return figures


# ----------------------------------------------------------------------------------------
# 2. unplug / replug under a running gravcald
# ----------------------------------------------------------------------------------------


def _rss_kb(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def _cpu_s(pid: int) -> float:
    """CPU time [s] (user + system) the process has used so far."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")


class Gravcald:
    """``python -m gravcal.daemon.gravcald --emulate ...`` in a temporary directory, log in a file."""

    def __init__(self, *args: str, fs: float = 100.0):
        self.tmp = tempfile.TemporaryDirectory(prefix="gravcal-faults-")
        root = Path(self.tmp.name)
        self.sock = str(root / "g.sock")
        self.log_path = root / "gravcald.log"
        cmd = [sys.executable, "-m", "gravcal.daemon.gravcald", "--emulate", "--seed", "0", "--fs", str(fs),
               "--socket", self.sock, "--state-dir", str(root / "state"), "--log-level", "info", *args]
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        for k in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID", "LISTEN_FDS", "LISTEN_PID"):
            env.pop(k, None)
        with open(self.log_path, "w") as log:
            self.proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)

    def log(self) -> str:
        return self.log_path.read_text()

    def wait_serving(self, timeout: float = 90.0) -> None:
        from gravcal.daemon.client import Client, ClientError

        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"gravcald exited ({self.proc.returncode}):\n{self.log()[-3000:]}")
            if os.path.exists(self.sock):
                try:
                    with Client(self.sock, timeout=5) as c:
                        if c.status()["device"].get("connected"):
                            return
                except (ClientError, OSError):
                    pass
            time.sleep(0.05)
        raise RuntimeError(f"gravcald not serving within {timeout} s:\n{self.log()[-3000:]}")

    def client(self, timeout: float = 30.0):
        from gravcal.daemon.client import Client

        return Client(self.sock, timeout=timeout)

    def stop(self, timeout: float = 60.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            return -9
        finally:
            self.tmp.cleanup()


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
    d = Gravcald(*args, fs=fs)
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
        rss_kb = _rss_kb(d.proc.pid)
        cpu_s = _cpu_s(d.proc.pid)
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
        "daemon_rss_kb": rss_kb,
        "daemon_cpu_percent": round(100 * cpu_s / wall_s, 1),
        "wall_s": round(wall_s, 1),
    }


# ----------------------------------------------------------------------------------------
# 4. socket abuse
# ----------------------------------------------------------------------------------------


def _watch_phase(c, seconds: float, seq: list, lat: list) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        m = c.read_message(timeout=30)
        if m["class"] == "IMU":
            lat.append(time.monotonic() - m["t"])
            seq.append(m["seq"])


def _abusers(path: str, *, bad_commands: int, mb_lines: int, connections: int, never_read: int,
             garbage_bytes: int, stop: threading.Event, tried: dict) -> list[threading.Thread]:
    def conn():
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(10)
        s.connect(path)
        return s

    def never_reading():  # watch everything, read nothing: the server must drop, then hang up
        socks = []
        for _ in range(never_read):
            s = conn()
            s.sendall(b'?WATCH={"enable":true,"raw":true};\n')
            socks.append(s)
        tried["never_read_clients"] += len(socks)
        stop.wait()
        for s in socks:
            s.close()

    def bad_commands_sender():
        s = conn()
        reader = threading.Thread(target=lambda: _drain(s), daemon=True)
        reader.start()
        lines = [b"hello\n", b"?FOO;\n", b'?WATCH={"speed":3};\n', b"?WATCH={nope;\n", b"?POLL=1;\n",
                 b'?WATCH={"rate":-1};\n', b"\xff\xfe\x00garbage\n", b";;;;\n"]
        for i in range(bad_commands):
            s.sendall(lines[i % len(lines)])
            tried["bad_commands"] += 1
        s.close()

    def megabyte_lines():
        for _ in range(mb_lines):
            s = conn()
            try:
                s.sendall(b"?" + b"X" * (1 << 20) + b"\n")
                tried["megabyte_lines"] += 1
            except OSError:
                tried["megabyte_lines_cut_off"] += 1  # hung up on us mid-line: allowed
            s.close()

    def garbage():
        s = conn()
        rng = np.random.default_rng(1)
        data = rng.integers(0, 256, garbage_bytes, dtype=np.uint8).tobytes()
        for k in range(0, len(data), 4096):
            try:
                s.sendall(data[k:k + 4096])
            except OSError:
                break  # hung up on (3 oversized requests): allowed
            tried["garbage_bytes"] += len(data[k:k + 4096])
        s.close()

    def crowd():
        socks = []
        for _ in range(connections):
            try:
                socks.append(conn())
            except OSError:
                tried["connections_refused"] += 1  # connect() failed: the server never saw it
        tried["connections"] += len(socks)
        for s in socks:  # the first line says which: VERSION (accepted) or ERROR (over the limit)
            first = _first_line(s)
            if first.get("class") == "VERSION":
                tried["crowd_accepted"] += 1
            elif first.get("class") == "ERROR" and "too many clients" in first.get("message", ""):
                tried["crowd_told_too_many"] += 1
            else:
                tried["crowd_no_answer"] += 1
        stop.wait()
        for s in socks:
            s.close()

    threads = [threading.Thread(target=t, daemon=True) for t in (never_reading, bad_commands_sender, megabyte_lines, garbage, crowd)]
    for t in threads:
        t.start()
    return threads


def _first_line(s: socket.socket, timeout: float = 10.0) -> dict:
    """The first protocol message on ``s`` as a dict ({} on timeout, EOF or garbage)."""
    buf = b""
    s.settimeout(timeout)
    try:
        while b"\n" not in buf:
            chunk = s.recv(4096)
            if not chunk:
                break
            buf += chunk
        return json.loads(buf.split(b"\n", 1)[0])
    except (OSError, ValueError):
        return {}


def _drain(s: socket.socket) -> None:
    try:
        while s.recv(65536):
            pass
    except OSError:
        pass


def run_socket_abuse(*, seconds: float = 6.0, bad_commands: int = 2000, mb_lines: int = 3, connections: int = 100,
                     never_read: int = 4, garbage_bytes: int = 1 << 20, speed: float = 2.0, fs: float = 200.0) -> dict:
    """A well-behaved watcher before and during abuse of a running gravcald (emulated serial)."""
    d = Gravcald("--bus", "serial", "--scenario", "static", "--speed", str(speed), "--duration", "100000",
                 "--driver-options", "batch_frames=1", fs=fs)
    tried = dict.fromkeys(["never_read_clients", "bad_commands", "megabyte_lines", "megabyte_lines_cut_off",
                           "garbage_bytes", "connections", "connections_refused", "crowd_accepted",
                           "crowd_told_too_many", "crowd_no_answer"], 0)
    stop = threading.Event()
    try:
        d.wait_serving()
        probe = d.client()
        with d.client() as c:
            c.set_watch(enable=True, rate=0)
            seq0, lat0, seq1, lat1 = [], [], [], []
            _watch_phase(c, seconds, seq0, lat0)
            rss0 = _rss_kb(d.proc.pid)
            threads = _abusers(d.sock, bad_commands=bad_commands, mb_lines=mb_lines, connections=connections,
                               never_read=never_read, garbage_bytes=garbage_bytes, stop=stop, tried=tried)
            poll_ms = []

            def poller():
                while not stop.is_set():
                    t = time.monotonic()
                    probe.poll()
                    poll_ms.append((time.monotonic() - t) * 1e3)
                    stop.wait(0.05)

            pt = threading.Thread(target=poller, daemon=True)
            pt.start()
            _watch_phase(c, seconds, seq1, lat1)
            rss1 = _rss_kb(d.proc.pid)
            stop.set()
            for t in threads + [pt]:
                t.join(30)
            st = c.status()
        probe.close()
    finally:
        stop.set()
        code = d.stop()
    seq = np.asarray(seq0 + seq1)
    steps = np.diff(seq)
    p = lambda x, q: round(float(np.percentile(np.asarray(x) * 1e3, q)), 2) if x else None
    return {
        **tried,
        "samples_received": int(seq.size),
        "samples_during_abuse": len(seq1),
        "expected_during_abuse": round(seconds * fs * speed),
        "seq_gaps": int((steps > 1).sum()),
        "seq_backwards": int((steps <= 0).sum()),
        "latency_ms_p50_before": p(lat0, 50), "latency_ms_p99_before": p(lat0, 99),
        "latency_ms_p50_abused": p(lat1, 50), "latency_ms_p99_abused": p(lat1, 99),
        "poll_rtt_ms_p99": round(float(np.percentile(poll_ms, 99)), 2) if poll_ms else None,
        "polls": len(poll_ms),
        "rss_kb_before": rss0, "rss_kb_abused": rss1,
        "clients_rejected": st["server"]["clients_rejected"],
        "clients_stalled": st["server"]["clients_stalled"],
        "inbox_overruns": st["server"]["inbox_overruns"],
        "ring_overwritten": st["ring"]["overwritten"],
        "device_gaps": st["device"].get("gaps"),
        "daemon_exit_code": code,
    }


# ----------------------------------------------------------------------------------------
# the command
# ----------------------------------------------------------------------------------------

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
                f"{f['gaps_flagged_reconnect']} gaps flagged, {f['unexpected_gaps']} unexpected gaps; replug to first "
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
