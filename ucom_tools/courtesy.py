"""A thread of bulk work that lets the threads waiting for Python's lock (the GIL) run.

Python runs one thread at a time.  A thread that wants the lock while another computes
waits for the switch interval (5 ms) before it may ask for it: a thread of bulk work
(the MCAP recorder's writer, the Foxglove feed's frames) keeps every other thread of the
process that many milliseconds from each of its steps, and a value that passes several
threads on its way (the consumers' pipe reader, the Foxglove feed) waits that long at
each.  Measured in ``benchmarks/record.py`` (ARMAR-III, ``--record run.mcap --foxglove``,
two cores): the values reached the Foxglove feed's thread 11-12 ms (p99) after the loop
took them while the recorder computed without a pause, 5-6 ms with a pause of
:data:`PAUSE_S` after each :data:`WORK_S` of its work; delivery to a client p99 15-17 ms
without the pauses, 9-10 ms with them.

A :class:`Courtesy` is called between two pieces of work; once :data:`WORK_S` of work
went by since its last pause it sleeps :data:`PAUSE_S`, which hands the lock to a thread
that waits for it (a release and at once a take again, as ``time.sleep(0)`` does, would
let the computing thread take it back before the waiting one woke up).
"""

from __future__ import annotations

import time
from typing import Final

WORK_S: Final = 0.0005
"""The work between two pauses (a tenth of the switch interval)."""
PAUSE_S: Final = 0.00005
"""A pause: long enough for a waiting thread to wake up and take the lock."""


class Courtesy:
    """Call between two pieces of a thread's bulk work (module docstring)."""

    __slots__ = ("_since",)

    def __init__(self) -> None:
        self._since = time.perf_counter()

    def __call__(self) -> None:
        if time.perf_counter() - self._since >= WORK_S:
            time.sleep(PAUSE_S)
            self._since = time.perf_counter()


__all__ = ["PAUSE_S", "WORK_S", "Courtesy"]
