"""A thread that reads a bus for good (a real bus shared by a console and a running
exchange: frames are delivered while nobody waits), python-can's Notifier thread.

It holds the bus's reading turn (:mod:`~ucom_tools.protocol.turns`) while it runs: the
waiters sleep until it has delivered.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from ucom_tools.errors import BusError
from ucom_tools.protocol.turns import POLL_S, Turns


class BackgroundReader:
    """Reads with ``read(timeout)`` in a thread of its own between :meth:`start` and
    :meth:`stop`, until the bus fails."""

    def __init__(self, turns: Turns, read: Callable[[float], int], name: str) -> None:
        self.turns = turns
        self.read = read
        self.name = name
        self._thread: threading.Thread | None = None
        self._stop = False

    def start(self) -> None:
        if self._thread is not None:
            return
        self._stop = False
        self._thread = threading.Thread(target=self._run, name=f"ucom-reader-{self.name}",
                                        daemon=True)
        self.turns.background = True
        self._thread.start()

    def stop(self) -> None:
        thread = self._thread
        if thread is None:
            return
        self._stop = True
        thread.join(timeout=2)
        with self.turns.cond:
            self._thread = None
            self.turns.background = False
            self.turns.cond.notify_all()

    def _run(self) -> None:
        while not self._stop:
            try:
                self.read(POLL_S)
            except BusError:
                return
            self.turns.wake()
