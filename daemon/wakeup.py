"""The main loop's wake-up: a self-pipe that signal handlers and other threads may poke.

A Python signal handler runs in the main thread between two bytecodes, possibly while that thread holds a lock
(inside ``threading.Event.wait`` or ``clear``); a handler that then takes the same lock (``Event.set``) waits
for itself forever. So the handlers only assign flags and write a byte here, which takes no lock. The write end
is also the interpreter's wakeup fd (``signal.set_wakeup_fd``): a signal delivered to any thread wakes the main
loop at once, not at its next tick, and the loop then finds the flag set.
"""
from __future__ import annotations

import os
import select
import signal


class SelfPipeWake:
    def __init__(self) -> None:
        self._r, self._w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        self._previous_wakeup_fd: int | None = None

    def poke(self) -> None:
        """Safe in a signal handler and from any thread: one non-blocking write, no lock."""
        try:
            os.write(self._w, b"\0")
        except (BlockingIOError, OSError):
            pass  # a full pipe already wakes the loop; a closed one belongs to a loop that ended

    def wait(self, timeout: float) -> None:
        """Sleep until poked (or a signal arrives, once installed) or ``timeout`` seconds pass; drain the pipe."""
        readable, _, _ = select.select([self._r], [], [], timeout)
        if readable:
            try:
                while os.read(self._r, 4096):
                    pass
            except BlockingIOError:
                pass

    def install_for_signals(self) -> None:
        """Make the pipe the interpreter's wakeup fd (main thread only, as the signal module requires)."""
        self._previous_wakeup_fd = signal.set_wakeup_fd(self._w, warn_on_full_buffer=False)

    def close(self) -> None:
        if self._previous_wakeup_fd is not None:
            try:
                signal.set_wakeup_fd(self._previous_wakeup_fd)
            except ValueError:  # not the main thread: keep the pipe open, or a signal would write to a reused fd
                return
            self._previous_wakeup_fd = None
        for fd in (self._r, self._w):
            try:
                os.close(fd)
            except OSError:
                pass
        self._r = self._w = -1
