"""What a driver delivers goes up in seq, one sample after another: no watcher acting on every sample sees a
step back.

The sequence unwrapper (sequence.py) must decide on a frame that jumps (after a loss, or at start-up, when
nothing is known yet) before it knows whether the stream continues it: the last frame of a read is judged by the
next read. When such a frame was a CRC-valid stray, it has been delivered ahead of the stream it overtook
(``strays_delivered``). This filter sits between the unwrapper's output and the caller:

- a sample that continues the last one delivered (seq + 1) goes out;
- a sample that jumps goes out once the next sample follows it (1 to STRAY_JUMP_MIN ahead: losses on both sides
  of a sample are not rare); a jumping sample that ends a read is held
  until the next read confirms it (``hold_s`` at most: a stream that stops there still delivers it; the very
  first sample waits for its confirmation without limit);
- a sample that jumps and the next lies behind (or far ahead), or one behind a sample already delivered, is
  dropped and counted in ``out_of_order`` (a stray the unwrapper could not yet tell, or the victim of one).

The cost is one read's latency for the sample after a loss, and the very first sample; nothing when the stream
continues by one.
"""
from __future__ import annotations

import math

import numpy as np

from ..core.samples import FLAG_GAP_BEFORE
from .sequence import SeqUnwrapper

JUMP = SeqUnwrapper.STRAY_JUMP_MIN  # the next sample this little ahead confirms a jump (a loss on both sides)


class InOrder:
    """The settled, increasing part of each read (see the module's docstring)."""

    def __init__(self) -> None:
        self.last: int | None = None  # output seq of the last sample delivered
        self.held: np.ndarray | None = None  # one jumping sample that ended a read, waiting for the next
        self.held_until = 0.0
        self.out_of_order = 0  # samples dropped: behind one delivered, or a jump nothing continued

    def settle(self, block: np.ndarray, now: float, hold_s: float) -> np.ndarray:
        """The samples of ``block`` (after any held one) that may go out now, in increasing seq."""
        n = block.shape[0]
        if self.held is not None:
            if n == 0:
                return self._release(now)
            block, self.held = np.concatenate([self.held, block]), None
            n = block.shape[0]
        elif n == 0:
            return block
        last = self.last
        if last is not None and int(block["seq"][0]) == last + 1 and (
                n == 1 or bool((np.diff(block["seq"]) == 1).all())):  # the stream continues: the usual case
            self.last = int(block["seq"][-1])
            return block
        seq = block["seq"].astype(np.int64).tolist()
        keep = np.zeros(n, bool)
        for i, s in enumerate(seq):
            if last is not None and s <= last:
                continue  # behind what went out
            if (last is not None and s == last + 1) or (i + 1 < n and 0 < seq[i + 1] - s <= JUMP):
                keep[i] = True
                last = s
            elif i == n - 1:  # a jump nothing has continued yet: the next read decides (the first sample of
                # all waits for it however long it takes: nothing went out before it to judge it by)
                self.held, self.held_until = block[i:].copy(), now + hold_s if last is not None else math.inf
        self.out_of_order += n - int(keep.sum()) - (self.held is not None)
        out = block[keep]
        self._flag_jumps(out)
        self.last = last
        return out

    def _release(self, now: float) -> np.ndarray:
        """The held sample once ``hold_s`` passed with nothing to judge it by (the stream stopped there)."""
        if now < self.held_until:
            return self.held[:0]
        out, self.held = self.held, None
        self._flag_jumps(out)
        self.last = int(out["seq"][-1])
        return out

    def _flag_jumps(self, out: np.ndarray) -> None:
        """FLAG_GAP_BEFORE wherever the delivered seq jumps (a dropped sample opens a gap the unwrapper did not
        count)."""
        if out.shape[0] == 0 or self.last is None and out.shape[0] == 1:
            return
        seq = out["seq"].astype(np.int64)
        before = np.concatenate([[seq[0] - 1 if self.last is None else self.last], seq[:-1]])
        out["flags"][seq - before > 1] |= FLAG_GAP_BEFORE

    @property
    def wait_until(self) -> float | None:
        """When the held sample is due out (None: nothing held)."""
        return None if self.held is None else self.held_until
