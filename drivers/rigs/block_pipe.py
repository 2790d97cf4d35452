"""A scenario's sample blocks generated in a child process and read back through a pipe.

``gravcald --emulate --bus i2c`` runs its fake I2C device inside the daemon; the sensor model behind
it (its random draws and filters, and scipy.spatial when a misalignment term is switched on) would
then share the daemon's memory and interpreter. Here the simulator runs in
``python -m gravcal.drivers.rigs.block_pipe`` instead and the device reads the
same blocks (SAMPLE_DTYPE bytes, each block preceded by its row count) from its stdout. The pipe's
back-pressure keeps the child only a few blocks ahead of the device.
"""
from __future__ import annotations

import argparse
import os
import signal
import struct
import subprocess
import sys
from typing import Iterator, Sequence

import numpy as np

from ...core.samples import SAMPLE_DTYPE

_COUNT = struct.Struct("<I")


class PipedBlocks:
    """Iterate the blocks of ``scenario_source(name, seed=, fs=, duration=)`` made by a child process."""

    def __init__(self, name: str, *, seed: int, fs: float, duration: float):
        from ...core.scenarios import SCENARIOS  # numpy only: a bad name fails here, before the device exists

        if name not in SCENARIOS:
            raise ValueError(f"unknown scenario {name!r}; choose one of {', '.join(SCENARIOS)} or pattern")
        cmd = [sys.executable, "-m", __name__, name, "--seed", str(int(seed)), "--fs", repr(float(fs)),
               "--duration", repr(float(duration))]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stdin=subprocess.DEVNULL)
        # Wait for the first block here: the child's start, imports and sensor model take ~0.4 s, which must pass
        # before the device announces itself and its stream clock starts (else its FIFO overflows at once).
        self._first = self._read()

    def _read(self) -> np.ndarray | None:
        out = self.proc.stdout
        head = out.read(_COUNT.size)
        if len(head) < _COUNT.size:
            return None
        (n,) = _COUNT.unpack(head)
        data = out.read(n * SAMPLE_DTYPE.itemsize)
        if len(data) < n * SAMPLE_DTYPE.itemsize:
            return None
        return np.frombuffer(data, dtype=SAMPLE_DTYPE).copy()

    def __iter__(self) -> Iterator[np.ndarray]:
        block, self._first = self._first, None
        while block is not None:
            yield block
            block = self._read()

    def close(self) -> None:
        """Stop the child: its next write fails (EPIPE) once the pipe is closed, which also works
        after the daemon dropped the privileges it would need to signal it."""
        self.proc.stdout.close()
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:
            try:
                self.proc.kill()
            except OSError:
                pass


def main(argv: Sequence[str] | None = None) -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the daemon handles Ctrl-C and then closes the pipe
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenario")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fs", type=float, default=200.0)
    ap.add_argument("--duration", type=float, default=60.0)
    args = ap.parse_args(argv)
    from .sources import scenario_source

    out = sys.stdout.buffer
    try:
        for b in scenario_source(args.scenario, seed=args.seed, fs=args.fs, duration=args.duration).blocks:
            b = np.ascontiguousarray(b, dtype=SAMPLE_DTYPE)
            out.write(_COUNT.pack(b.shape[0]))
            out.write(b.tobytes())
        out.flush()
    except BrokenPipeError:  # the reader has gone (the daemon stopped): no flush at exit either
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0


if __name__ == "__main__":
    sys.exit(main())
