"""Which thread reads a bus now: one at a time, whichever waits (python-can's Notifier
reads in a thread of its own; here the waiting thread reads, so that in virtual time the
wait drives the fleet clock).

A thread that wants a frame takes the turn when nobody has it and reads; a second one
sleeps until the reader has delivered, or its deadline passes.  A background reader
(:mod:`~ucom_tools.protocol.background`) holds the turn for good.  A failure of the bus
ends every wait.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Final

from ucom_tools.errors import BusError

POLL_S: Final = 0.05
"""How long a thread sleeps while another reads before it looks again (and how long the
background reader waits for a frame before it looks at its stop flag)."""


class Turns:
    """The reading turn of one bus, and the bus's failure."""

    def __init__(self) -> None:
        self.lock = threading.RLock()
        """``cond``'s lock: ``with self.lock`` is ``with self.cond`` without the Python
        wrapper around it (the per-cycle paths take it several times).  The reading flag
        is set and cleared under it, never under ``cond``: a stop signal's exception
        can be raised in Condition's Python ``__exit__``, after the flag was set and
        before the ``try`` that clears it, and then every later wait (the boards' stop)
        would wait for a reader that is gone."""
        self.cond = threading.Condition(self.lock)
        self.sleepers = 0
        """Threads in ``cond.wait``: the reader notifies only when there are any."""
        self.reading = False
        """A thread has the turn."""
        self.background = False
        """A background reader has the turn for good."""
        self.failure: BusError | None = None

    def take(self) -> bool:
        """The turn, if nobody has it (for a read that does not wait: :meth:`give_back`
        after it); False when another thread reads."""
        with self.lock:
            if self.background or self.reading:
                return False
            self.reading = True
        return True

    def give_back(self) -> None:
        """The turn taken back after a read; the sleepers woken to look."""
        with self.lock:
            self.reading = False
            if self.sleepers:
                self.cond.notify_all()

    def read_until(self, deadline: float, clock: Callable[[], float],
                   read: Callable[[float], int], finished: Callable[[float, int], bool],
                   ready: Callable[[], bool] | None = None) -> int:
        """Read in turns with the other threads until ``deadline`` on ``clock``: while
        nobody else reads, this thread takes the turn and calls ``read(time left)`` (the
        frames it took), else it sleeps until the reader has delivered.  Ends when
        ``ready()`` (asked under :attr:`lock` before each turn; it may raise), when
        another thread has the turn at ``deadline``, or when ``finished(time left before
        the read, frames it took)`` after a read.  Returns the frames taken."""
        count = 0
        while True:
            with self.lock:
                if ready is not None and ready():
                    return count
                remaining = deadline - clock()
                busy = self.reading or self.background
                if busy:  # another thread reads: wait for it (continue after the lock)
                    if remaining <= 0:
                        return count
                    self.sleep(min(remaining, POLL_S))
                else:
                    self.reading = True
            if busy:
                continue
            try:
                taken = read(max(0.0, remaining))
            finally:
                self.give_back()
            count += taken
            if finished(remaining, taken):
                return count

    def sleep(self, timeout: float) -> None:
        """``cond.wait``, counted in :attr:`sleepers` (called with ``cond`` held)."""
        self.sleepers += 1
        try:
            self.cond.wait(timeout)
        finally:
            self.sleepers -= 1

    def wake(self) -> None:
        """Every sleeper woken to look again."""
        with self.cond:
            self.cond.notify_all()

    def fail(self, text: str) -> BusError:
        """The bus failed: every wait raises ``BusError(text)`` from now on; that error."""
        err = BusError(text)
        with self.cond:
            self.failure = err
            self.cond.notify_all()
        return err
