"""The shared frame codec: CRC, layout, conversions, streaming decode, resynchronisation."""
from __future__ import annotations

import binascii

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gravcal.core.samples import FLAG_GAP_BEFORE, SAMPLE_DTYPE
from gravcal.drivers import codec
from gravcal.drivers.codec import FRAME_LEN, FrameDecoder, SeqUnwrapper, decode_frames, encode_frames


def make_samples(n: int, seed: int = 0, seq0: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    s = np.zeros(n, SAMPLE_DTYPE)
    s["seq"] = seq0 + np.arange(n)
    s["tick"] = rng.integers(0, 2**32, n, dtype=np.uint64)
    s["t1"] = rng.integers(0, 2**16, (n, 4))
    s["t2"] = rng.integers(0, 2**16, (n, 2))
    s["gyro"] = rng.integers(0, 2**16, n)
    s["temp"] = rng.uniform(-40, 120, n)
    s["vsupply"] = rng.uniform(2.5, 6.0, n)
    return s


def assert_same_payload(got: np.ndarray, want: np.ndarray) -> None:
    """Equal in every field the wire carries (seq compared unwrapped as given)."""
    for name in ("seq", "tick", "t1", "t2", "gyro"):
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)
    np.testing.assert_array_equal(got["temp"], want["temp"])
    np.testing.assert_array_equal(got["vsupply"], want["vsupply"])


def test_crc_is_ccitt_false_with_check_value():
    assert codec.crc16(b"123456789") == 0x29B1
    # Residue property the decoder relies on: CRC over frame + big-endian CRC is 0.
    data = b"gravcal frame"
    crc = codec.crc16(data)
    assert binascii.crc_hqx(data + crc.to_bytes(2, "big"), 0xFFFF) == 0


def test_frame_layout_byte_by_byte():
    s = np.zeros(1, SAMPLE_DTYPE)
    s["seq"], s["tick"] = 0x11234, 0xA1B2C3D4
    s["t1"] = [0x0102, 0x0304, 0x0506, 0x0708]
    s["t2"] = [0x090A, 0x0B0C]
    s["gyro"] = 0x0D0E
    s["temp"], s["vsupply"] = 25.0, 3.3
    b = encode_frames(s)
    assert len(b) == FRAME_LEN == 29
    assert b[0:2] == b"\xa5\x5a" and b[2] == 24
    assert b[3:5] == bytes([0x34, 0x12])  # seq mod 2**16, little-endian
    assert b[5:9] == bytes([0xD4, 0xC3, 0xB2, 0xA1])
    assert b[9:17] == bytes([2, 1, 4, 3, 6, 5, 8, 7])
    assert b[17:21] == bytes([0x0A, 0x09, 0x0C, 0x0B])
    assert b[21:23] == bytes([0x0E, 0x0D])
    temp_code = round((0.5 + 0.01 * 25.0) * 4096 / 2.5)  # 1229
    vs_code = round(3.3 / 3 * 4096 / 2.5)  # 1802
    assert int.from_bytes(b[23:25], "little") == temp_code
    assert int.from_bytes(b[25:27], "little") == vs_code
    assert int.from_bytes(b[27:29], "big") == codec.crc16(b[:27])


def test_housekeeping_conversions():
    raw = np.array([0, 1229, 4095, 4096, codec.ADC_MISSING])
    t = codec.temp_from_raw(raw)
    np.testing.assert_allclose(t[:3], (raw[:3] * 2.5 / 4096 - 0.5) / 0.01)
    assert np.isnan(t[3]) and np.isnan(t[4])  # reserved / missing codes
    v = codec.vsupply_from_raw(raw)
    np.testing.assert_allclose(v[:3], raw[:3] * 2.5 / 4096 * 3)
    # saturation like the ADC, NaN -> missing code
    np.testing.assert_array_equal(codec.temp_to_raw([-100.0, 500.0, np.nan]), [0, 4095, codec.ADC_MISSING])
    np.testing.assert_array_equal(codec.vsupply_to_raw([-1.0, 10.0, np.nan]), [0, 4095, codec.ADC_MISSING])


def test_timer_counts_beyond_16_bits_are_refused():
    s = make_samples(3)
    s["t2"][1, 0] = 70000
    with pytest.raises(ValueError, match="T2 = 70000.*16-bit"):
        encode_frames(s)


