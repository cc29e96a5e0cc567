"""Periodic frames on their deadlines on the bus clock (python-can's broadcast manager,
sent by the bus's reader rather than by a thread of their own).

The cyclic exchange's CI maps and MCA Alive are sent by whoever reads the bus, on their
deadlines on the bus clock: whoever waits for a frame keeps them going, so a console
command that waits for a board's answer never starves the watchdog of a running
exchange.  A task that could not be sent within its period counts the occurrences it
missed (``late``) and keeps its schedule.  A :class:`Schedule` is one bus's tasks.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable

import can

from ucom_tools.protocol.sending import Sender

Frames = Callable[[], Iterable[can.Message | tuple[int, bytes]]]
"""A periodic task's frames: messages, or standard data frames as (identifier, data),
sent without a ``can.Message`` (:meth:`~ucom_tools.protocol.sending.Sender.send_data`)."""


class Periodic:
    """Frames sent every ``period`` seconds of the bus clock, due at ``start + k period``."""

    def __init__(self, period: float, frames: Frames, name: str, due: float) -> None:
        if period <= 0:
            raise ValueError("period must be positive")
        self.period = period
        self.frames = frames
        self.name = name
        self.due = due
        self.sent = 0
        """Occurrences sent."""
        self.late = 0
        """Occurrences missed: the reader came to the task a whole period or more after
        it was due (the bus clock was not read in time)."""
        self.max_delay = 0.0
        """Longest time between an occurrence's due time and its sending (seconds)."""
        self.cancelled = False


def earliest(times: list[float | None]) -> float | None:
    """The earliest of ``times`` that is not None (None if none is)."""
    out: float | None = None
    for t in times:
        if t is not None and (out is None or t < out):
            out = t
    return out


class Schedule:
    """The periodic tasks of one bus, sent through its :class:`Sender`."""

    def __init__(self, clock: Callable[[], float], lock: threading.RLock,
                 sender: Sender) -> None:
        self.clock = clock
        self.lock = lock
        """Held to change the tasks (the reading turns' lock)."""
        self.sender = sender
        self.tasks: list[Periodic] = []
        self._running = False
        """:meth:`run_due` is sending (a task's frames that wait again do not recurse)."""
        self._next_due: float | None = None
        """When the next task is due (None: look)."""

    def every(self, period: float, frames: Frames, name: str,
              start: float | None = None) -> Periodic:
        """Send ``frames()`` every ``period`` seconds of :attr:`clock`, the first time at
        ``start`` (now when None)."""
        task = Periodic(period, frames, name, self.clock() if start is None else start)
        with self.lock:
            self.tasks.append(task)
            self._next_due = None  # look at the tasks again
        return task

    def cancel(self, task: Periodic) -> None:
        with self.lock:
            task.cancelled = True
            if task in self.tasks:
                self.tasks.remove(task)
            self._next_due = None

    def run_due(self) -> float | None:
        """Send every task that is due; the time the next one is due."""
        if not self.tasks:
            return None
        nxt = self._next_due
        if nxt is not None and self.clock() < nxt:
            return nxt  # nothing due (the common case: no lock taken)
        with self.lock:
            if self._running:
                return min(t.due for t in self.tasks) if self.tasks else None
            self._running = True
            tasks = list(self.tasks)
        try:
            now = self.clock()
            for task in tasks:
                if not task.cancelled and task.due <= now:
                    self._send(task, now)
            self._next_due = earliest([None if t.cancelled else t.due for t in tasks])
            return self._next_due
        finally:
            with self.lock:
                self._running = False

    def _send(self, task: Periodic, now: float) -> None:
        """One occurrence of ``task``, due by ``now``: the ones it missed counted."""
        delay = now - task.due
        missed = int(delay // task.period)
        task.late += missed
        task.max_delay = max(task.max_delay, delay)
        sender = self.sender
        for frame in task.frames():
            if isinstance(frame, tuple):
                sender.send_data(frame[0], frame[1], task.period)
            else:
                sender.send(frame, timeout=task.period)
        task.sent += 1
        task.due += (missed + 1) * task.period
