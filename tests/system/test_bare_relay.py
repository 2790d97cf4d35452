"""bench/bare_relay.c, the floor under gravcald's CPU in bench/bench_latency.py: both ways of sending (a send()
per client, one io_uring batch) must deliver every client the same lines, numbered as the frames, or the two
floors would not measure the same work; on the emulated I2C bus it must relay every frame of the FIFO."""
from __future__ import annotations

import json
import os
import pty
import signal
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from gravcal.drivers.rigs.fake_i2c import FakeI2CDevice
from gravcal.drivers.rigs.i2c_dev import I2CDevServer
from gravcal.drivers.rigs.sources import pattern_blocks
from support.umockdev import require_umockdev
from tests.support.bench_c import build_bench_program

FRAME_BYTES, LINE_BYTES, CLIENTS = 29, 96, 3


@pytest.fixture(scope="module")
def relay(tmp_path_factory) -> str:
    return build_bench_program("bare_relay", tmp_path_factory.mktemp("relay"))


def _frame(seq: int) -> bytes:
    return bytes([0xA5, 0x5A, 0x00]) + seq.to_bytes(2, "little") + bytes(FRAME_BYTES - 5)


def _relay_lines(relay: str, tmp_path: Path, extra: list[str], seqs: list[int]) -> tuple[list[bytes], dict]:
    master, slave = pty.openpty()
    path = str(tmp_path / f"relay{len(extra)}.sock")
    proc = subprocess.Popen([relay, *extra, os.ttyname(slave), path, str(CLIENTS), str(LINE_BYTES),
                             str(FRAME_BYTES)], stdout=subprocess.PIPE, text=True)
    clients = []
    try:
        assert proc.stdout.readline().strip() == "listening"
        for _ in range(CLIENTS):
            c = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            c.connect(path)
            c.settimeout(5.0)
            clients.append(c)
        assert proc.stdout.readline().strip() == "ready"
        for seq in seqs:  # one frame at a time: each wake-up finds a whole frame
            os.write(master, _frame(seq))
            time.sleep(0.01)
        got = []
        for c in clients:
            data = b""
            while data.count(b"\n") < len(seqs):
                chunk = c.recv(1 << 16)
                assert chunk, "the relay closed a client early"
                data += chunk
            got.append(data)
        proc.send_signal(signal.SIGTERM)
        out = proc.communicate(timeout=10)[0].split()
        return got, dict(zip(out[::2], map(int, out[1::2])))
    finally:
        for c in clients:
            c.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(master)
        os.close(slave)


@pytest.mark.parametrize("extra", [[], ["--uring"]], ids=["send", "io_uring"])
def test_every_client_gets_one_numbered_line_per_frame(relay, tmp_path, extra):
    seqs = [7, 8, 9, 300, 65535]
    got, counts = _relay_lines(relay, tmp_path, extra, seqs)
    for data in got:
        lines = data.split(b"\n")[:-1]
        assert [len(line) + 1 for line in lines] == [LINE_BYTES] * len(seqs)
        assert [json.loads(line)["seq"] for line in lines] == seqs
    assert counts["lines"] == CLIENTS * len(seqs)
    assert counts["bytes"] == CLIENTS * len(seqs) * LINE_BYTES


@pytest.mark.parametrize("first", ["", ":0"], ids=["combined-poll", "status-first"])
def test_the_i2c_relay_numbers_every_frame_it_polls_from_the_device_node(relay, tmp_path, first):
    """i2c:DEVICE:POLL_US[:FIRST] under umockdev's preload: the relay enables the emulated logger and relays each
    frame of its FIFO, in order, as gravcald's driver would read them (its combined poll, or STATUS first)."""
    require_umockdev()
    fs = 200.0
    samples = next(pattern_blocks(seed=1, fs=fs, duration=1.0, block=200)).copy()
    samples["seq"] = (np.arange(200) + 65436) & 0xFFFF  # through the 16-bit wrap
    device = FakeI2CDevice([samples], fs, speed=2.0, fifo_depth=64)
    path = str(tmp_path / "relay-i2c.sock")
    with I2CDevServer(device) as server:
        proc = subprocess.Popen([relay, f"i2c:/dev/i2c-1:2000{first}", path, "1", str(LINE_BYTES), str(FRAME_BYTES)],
                                stdout=subprocess.PIPE, text=True, env=server.env())
        c = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            assert proc.stdout.readline().strip() == "listening"
            c.connect(path)
            c.settimeout(10.0)
            assert proc.stdout.readline().strip() == "ready"
            data = b""
            while data.count(b"\n") < samples.shape[0]:
                chunk = c.recv(1 << 16)
                assert chunk, "the relay closed its client early"
                data += chunk
        finally:
            c.close()
            proc.send_signal(signal.SIGTERM)
            proc.communicate(timeout=10)
    lines = data.split(b"\n")[:-1]
    assert [json.loads(line)["seq"] for line in lines] == samples["seq"].tolist()