sample_rows = st.tuples(
    st.integers(0, 2**32 - 1),  # tick
    st.lists(st.integers(0, 2**16 - 1), min_size=4, max_size=4),
    st.lists(st.integers(0, 2**16 - 1), min_size=2, max_size=2),
    st.integers(0, 2**16 - 1),
    st.floats(-50.0, 150.0),
    st.floats(0.0, 7.49),
)


@settings(max_examples=150, deadline=None)
@given(st.lists(sample_rows, min_size=1, max_size=40), st.integers(0, 2**40))
def test_roundtrip_property(rows, seq0):
    s = np.zeros(len(rows), SAMPLE_DTYPE)
    s["seq"] = seq0 + np.arange(len(rows))
    for i, (tick, t1, t2, gyro, temp, vs) in enumerate(rows):
        s[i]["tick"], s[i]["t1"], s[i]["t2"], s[i]["gyro"] = tick, t1, t2, gyro
        s[i]["temp"], s[i]["vsupply"] = temp, vs
    got = decode_frames(encode_frames(s))
    assert got.shape == s.shape
    np.testing.assert_array_equal(got["seq"], s["seq"] & 0xFFFF)
    for name in ("tick", "t1", "t2", "gyro"):
        np.testing.assert_array_equal(got[name], s[name])
    # Housekeeping is quantised by the 12-bit ADC: within half an LSB (+ float32 rounding).
    lsb_t = 2.5 / 4096 / 0.01
    lsb_v = 2.5 / 4096 * 3
    assert np.all(np.abs(got["temp"] - s["temp"]) <= lsb_t / 2 + 1e-4)
    assert np.all(np.abs(got["vsupply"] - s["vsupply"]) <= lsb_v / 2 + 1e-5)
    # ... and the quantised values are a fixed point: re-encoding gives the same bytes.
    again = got.copy()
    again["seq"] = s["seq"]
    assert encode_frames(again) == encode_frames(s)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(1, 200), min_size=0, max_size=30))
def test_any_chunking_gives_the_same_samples(cuts):
    s = make_samples(40, seed=3, seq0=65520)  # crosses the 16-bit wrap
    stream = encode_frames(s)
    dec = FrameDecoder()
    parts, pos = [], 0
    for c in cuts:
        parts.append(dec.feed(stream[pos : pos + c]))
        pos += c
    parts.append(dec.feed(stream[pos:]))
    got = np.concatenate(parts)
    want = codec.wire_roundtrip(s)
    assert_same_payload(got, want)  # unwrapped 65520.. continues past 65535
    assert not (got["flags"] & FLAG_GAP_BEFORE).any()
    assert dec.stats()["frames"] == 40 and dec.stats()["bytes_skipped"] == 0


def corrupt_stream(samples: np.ndarray, rng: np.random.Generator):
    """Frames with random damage. Returns (stream, indices of frames left intact)."""
    frames = [bytearray(encode_frames(samples[i : i + 1])) for i in range(samples.shape[0])]
    out = bytearray()
    intact = []
    for i, f in enumerate(frames):
        r = rng.random()
        if r < 0.1:  # 1..3 bit flips: CRC-16 (Hamming distance 4) detects every one
            for b in rng.choice(FRAME_LEN * 8, rng.integers(1, 4), replace=False):
                f[b >> 3] ^= 1 << (b & 7)
        elif r < 0.2:  # truncated: the next frame follows right after a partial one
            f = f[: rng.integers(1, FRAME_LEN)]
        else:
            intact.append(i)
        if rng.random() < 0.15:  # garbage between frames, sometimes with fake sync bytes
            g = bytearray(rng.integers(0, 256, rng.integers(1, 40), dtype=np.uint8).tobytes())
            if rng.random() < 0.5:
                g[0:2] = b"\xa5\x5a"
            out += g
        out += f
    return bytes(out), np.asarray(intact)


