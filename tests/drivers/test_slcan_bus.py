"""The slcan read path: python-can's slcan bus, reading its port in bursts instead of a byte per call."""
from __future__ import annotations

import time

import numpy as np

from gravcal.drivers.can import SampleAssembler
from gravcal.drivers.rigs.can_links import SlcanPtyLink
from gravcal.drivers.rigs.emulator import Faults
from gravcal.drivers.rigs.sources import pattern_blocks
from gravcal.drivers.slcan import BufferedSlcanBus


def test_slcan_frames_arrive_whole_with_few_port_reads(tmp_path):
    link = SlcanPtyLink(tmp_path / "ttyCAN")
    link.connect()
    bus = BufferedSlcanBus(channel=str(link.link), bitrate=1_000_000, sleep_after_open=0.0, timeout=0.01)
    reads = {"calls": 0}
    real_take = bus._take_bytes

    def counted(wait_s):
        data = real_take(wait_s)
        reads["calls"] += bool(data)  # reads of the port that returned bytes
        return data

    bus._take_bytes = counted
    try:
        deadline = time.monotonic() + 5
        while not link.channel_open and time.monotonic() < deadline:
            link.service(0.02)
        assert link.channel_open
        samples = np.concatenate(list(pattern_blocks(seed=4, fs=200, duration=0.25)))  # 50 samples, 200 frames
        status, _ = link.send(samples, Faults(), blocking=True)
        asm = SampleAssembler()
        frames, sent_bytes = 0, 0
        while frames < 4 * samples.shape[0]:
            msg = bus.recv(timeout=2.0)
            assert msg is not None, f"only {frames} frames arrived"
            if msg.arbitration_id:  # the acknowledgements parse to no frame
                frames += 1
                sent_bytes += 6 + 2 * len(msg.data)
                asm.on_message_received(msg)
        assert bus.recv(timeout=0.0) is None  # nothing left: a zero timeout does not block
        got = asm.take()
        np.testing.assert_array_equal(got["seq"], samples["seq"])
        np.testing.assert_array_equal(got["tick"], samples["tick"])
        # python-can's own reader calls read(1) once per byte (here ~6000): a burst read takes a few
        assert reads["calls"] < frames / 4, (reads["calls"], frames, sent_bytes)
    finally:
        bus.shutdown()
        link.close()
