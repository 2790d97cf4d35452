"""The device's 16-bit sample counter: unwrapping, gaps, duplicates, stray frames, restarts
(shared by the serial/I2C frame decoder and the CAN driver)."""
from __future__ import annotations

import numpy as np

MAX_U16 = 0xFFFF


class _Pending:
    """A frame, or a run of frames, the stream has not confirmed yet (SeqUnwrapper rule 4)."""

    AHEAD, RETAKE, HELD = "ahead", "retake", "held"
    __slots__ = ("kind", "value", "run", "delivered")

    def __init__(self, kind: str, value: int) -> None:
        self.kind = kind
        self.value = value  # unwrapped value of its newest frame (raw seq = value mod 2**16)
        self.run = 1  # frames so far
        self.delivered: list[list[int]] = []  # [block index (-1: an earlier block), samples counted missing]


class SeqUnwrapper:
    """Unwraps the device's 16-bit counter to int64, finds gaps and drops stray frames.

    A step of d = (seq - previous) mod 2**16 means d-1 samples are missing. A *stray* is a
    CRC-valid frame that is not the next part of the stream (an old frame repeated by a
    buffering adapter, a frame spliced from elsewhere, the rare garbage that passes the CRC);
    it must be dropped without shifting later sequence numbers by 2**16. The *head* is the
    last frame believed; with J = STRAY_JUMP_MIN and R = STRAY_RESYNC_RUN each frame is:

    1. a duplicate (d = 0 from the head or from a pending frame): dropped;
    2. the next part of the stream (1 <= d <= J from the head): believed at once, every
       pending frame was a stray;
    3. the continuation of a pending run: ahead of the head by at most J, behind it by exactly
       1 (in a row). The run is believed once it is long enough: 2 frames ahead of the head
       (a long loss), R behind it (see 4); the other pending frames were strays;
    4. otherwise a new pending run:
       - *ahead*: more than J ahead of the head (or at start-up, when nothing is known),
         delivered at once (the last frame of a read can only be judged by the next read);
       - *retake*: in the hole of the head's latest jump, continuing the head from before it
         (the jump was a stray, e.g. two that continued each other), delivered at once;
         believed after R in a row, which takes the jump back (its frames were strays);
       - *held*: anywhere else behind the head (an old frame), held back; R in a row are
         believed: the device restarted its counter (one gap of the samples since the restart,
         not of a 16-bit wrap; the output seq continues after them, ``restarts`` counts it).

    A stray found in the read it came with is removed from it; one delivered with an earlier
    read is counted in ``strays_delivered``. Unwrapped values start at the raw value of the
    first genuine frame. A forward step cannot be told from a wrap: after a long outage the
    caller passes the expected advance (from host time) to ``expect_advance``; the next frame
    is then believed, with the multiples of 2**16 that bring it nearest that advance.
    """

    STRAY_JUMP_MIN = 64  # J: a larger forward step is believed only with a continuation
    STRAY_RESYNC_RUN = 3  # R: frames in a row that outweigh a believed frame ahead of them
    MAX_PENDING = 8  # more open runs than this: the oldest is forgotten (as delivered or held)

    def __init__(self) -> None:
        self.last: int | None = None  # unwrapped value of the last frame delivered
        self._head: int | None = None  # unwrapped value of the last frame believed
        self._pending: list[_Pending] = []
        self._fallback: int | None = None  # the head before its latest jump (None: no jump since)
        self._jumped: list[list[int]] = []  # the frames that jump delivered, as _Pending.delivered
        self._expected: float | None = None
        self._keep: np.ndarray | None = None  # the block being unwrapped, frame by frame
        self._seq: np.ndarray | None = None
        self._gap: np.ndarray | None = None
        self.gaps = 0  # gap events
        self.missing = 0  # samples missing in those gaps
        self.duplicates = 0
        self.strays = 0  # frames dropped as strays, or found to be strays after delivery
        self.strays_delivered = 0  # of which already delivered with an earlier read
        self.restarts = 0  # the device's counter started again from 0 (its missed samples are in `missing`)
        self.offset = 0  # output seq - internal value: restarts keep the output continuous
        self._after_outage = False
        self._held = 0  # frames the device held through the outage, still to come
        self._tick_period: float | None = None  # device ticks per sample
        self._tick_last: int | None = None

    def expect_advance(self, samples: float | None, held: int = 0) -> None:
        """After an outage: about ``samples`` samples went by (None: unknown); the device may still hold
        ``held`` frames from before it (a FIFO's count at reconnect), which come first."""
        self._expected = None if samples is None else float(samples)
        self._after_outage = True
        self._held = max(0, int(held))

    def unwrap(self, seq_raw: np.ndarray, ticks: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(keep mask, unwrapped seq of kept frames, gap-before flag of kept frames); ``ticks`` (the
        frames' device ticks) let a device restart behind an outage be told from a long loss."""
        s = np.asarray(seq_raw).astype(np.int64)
        if s.shape[0] == 0:
            return np.zeros(0, bool), np.zeros(0, np.int64), np.zeros(0, bool)
        t = None if ticks is None else np.asarray(ticks).astype(np.int64)
        last_before, tick_before = self.last, self._tick_last
        if self._after_outage and self._held:
            m = self._held_through(s, t)
            if m:
                return self._unwrap_held(s, t, m)
        hint, self._expected = self._expected, None
        after, self._after_outage, self._held = self._after_outage, False, 0
        restarted = after and t is not None and self._restarted(int(s[0]), int(t[0]), hint)
        if restarted:
            self._rebase(int(s[0]))
        keep, seq, gap = self._unwrap(s, None if restarted else hint)
        if restarted and keep[0] and s[0] > 0:
            gap[0] = True
        if t is not None:
            self._learn_ticks(s, t, keep)
            one_step = last_before is not None and self.last == last_before + 1
            if s.shape[0] == 1 and keep[0] and not restarted and one_step:
                self._learn_step(tick_before, int(t[0]), 1)
        return keep, seq, gap

    def next_frame(self) -> tuple[int, int] | None:
        """(raw 16-bit seq, output seq) of the frame that continues the stream by one while rule 2 alone decides
        it (nothing pending, no outage): what the daemon's C step takes; None: not that case."""
        if self._pending or self._head is None or self._after_outage or self._expected is not None:
            return None
        return (self._head + 1) & MAX_U16, self._head + 1 + self.offset

    def continued(self, n: int, tick: int, tick_period: float | None) -> None:
        """``n`` frames from :meth:`next_frame` on continued the stream one by one (taken by the daemon's C
        step): the state :meth:`unwrap` leaves after them. ``tick``: the last one's; ``tick_period``: learnt
        from a read of several (None: none had several)."""
        if n <= 0:
            return
        self._fallback, self._jumped = None, []
        self._head = self.last = self._head + n
        if tick_period is not None:
            self._tick_period = tick_period
        else:
            self._learn_step(self._tick_last, tick, n)
        self._tick_last = tick

    # -------------------------------------------------------- device restarts (sequence and tick from 0)
    def _learn_ticks(self, s: np.ndarray, t: np.ndarray, keep: np.ndarray) -> None:
        if s.shape[0] >= 2 and bool((((s[1:] - s[:-1]) & MAX_U16) == 1).all()):
            self._tick_period = ((int(t[-1]) - int(t[0])) & 0xFFFFFFFF) / (s.shape[0] - 1)
        kept = np.flatnonzero(keep)
        if kept.shape[0]:
            self._tick_last = int(t[kept[-1]])

    def _learn_step(self, tick_before: int | None, tick: int, n: int) -> None:
        """A stream read one frame at a time never holds two frames in one read: its tick period comes from
        ``n`` frames that continued the previous one by one, learnt once (a read of several refines it), so
        a device restart behind an outage can be told from a 16-bit wrap on every bus."""
        if self._tick_period is None and tick_before is not None:
            self._tick_period = ((tick - tick_before) & 0xFFFFFFFF) / n or None

    def _held_through(self, s: np.ndarray, t: np.ndarray | None) -> int:
        """How many leading frames of a read after an outage the device held through it (at most the held
        count): they continue the stream, one by one, and so do their ticks (0: none, or not known)."""
        if self.last is None:
            return 0
        step = (int(s[0]) - self.last) & MAX_U16
        if not 1 <= step <= self.STRAY_JUMP_MIN:
            return 0
        tp, last_tick = self._tick_period, self._tick_last
        if t is not None and tp and last_tick is not None:
            advance = ((int(t[0]) - last_tick) & 0xFFFFFFFF) / tp
            if abs(advance - step) > 2:
                return 0
        m = 1
        while m < min(self._held, s.shape[0]) and (int(s[m]) - int(s[m - 1])) & MAX_U16 == 1:
            m += 1
        return m

    def _unwrap_held(self, s: np.ndarray, t: np.ndarray | None, m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Frames the device held through an outage continue the stream as if there had been none; the
        outage's judgement (its expected advance, a restart) waits for the first frame after them, in this
        read or a later one."""
        hint, held = self._expected, self._held
        self._expected, self._after_outage, self._held = None, False, 0
        first = self.unwrap(s[:m], None if t is None else t[:m])
        self._expected, self._after_outage, self._held = hint, True, held - m
        if m == s.shape[0]:
            return first
        self._held = 0
        rest = self.unwrap(s[m:], None if t is None else t[m:])
        return tuple(np.concatenate([a, b]) for a, b in zip(first, rest))

    def _restarted(self, raw: int, tick: int, hint: float | None) -> bool:
        """The first frame after an outage is a restarted device's: its seq and tick both count from a
        recent boot, and its tick does not continue the stream's (by seq, and by the host's clock)."""
        tp, last_tick = self._tick_period, self._tick_last
        if self.last is None or not tp or last_tick is None:
            return False
        if abs(tick / tp - raw) > 2 + 0.01 * raw:  # not both counting from a boot
            return False
        advance = ((tick - last_tick) & 0xFFFFFFFF) / tp  # samples elapsed if the device ran on
        step = (raw - self.last) & MAX_U16
        k = max(0, round((advance - step) / 65536.0))
        if abs(advance - step - 65536 * k) > 2 + 1e-3 * advance:  # one crystal paces ticks and samples
            return True
        # ticks that continue by coincidence (a short session before and after): fewer samples than the
        # host saw go by between noticing the outage and reopening (which lies inside the true interval)
        return hint is not None and advance < 0.5 * hint - 50

    def _rebase(self, raw: int) -> None:
        """A restart: ``raw`` samples of the new session were missed; the output continues after them."""
        step = (raw - self.last) & MAX_U16 or 65536
        value = self.last + step  # the internal value of the frame (same residue mod 2**16)
        self.offset += self.last + 1 + raw - value
        self._head = self.last = value - 1  # the frame then continues the stream (rule 2)
        self._pending, self._fallback, self._jumped = [], None, []
        self.restarts += 1
        if raw > 0:
            self.gaps += 1
            self.missing += raw

    def _unwrap(self, s: np.ndarray, hint: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = s.shape[0]
        if hint is not None and self.last is None:
            hint = None  # nothing delivered yet: nothing to advance from
        # Fast path, the common case: no open question and a block that continues itself.
        if not self._pending and bool((((s[1:] - s[:-1]) & MAX_U16) == 1).all()):
            if self._head is None and n >= 2:  # a first read: rule 3 at start-up
                seq = int(s[0]) + np.arange(n, dtype=np.int64)
                self._head = self.last = int(seq[-1])
                return np.ones(n, bool), seq + self.offset, np.zeros(n, bool)
            if self._head is not None:
                step = (int(s[0]) - self._head) & MAX_U16
                if hint is not None:
                    step += 65536 * max(0, round((hint - step) / 65536.0))
                if 1 <= step <= self.STRAY_JUMP_MIN or (hint is not None and step >= 1):  # rule 2
                    seq = self._head + step + np.arange(n, dtype=np.int64)
                    gap = np.zeros(n, bool)
                    gap[0] = step > 1
                    self.gaps += int(gap[0])
                    self.missing += step - 1
                    jump = n == 1 and step > 1 and hint is None
                    self._fallback, self._jumped = (self._head, [[-1, step - 1]]) if jump else (None, [])
                    self._head = self.last = int(seq[-1])
                    return np.ones(n, bool), seq + self.offset, gap
        return self._unwrap_frames(s.tolist(), hint)

    # -------------------------------------------------------- frame by frame: the rules
    def _unwrap_frames(self, frames: list[int], hint: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = len(frames)
        self._keep, self._seq, self._gap = np.zeros(n, bool), np.zeros(n, np.int64), np.zeros(n, bool)
        start = 0
        if hint is not None:  # after an outage: believe the frame delivered last, then the hint
            self._head, self._pending, self._fallback, self._jumped = self.last, [], None, []
            step = (frames[0] - self.last) & MAX_U16
            step += 65536 * max(0, round((hint - step) / 65536.0))
            if step:  # (else a duplicate: rule 1)
                self._head += step
                self._deliver(0, self._head, step - 1)
                start = 1
        for i in range(start, n):
            self._frame(i, frames[i])
        for delivered in [p.delivered for p in self._pending] + [self._jumped]:
            for frame in delivered:
                frame[0] = -1  # delivered with an earlier read from now on
        keep, seq, gap = self._keep, self._seq, self._gap
        self._keep = self._seq = self._gap = None
        return keep, seq[keep], gap[keep]

    def _frame(self, i: int, x: int) -> None:
        J, R = self.STRAY_JUMP_MIN, self.STRAY_RESYNC_RUN
        head = self._head
        d = (x - head) & MAX_U16 if head is not None else 0
        if head is not None and d == 0:  # rule 1
            self.duplicates += 1
            return
        if head is not None and d <= J:  # rule 2
            self._drop_pending()
            self._fallback, self._jumped = (head, [[i, d - 1]]) if d > 1 else (None, [])
            self._believe(i, head + d, d - 1)
            return
        best, best_d = None, 0
        for p in self._pending:
            dp = (x - p.value) & MAX_U16
            if dp == 0:  # rule 1
                self.duplicates += 1
                return
            if (dp <= J if p.kind == _Pending.AHEAD else dp == 1) and (best is None or dp < best_d):
                best, best_d = p, dp
        if best is not None:  # rule 3
            p = best
            p.run += 1
            p.value += best_d
            if p.run < (2 if p.kind == _Pending.AHEAD else R):
                self._add(p, i, 0)
            else:
                self._confirm(p, i, best_d)
            return
        # rule 4
        fallback = self._fallback
        df = (x - fallback) & MAX_U16 if fallback is not None else 0
        if fallback is not None and 0 < df < head - fallback:
            p = _Pending(_Pending.RETAKE, fallback + df)
            self._add(p, i, df - 1)
        elif head is None or d < 0x8000:
            p = _Pending(_Pending.AHEAD, head + d if head is not None else x)
            # at start-up nothing is known before it: a discontinuity, no samples counted missing
            self._add(p, i, d - 1, gap=None if head is not None else self.last is not None)
        else:
            p = _Pending(_Pending.HELD, head + d)
            self.strays += 1
        self._pending.append(p)
        if len(self._pending) > self.MAX_PENDING:
            del self._pending[0]  # forgotten: it stays as delivered (or held back)

    def _add(self, p: _Pending, i: int, missing: int, gap: bool | None = None) -> None:
        """Frame ``i`` joins the pending run ``p``: delivered now, unless the run is held back."""
        if p.kind == _Pending.HELD:
            self.strays += 1  # (taken back if the run is believed)
            return
        p.delivered.append([i, missing])
        self._deliver(i, p.value, missing, gap)

    def _confirm(self, p: _Pending, i: int, d: int) -> None:
        """Rule 3: frame ``i`` (``d`` after the run's last frame) makes ``p`` believed."""
        head = self._head
        self._pending.remove(p)
        if p.kind == _Pending.RETAKE:  # the head's latest jump was a stray after all
            for at, missing in self._jumped:
                self._disown(at, missing)
            # the other frames delivered from the same hole may be the stream too: left as they are
            self._pending = [q for q in self._pending if q.kind != _Pending.RETAKE]
            self._drop_pending()
            self._fallback, self._jumped = None, []
            self._believe(i, p.value, d - 1)
        elif p.kind == _Pending.HELD:  # the counter restarted from 0: the held-back frames are in its gap
            self.strays -= p.run - 1
            self._drop_pending()
            self._fallback, self._jumped = None, []
            raw = p.value & MAX_U16  # samples since the restart not delivered (not a wrap's 2**16)
            self.offset += self.last + 1 + raw - p.value
            self.restarts += 1
            self._believe(i, p.value, raw)
        else:  # a long loss (or the start): can still be taken back while nothing follows it
            self._drop_pending()
            if head is not None:
                self._fallback, self._jumped = head, p.delivered + [[i, d - 1]]
            else:
                self._fallback, self._jumped = None, []
            self._believe(i, p.value, d - 1)

    # -------------------------------------------------------- bookkeeping
    def _believe(self, i: int, value: int, missing: int) -> None:
        self._head = value
        self._deliver(i, value, missing)

    def _deliver(self, i: int, value: int, missing: int, gap: bool | None = None) -> None:
        self._keep[i], self._seq[i] = True, value + self.offset
        self._gap[i] = missing > 0 if gap is None else gap
        if missing > 0:
            self.gaps += 1
            self.missing += missing
        self.last = value

    def _drop_pending(self) -> None:
        """Every pending run was a stray (a held-back one was counted when it came)."""
        for p in self._pending:
            for at, missing in p.delivered:
                self._disown(at, missing)
        self._pending = []

    def _disown(self, at: int, missing: int) -> None:
        """A delivered frame was a stray: removed from this block, or counted as delivered."""
        self.strays += 1
        if missing > 0:
            self.gaps -= 1
            self.missing -= missing
        if at >= 0:
            self._keep[at] = False
        else:
            self.strays_delivered += 1
