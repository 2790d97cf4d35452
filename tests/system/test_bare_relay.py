"""bench/bare_relay.c, the floor under gravcald's CPU in bench/bench_latency.py: both ways of sending (a send()
per client, one io_uring batch) must deliver every client the same lines, numbered as the frames, or the two
floors would not measure the same work."""
from __future__ import annotations

import json
import os
import pty
import signal
import socket
import subprocess
import time
from pathlib import Path

import pytest

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
