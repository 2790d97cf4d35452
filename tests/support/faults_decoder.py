"""Decoder fuzzing: mutated frame streams through the wire decoder; every intact frame must come out."""
from __future__ import annotations

import time

import numpy as np
from gravcal.core.samples import FLAG_GAP_BEFORE, SAMPLE_DTYPE
from gravcal.drivers import codec
from gravcal.drivers.codec import FRAME_LEN, SYNC, FrameDecoder, encode_frames

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
        self.rejectable = 0  # damaged frames whose header survived, not at the stream's end
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
                damaged = self._damage(kind, f)
                # the decoder sees a candidate it must reject: sync and length byte intact, more bytes after
                self.rejectable += damaged[:len(SYNC) + 1] == f[:len(SYNC) + 1] and i < n_frames - 1
                out += damaged
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
