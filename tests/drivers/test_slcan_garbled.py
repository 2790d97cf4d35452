"""Garbled slcan lines on a real pty, parsed by python-can's own slcan reader: each is one lost line, counted
by the kind of error the parser raised, never a reopen of the adapter."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from gravcal.drivers import open_driver
from gravcal.drivers.can import pack_frames
from gravcal.drivers.rigs.can_links import SlcanPtyLink
from gravcal.drivers.rigs.sources import pattern_blocks

# What a USB-serial link that loses or corrupts bytes delivers, and what python-can's slcan parser raises on it
# (None: nothing; the frame it makes is the driver's bad_frames)
GARBLED = [
    (b"t12\r", "IndexError"),  # standard frame cut after its identifier
    (b"x1\r", "IndexError"),  # CANDapter's extended frame, cut
    (b"B3B\r", "IndexError"),  # FD extended frame with bit-rate switch, cut
    (b"t10G8\r", "ValueError"),  # not hexadecimal
    (b"t1009" + b"00" * 9 + b"\r", None),  # DLC 9 on a classic frame: parsed, a 9-byte frame the driver refuses
    (b"t\xff\xfe1\r", "UnicodeDecodeError"),  # not ASCII
    (b"d1\r", "IndexError"),  # FD standard frame, cut
    (b"t1008" + b"0" * 5 + b"\r", "ValueError"),  # odd number of data digits
]


def slcan_lines(samples: np.ndarray, base_id: int = 0x100) -> list[bytes]:
    """Each sample's four frames as one slcan byte string, as the adapter sends them."""
    return [b"".join(b"t%03X%d%s\r" % (base_id + k, len(d), d.hex().upper().encode()) for k, d in enumerate(parts))
            for parts in pack_frames(samples)]


@pytest.fixture
def link(tmp_path):
    link = SlcanPtyLink(tmp_path / "ttyCAN")
    link.connect()
    stop = threading.Event()
    serving = threading.Thread(target=lambda: [link.service(0.01) for _ in iter(stop.is_set, True)], daemon=True)
    serving.start()
    yield link
    stop.set()
    serving.join(2)
    link.close()


def test_a_garbled_line_per_sample_costs_one_line_each_and_no_reopen(link):
    samples = np.concatenate(list(pattern_blocks(seed=3, fs=200, duration=1.0)))  # 200 samples
    with open_driver(link.spec) as drv:
        deadline = time.monotonic() + 5
        while not link.channel_open and time.monotonic() < deadline:
            time.sleep(0.01)
        assert link.channel_open
        stream, kinds = [], {}
        for i, frames in enumerate(slcan_lines(samples)):
            bad, kind = GARBLED[i % len(GARBLED)]
            stream += [frames, bad]  # one garbled line after every sample's frames
            kinds[kind] = kinds.get(kind, 0) + 1
        writer = threading.Thread(target=link.write, args=(b"".join(stream), True), daemon=True)
        writer.start()  # more than the pty holds: written while the driver reads
        got, deadline = [], time.monotonic() + 20
        while sum(b.shape[0] for b in got) < samples.shape[0] and time.monotonic() < deadline:
            got.append(drv.read(max_samples=4096, timeout=0.2))
        st = drv.stats()
        writer.join(5)
    got = np.concatenate(got)
    np.testing.assert_array_equal(got["seq"], samples["seq"] - samples["seq"][0] + got["seq"][0])
    np.testing.assert_array_equal(got["tick"], samples["tick"])
    bad = kinds.pop(None)
    assert st["garbled_lines"] == samples.shape[0] - bad and st["garbled_kinds"] == kinds, st
    assert st["bad_frames"] == bad and st["can_frames"] == 4 * samples.shape[0]
    assert st["reconnects"] == 0 and st["disconnects"] == 0 and st["partial"] == 0