@pytest.mark.parametrize("seed", range(6))
def test_corrupted_stream_recovers_every_intact_frame(seed):
    rng = np.random.default_rng(seed)
    s = make_samples(400, seed=seed)
    stream, intact = corrupt_stream(s, rng)
    dec = FrameDecoder()
    got = []
    pos = 0
    while pos < len(stream):  # random read sizes, like a serial port
        n = int(rng.integers(1, 300))
        got.append(dec.feed(stream[pos : pos + n]))
        pos += n
    got = np.concatenate(got)
    want = codec.wire_roundtrip(s[intact])
    assert_same_payload(got, want)
    # FLAG_GAP_BEFORE exactly where a frame was lost, and the counters agree.
    lost_before = np.diff(np.r_[-1, intact]) > 1
    lost_before[0] = False  # nothing is known before the first frame
    np.testing.assert_array_equal((got["flags"] & FLAG_GAP_BEFORE) != 0, lost_before)
    st_ = dec.stats()
    assert st_["frames"] == intact.shape[0]
    assert st_["missing"] == intact[-1] - intact[0] + 1 - intact.shape[0]
    assert st_["crc_errors"] + st_["length_errors"] > 0


def test_bad_input_wrong_sync_lying_lengths_and_empty():
    s = make_samples(3)
    good = encode_frames(s)
    dec = FrameDecoder()
    assert dec.feed(b"").shape == (0,)
    # wrong sync: nothing decodes, bytes counted as skipped, nothing kept beyond a frame
    wrong = bytearray(good)
    for k in range(3):
        wrong[k * FRAME_LEN + 1] = 0x5B
    assert dec.feed(bytes(wrong)).shape == (0,)
    assert dec.stats()["bytes_skipped"] >= len(wrong) - (FRAME_LEN - 1)
    # A frame claiming 200 bytes ("too long") is refused at once; the next frame still decodes.
    dec = FrameDecoder()
    too_long = bytearray(good[:FRAME_LEN])
    too_long[2] = 200
    out = dec.feed(bytes(too_long) + good[FRAME_LEN:])
    np.testing.assert_array_equal(out["seq"], [1, 2])
    assert dec.stats()["length_errors"] == 1
    # A length byte claiming fewer bytes than the layout: refused the same way.
    short = bytearray(good[:FRAME_LEN])
    short[2] = 10
    dec = FrameDecoder()
    assert dec.feed(bytes(short)).shape == (0,) and dec.stats()["length_errors"] == 1
    # The length byte is right but the frame is cut short (the length lies): CRC rejects the
    # merged candidate, the following frame is decoded.
    dec = FrameDecoder()
    out = dec.feed(good[:20] + good[FRAME_LEN:])
    np.testing.assert_array_equal(out["seq"], [1, 2])
    assert dec.stats()["crc_errors"] == 1


def test_decoder_memory_is_bounded_on_endless_garbage():
    dec = FrameDecoder()
    rng = np.random.default_rng(1)
    for _ in range(50):
        dec.feed(rng.integers(0, 256, 10_000, dtype=np.uint8).tobytes())
    assert len(dec.tail) < FRAME_LEN
    assert dec.stats()["bytes_skipped"] > 500_000 - FRAME_LEN


def test_seq_unwrapper_wraps_gaps_duplicates_and_long_outages():
    u = SeqUnwrapper()
    keep, seq, gap = u.unwrap(np.array([65533, 65534, 65534, 65535, 2, 3], np.uint16))
    np.testing.assert_array_equal(keep, [1, 1, 0, 1, 1, 1])
    np.testing.assert_array_equal(seq, [65533, 65534, 65535, 65538, 65539])
    np.testing.assert_array_equal(gap, [0, 0, 0, 1, 0])
    assert (u.gaps, u.missing, u.duplicates) == (1, 2, 1)
    # After an outage of ~3 wraps, the hint restores the lost multiples of 2**16.
    u.expect_advance(3 * 65536 + 10.4)
    _, seq, gap = u.unwrap(np.array([13], np.uint16))
    assert seq[0] == 65539 + 3 * 65536 + 10 and gap[0]


def test_one_frame_decodes_exactly_as_in_a_block():
    # the single-frame fast path (one frame per wake-up) must give the block path's values bit for bit
    from gravcal.drivers.codec import to_wire, wire_to_samples
    from gravcal.drivers.rigs.sources import pattern_blocks

    b = np.concatenate(list(pattern_blocks(seed=7, fs=200, duration=2)))
    b["temp"][3], b["vsupply"][5] = np.nan, np.nan  # missing ADC codes
    w = to_wire(b)
    block = wire_to_samples(w)
    single = np.concatenate([wire_to_samples(w[i:i + 1]) for i in range(w.shape[0])])
    for name in block.dtype.names:
        np.testing.assert_array_equal(single[name], block[name], err_msg=name)
    assert np.isnan(single["temp"][3]) and np.isnan(single["vsupply"][5])
