"""docs/protocol.md's worked examples decode to the values the document states."""
from __future__ import annotations

import re
from pathlib import Path

import can
import numpy as np

from gravcal.drivers import can as gcan
from gravcal.drivers.codec import SeqUnwrapper, decode_frames, encode_frames

DOC = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"


def block(marker: str) -> str:
    text = DOC.read_text(encoding="utf-8")
    m = re.search(rf"<!-- {marker} -->\s*```[a-z]*\n(.*?)```", text, re.S)
    assert m, f"docs/protocol.md has no block {marker}"
    return m.group(1)


def documented_values() -> dict[str, np.ndarray]:
    out = {}
    for line in block("serial-decoded").strip().splitlines():
        name, _, value = line.partition("=")
        out[name.strip()] = np.array([float(v) for v in value.split()])
    return out


def check(sample: np.void, want: dict[str, np.ndarray]) -> None:
    for name, value in want.items():
        got = np.atleast_1d(sample[name]).astype(np.float64)
        if name in ("temp", "vsupply"):
            np.testing.assert_allclose(got, value, rtol=0, atol=5e-6, err_msg=name)
        else:
            np.testing.assert_array_equal(got, value, err_msg=name)


def test_serial_example_decodes_to_documented_values():
    frame = bytes.fromhex(block("serial-example"))
    assert len(frame) == 29
    samples = decode_frames(frame)
    assert samples.shape == (1,)
    check(samples[0], documented_values())
    # and the codec produces exactly the documented bytes for that sample
    again = samples.copy()
    assert encode_frames(again) == frame


def test_can_example_decodes_to_documented_values():
    lines = block("can-example").split()
    msgs = []
    for ln in lines:
        assert ln[0] == "t"
        ident, dlc, data = int(ln[1:4], 16), int(ln[4]), bytes.fromhex(ln[5:])
        assert len(data) == dlc
        msgs.append(can.Message(arbitration_id=ident, data=data, is_extended_id=False))
    asm = gcan.SampleAssembler()
    for m in msgs:
        asm.on_message_received(m)
    samples = gcan.records_to_samples(asm.take(), SeqUnwrapper())
    assert samples.shape == (1,) and samples["flags"][0] == 0
    check(samples[0], documented_values())
    # the CAN example carries the same sample as the serial example
    serial_sample = decode_frames(bytes.fromhex(block("serial-example")))
    assert [bytes(m.data) for m in gcan.to_messages(serial_sample)] == [bytes(m.data) for m in msgs]


def test_crc_check_value_is_documented():
    text = DOC.read_text(encoding="utf-8")
    assert "0x29B1" in text and "binascii.crc_hqx(data, 0xFFFF)" in text
    from gravcal.drivers.codec import crc16

    assert crc16(b"123456789") == 0x29B1
