"""The frame kernel's one-frame writer under the one-frame continuation rule (tests/support/sequence_reference.py
decode_one) gives the bytes the decoder's general path gives: every field, the unwrapped seq, the flags and the
counters."""
import numpy as np
import pytest

from gravcal.drivers.codec import FRAME_LEN, FrameDecoder, encode_frames
from gravcal.drivers.rigs.sources import pattern_blocks
from support.sequence_reference import decode_one


def _chunks(rng: np.random.Generator, n: int) -> list[bytes]:
    """Reads of a stream: mostly one frame each, with losses, duplicates, strays, bit errors,
    garbage, missing ADC readings and reads that split frames."""
    s = next(pattern_blocks(seed=int(rng.integers(1 << 30)), fs=200, duration=n / 200, block=n))
    s["temp"][rng.random(n) < 0.02] = np.nan  # sent as ADC_MISSING
    frames = [encode_frames(s[i:i + 1]) for i in range(n)]
    out, i = [], 0
    while i < n:
        r = rng.random()
        f = frames[i]
        if r < 0.03:
            i += int(rng.integers(1, 40))  # lost frames
            continue
        if r < 0.05:
            out.append(frames[int(rng.integers(0, n))])  # a stray (an old or future frame)
        elif r < 0.07 and out:
            out.append(out[-1])  # a duplicate
        elif r < 0.09:
            k = int(rng.integers(3, FRAME_LEN))
            out.append(f[:k] + bytes([f[k] ^ 0x10]) + f[k + 1:])  # a bit error: CRC fails
        elif r < 0.11:
            k = int(rng.integers(1, FRAME_LEN))
            out += [f[:k], f[k:]]  # split across reads
        elif r < 0.12:
            out.append(bytes(rng.integers(0, 256, int(rng.integers(1, 40)), dtype=np.uint8)))  # garbage
        else:
            out.append(f)
        i += 1
    return out


def _decode(chunks: list[bytes], one_path: bool) -> tuple[bytes, dict]:
    dec, got = FrameDecoder(), []
    for c in chunks:
        one = decode_one(dec, c) if one_path else None
        got.append(dec.feed(c) if one is None else one)
    return np.concatenate(got).tobytes(), dec.stats()


@pytest.mark.parametrize("seed", range(6))
def test_one_frame_path_gives_the_general_paths_bytes_and_counters(seed):
    chunks = _chunks(np.random.default_rng(seed), 3000)
    fast, fast_stats = _decode(chunks, True)
    slow, slow_stats = _decode(chunks, False)
    assert len(slow) > 1500 * 56
    assert fast == slow
    assert fast_stats == slow_stats
    assert slow_stats["crc_errors"] > 0 and slow_stats["gaps"] > 0 and slow_stats["strays"] > 0


def test_frame_kernel_judges_frames_and_rejects_wrong_buffers():
    from gravcal.drivers._framekernel import frame_header, frame_to_row

    s = next(pattern_blocks(seed=3, fs=200, duration=1, block=4))
    frame = encode_frames(s[:1])
    assert frame_header(frame) == (int(s["seq"][0]) & 0xFFFF, int(s["tick"][0]))
    assert frame_header(frame[:-1]) is None and frame_header(frame + b"\0") is None
    for k in range(FRAME_LEN):  # any damaged byte: sync, length or CRC fails
        assert frame_header(frame[:k] + bytes([frame[k] ^ 0x01]) + frame[k + 1:]) is None
    with pytest.raises(ValueError, match="56-byte SAMPLE_DTYPE"):
        frame_to_row(frame, bytearray(55), 0, 0)
    with pytest.raises(ValueError, match="intact 29-byte frame"):
        frame_to_row(frame[:-1], bytearray(56), 0, 0)
    with pytest.raises(ValueError, match="16 bits"):
        frame_to_row(frame, bytearray(56), 0, 1 << 16)
    with pytest.raises(TypeError):  # a read-only row
        frame_to_row(frame, bytes(56), 0, 0)


def test_frame_kernel_row_equals_wire_to_samples_at_every_adc_code():
    """Each 12-bit temperature and supply code (and the reserved/missing ones, NaN) converts to the
    float32 the numpy form stores, and every other field is carried over as it is."""
    from gravcal.core.samples import SAMPLE_DTYPE
    from gravcal.drivers._framekernel import frame_to_row
    from gravcal.drivers.codec import crc16, to_wire, wire_to_samples

    codes = np.concatenate([np.arange(4096), [4096, 40000, 0xFFFE, 0xFFFF]])
    n = codes.shape[0]
    rec = to_wire(next(pattern_blocks(seed=5, fs=200, duration=n / 200, block=n)))
    rec["temp_raw"] = codes
    rec["vsupply_raw"] = codes[::-1]
    rec["tick"][:2] = [0, 0xFFFFFFFF]
    rec["t1"][:2] = 0xFFFF
    raw = rec.view(np.uint8).reshape(n, FRAME_LEN)
    for i in range(n):
        rec["crc"][i] = crc16(raw[i, :FRAME_LEN - 2].tobytes())
    want = wire_to_samples(rec)
    rows = np.zeros(n, dtype=SAMPLE_DTYPE)
    for i in range(n):
        frame_to_row(raw[i].tobytes(), rows[i:i + 1], int(rec["seq"][i]), 0)
    assert rows.tobytes() == want.tobytes()
