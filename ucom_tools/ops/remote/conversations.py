"""The conversations the loop steps after each cycle's drain: the rejoins that bring a lost
board back (:mod:`~ucom_tools.ops.remote.rejoin`) and the writes it does not wait for
(:mod:`~ucom_tools.ops.remote.par_write`).

:class:`Conversations` is a part the loop holds (:class:`~ucom_tools.ops.remote.loop.
RemoteLoop`): it starts them, hands each control in turn, and calls the loop back with
what changes the loop's state (a rejoin that ended, a value held or put back).  Each
conversation is an object with ``step(budget)``, ``busy()``, ``cancel()``, ``done``,
``ok``, ``how``, ``answered``, ``bus``, ``board`` and ``is_rejoin``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Final

from ucom_tools.ops.edges import EdgeRef

REJOIN_MARGIN_S: Final = 0.0003
"""On the wall clock a rejoin's step ends this long before the loop's next deadline at the
latest (its worker runs on beside the loop if it needs longer)."""
_monotonic: Final = time.monotonic


class Conversations:
    """The loop's conversations (see the module docstring).  ``ended`` is called with a
    rejoin that ended (the loop brings its board back, or says why not); ``held`` and
    ``hold`` read and set the raw value the PC holds for an edge (a write that fails puts
    the one before back); ``forget`` drops the copies of a conversation's answers that
    the run time's own client of that bus got."""

    def __init__(self, virtual: bool, ended: Callable[[Any], None],
                 held: Callable[[EdgeRef], int | None], hold: Callable[[EdgeRef, int], None],
                 forget: Callable[[str], None]) -> None:
        self.virtual = virtual
        self.ended = ended
        self.held = held
        self.hold = hold
        self.forget = forget
        self.under_way: list[Any] = []
        """The conversations stepped after each cycle's drain: rejoins, and PAR writes the
        loop does not wait for."""
        self.rejoiner: Callable[[str, int, float], Any] | None = None
        """Starts the conversation that brings board (bus, n) back after a delay in seconds
        (set by :class:`~ucom_tools.ops.remote.RemotePart` with ``rejoin``)."""
        self.par_writer: Callable[[EdgeRef, int], Any] | None = None
        """Starts a write (a PAR, a CI outside the maps) the loop steps (set by
        :class:`~ucom_tools.ops.remote.RemotePart`), ``is_rejoin`` False."""
        self.par_failed: Callable[[EdgeRef, int, str], None] | None = None
        """Told of a write the loop did not wait for that failed (the part keeps it)."""
        self._par_next: dict[EdgeRef, tuple[int, int]] = {}
        """Per edge with a write under way: the next raw value asked for."""
        self._par_busy: dict[EdgeRef, int] = {}
        """Per edge with a write under way: the value it had before (put back where the
        write fails)."""

    def rejoin(self, bus: str, board: int, delay: float) -> None:
        """Start asking board (bus, board) back after ``delay`` seconds."""
        assert self.rejoiner is not None
        self.under_way.append(self.rejoiner(bus, board, delay))

    def call_off(self, bus: str, board: int) -> bool:
        """The board's maps came again: a rejoin of it under way that has not reached it
        yet is called off.  False where one has reached it (it finishes the job)."""
        for r in self.under_way:
            if r.is_rejoin and r.bus == bus and r.board == board:
                if r.answered is not None:
                    return False
                self.under_way.remove(r)
                r.cancel()
                break
        return True

    def step(self, k: int, ends: float) -> None:
        """Hand each conversation control if what it waits for came (after the cycle's
        drain, cycle ``k``; on the wall clock until ``ends`` at most); a conversation that
        ended brings its board back, or says why not.  On the wall clock the
        conversations share that time: once it is spent the others wait for the next
        cycle (handed control with none left, each would run on beside the loop, and
        several at once kept it from its deadlines: boards lost together, an emergency
        stop), and each cycle another one has the first turn."""
        virtual = self.virtual
        talks = list(self.under_way)
        count = len(talks)
        first = 0 if virtual else k % count
        if not virtual and any([r.busy() for r in talks]):
            count = 0  # one runs beside the loop: none other joins it (each would share
        for i in range(count):  # the GIL with the loop: boards lost together, 2-4 ms late)
            r = talks[(first + i) % count]
            if virtual:
                r.step(None)
            else:
                budget = ends - _monotonic()
                if budget <= 0.0:
                    break
                r.step(budget)
        for r in talks:
            if r.done:
                self.under_way.remove(r)
                if r.is_rejoin:
                    self.ended(r)
                else:
                    self._par_ended(r)
            # the run time's own client got a copy of every answer the conversation
            # had: dropped here, between its requests (kept, they piled up to the
            # dispatcher's limit: megabytes over a day of faults)
            self.forget(r.bus)

    def write_later(self, ref: EdgeRef, raw: int) -> bool:
        """Write ``raw`` to ``ref`` as a conversation (False: no writer, write it now)."""
        if self.par_writer is None:
            return False
        if ref in self._par_busy:  # one write of an edge at a time: the last one wins
            self._par_next[ref] = (raw, 0)
            return True
        held = self.held(ref)
        self._par_busy[ref] = raw if held is None else held
        self.under_way.append(self.par_writer(ref, raw))
        return True

    def _par_ended(self, w: Any) -> None:
        """A write the loop did not wait for ended: the next one of that edge, or the
        value put back where the board did not acknowledge it (kept in the run's writes
        as failed)."""
        ref: EdgeRef = w.ref
        before = self._par_busy.pop(ref, w.raw)
        queued = self._par_next.pop(ref, None)
        if not w.ok:
            self.hold(ref, before)
            if self.par_failed is not None:
                self.par_failed(ref, w.raw, w.how)
            return
        if queued is not None and self.par_writer is not None:
            self._par_busy[ref] = w.raw
            self.under_way.append(self.par_writer(ref, queued[0]))

    def end(self) -> None:
        """Cancel every conversation under way (the part stops)."""
        talks, self.under_way = self.under_way, []
        for r in talks:
            r.cancel()
