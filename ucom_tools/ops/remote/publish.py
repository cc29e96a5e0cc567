"""The loop's state for everyone else: one hand-over between the PC's 1 kHz loop and
whatever shows, records, shares or serves the run (the live view, ``--record``, the
Zenoh share, a gateway).

The loop's own structures (its lateness deque, the process image, the lists of events,
the lost boards) change on the loop's thread at every cycle; a thread that reads them
meanwhile can see them half-changed (``deque mutated during iteration``) or, reading a
lot of them, hold Python's lock the loop waits for.  So nothing but the loop reads them:
every few cycles (:attr:`LoopHandover.rate_hz`, at most the loop's rate, and only while
someone reads) the loop's thread takes a :class:`LoopSnapshot` (the values' raw state as
:meth:`~ucom_tools.ops.remote.values.RemoteValues.snapshot` takes it, the loop's figures
with what percentiles need, the events, writes and faults so far, the lost boards, each
bus's traffic) and swaps it in by reference.  A snapshot is never changed after that:
any number of threads read it, each as long as it likes.

- :attr:`LoopHandover.latest` is the newest snapshot (None before the first);
- :meth:`LoopHandover.subscribe` gives a :class:`Doorbell` that wakes its thread when a
  new one is there (at most every ``1 / rate`` seconds; the loop puts one token in a
  queue that holds at most one, it never waits);
- :attr:`LoopHandover.taken` are called with each snapshot on the loop's thread: the
  hand-over to the consumers' process of ``ucom remote run``
  (:mod:`~ucom_tools.ops.remote.feed`), which runs the view, the recording and the
  share apart from the loop, so that none of them holds the lock the loop needs.

What the loop pays: a hand-over that nobody reads costs one decrement and one test a
cycle, a snapshot some microseconds (``benchmarks/consumers.py`` prints both).
Where no hand-over was asked for, nothing at all.
"""

from __future__ import annotations

import itertools
import queue
import time
import weakref
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final, Generic, TypeVar

from ucom_tools.ops.remote.faults import BoardFault, LostBoard
from ucom_tools.ops.remote.loop import RECENT_SAMPLES, RemoteLoop
from ucom_tools.ops.remote.report import BoardEvent, RawSnapshot, WriteEvent

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey

READ_LEASE_S: Final = 1.0
"""A hand-over goes on publishing this long (of the loop's time) after a consumer last
read :attr:`~Snapshots.latest`, then stops until the next read: a reader now and then
always gets one at most a publishing period old, nobody reading costs nothing."""
RATE_HZ: Final = 20.0
"""The rate a hand-over publishes at unless a consumer asks for more (a terminal view
refreshes ten times a second; the Zenoh share asks for its ``--publish-rate``)."""
KEPT: Final = 1000
"""The newest events (and writes, and faults) a snapshot carries; its ``*_total`` says
how many there were in all."""

T = TypeVar("T")


# ---------------------------------------------------------------------- what is handed over
@dataclass(frozen=True)
class LoopFigures:
    """The loop's figures at one moment (:class:`~ucom_tools.ops.remote.report.LoopStats`
    as the loop's thread saw it), with the lateness of the last cycles."""

    period_s: float
    cycles: int
    missed: int
    longest_gap_s: float
    started_clock: float
    ended_clock: float | None
    late: tuple[tuple[float, ...], ...]
    """How late the last cycles sent (seconds), in chunks, oldest first: at least the
    last :data:`~ucom_tools.ops.remote.loop.RECENT_SAMPLES` where as many ran."""

    def recent(self, last: int = RECENT_SAMPLES) -> list[float]:
        """The lateness of the last ``last`` cycles (fewer where fewer ran)."""
        out: list[float] = []
        for chunk in reversed(self.late):
            out.extend(reversed(chunk))
            if len(out) >= last:
                break
        return out[:last]

    def percentile(self, p: float, last: int = RECENT_SAMPLES) -> float:
        """Lateness in seconds that ``p`` % of the last ``last`` cycles stayed under."""
        ordered = sorted(self.recent(last))
        if not ordered:
            return 0.0
        return ordered[min(len(ordered) - 1, int(p / 100 * len(ordered)))]

    def rate(self, now: float) -> float:
        """Cycles per second of the bus clock from the start to ``now`` (or the end)."""
        end = now if self.ended_clock is None else self.ended_clock
        span = end - self.started_clock
        return self.cycles / span if span > 0 else 0.0


@dataclass(frozen=True)
class LoopSnapshot:
    """The loop's state at one moment (see the module docstring): immutable, taken on
    the loop's thread, read by any."""

    number: int
    """1 for the first snapshot of the hand-over, then one more for each."""
    clock: float
    """The bus clock when it was taken (``time.monotonic()`` on real buses, the fleet's
    virtual time in process)."""
    stamp: float
    """The same moment on the base of the frames' time stamps (the values' ``t``: Unix
    time on real buses): ``stamp - t`` is a value's age."""
    taken: float
    """``time.monotonic()`` when it was taken (for ages on this host)."""
    running: bool
    values: RawSnapshot
    """Every value's raw state; :meth:`RemotePart.decode
    <ucom_tools.ops.remote.values.RemoteValues.decode>` makes values of it."""
    figures: LoopFigures
    events: tuple[BoardEvent, ...]
    """The newest of the boards' Errors (at most :data:`KEPT`)."""
    events_total: int
    writes: tuple[WriteEvent, ...]
    """The newest of the values set or stops asked from the network."""
    writes_total: int
    faults: tuple[BoardFault, ...]
    """The newest boards lost or rejoined."""
    faults_total: int
    lost: Mapping[BoardKey, LostBoard]
    """(bus, board) -> the board (since when, what was seen last) for every board lost at
    that moment: its values are stale."""
    traffic: Mapping[str, tuple[float, int, int]]
    """Bus -> (its clock, bits seen so far, its bitrate): two snapshots give its load
    (:meth:`load_since`)."""

    def stale(self, bus: str, board: int) -> bool:
        """Are the board's values stale (the board is lost)?"""
        return (bus, board) in self.lost

    def on_stamps(self, since: float) -> float:
        """A time of the run's events (seconds since the exchange started: a fault's
        ``time``, a lost board's ``since``) on the base of the frames' time stamps (the
        values' ``t``)."""
        return self.stamp - (self.clock - self.figures.started_clock - since)

    def lost_since(self, bus: str, board: int) -> float | None:
        """Since when the board is lost, on the base of the frames' time stamps (None: it
        is not)."""
        lost = self.lost.get((bus, board))
        return None if lost is None else self.on_stamps(lost.since)

    @staticmethod
    def newer(items: tuple[T, ...], total: int, seen: int) -> tuple[T, ...]:
        """Of a snapshot's ``items`` (``events``, ``writes``, ``faults``) with their
        ``total``, those after the first ``seen`` (the oldest of them gone where more
        than :data:`KEPT` came since)."""
        new = total - seen
        if new <= 0:
            return ()
        return items[-new:] if new < len(items) else items

    def load_since(self, before: LoopSnapshot) -> dict[str, float]:
        """Each bus's load between ``before`` and this snapshot (the share of its
        capacity its frames took)."""
        out = {}
        for name, (t1, bits1, bitrate) in self.traffic.items():
            t0, bits0, _ = before.traffic.get(name, (t1, bits1, bitrate))
            out[name] = (bits1 - bits0) / ((t1 - t0) * bitrate) if t1 > t0 else 0.0
        return out


# ---------------------------------------------------------------------- faults
def lost_of(part: RemoteLoop) -> Mapping[BoardKey, LostBoard]:
    """The boards lost now (``part.lost``, a copy: (bus, board) -> since when, what was
    seen last, what the PC does about it)."""
    return part.lost


def faults_of(part: RemoteLoop) -> Sequence[BoardFault]:
    """The boards lost and rejoined so far (``part.faults``), in order."""
    return part.faults


# ---------------------------------------------------------------------- the loop's side
class Tail(Generic[T]):
    """The newest :data:`KEPT` of a list something appends to, as a tuple rebuilt only
    when the list grew, and how many there were in all."""

    def __init__(self) -> None:
        self.items: tuple[T, ...] = ()
        self.total = 0

    def update(self, source: Sequence[T]) -> tuple[T, ...]:
        """Take what ``source`` has more than last time; returns the new ones."""
        n = len(source)
        if n == self.total:
            return ()
        if n < self.total:  # a new list (the loop started again)
            self.items, self.total = (), 0
        new = tuple(source[self.total:n]) if n - self.total < KEPT else tuple(
            source[n - KEPT:n])
        self.add(new, n)
        return new

    def add(self, new: tuple[T, ...], total: int) -> None:
        """The items after the first ``total - len(new)``: ``new``."""
        if total < self.total:
            self.items = ()
        self.items = (self.items + new)[-KEPT:]
        self.total = total


class LateChunks:
    """The lateness of the last cycles (at least :data:`RECENT_SAMPLES` of them) as a
    tuple of chunks, a chunk added at a time (:attr:`LoopFigures.late`)."""

    def __init__(self) -> None:
        self.chunks: tuple[tuple[float, ...], ...] = ()
        self._count = 0

    def add(self, chunk: tuple[float, ...]) -> None:
        if not chunk:
            return
        chunks = [*self.chunks, chunk]
        count = self._count + len(chunk)
        while len(chunks) > 1 and count - len(chunks[0]) >= RECENT_SAMPLES:
            count -= len(chunks.pop(0))
        self.chunks, self._count = tuple(chunks), count

    def clear(self) -> None:
        self.chunks, self._count = (), 0


class Doorbell:
    """Wakes one consumer's thread when there is a new snapshot, at most every
    ``period_s`` of the bus clock (see :meth:`Snapshots.subscribe`).  Whoever hands the
    snapshot over (the loop) rings, never waits: it puts the doorbell itself into the
    consumer's queue (its own, or ``into``: a consumer that waits for other things too),
    at most once until the consumer answers (:meth:`wait`, :meth:`answer`)."""

    def __init__(self, snapshots: Snapshots, period_s: float,
                 into: queue.SimpleQueue[Any] | None = None) -> None:
        self._snapshots = snapshots
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue() if into is None else into
        self._rung = False
        self.period_s = period_s
        self._next = float("-inf")

    def _ring(self, now: float, tolerance: float) -> None:
        """At every snapshot (taken at ``now``, the bus clock)."""
        if now < self._next:
            return
        self._next = now + self.period_s - tolerance
        if not self._rung:
            self._rung = True
            self._queue.put(self)

    def wait(self, timeout: float | None = None) -> LoopSnapshot | None:
        """The newest snapshot once one came since the last wait (None at ``timeout``)."""
        try:
            self._queue.get(timeout=timeout)
        except queue.Empty:
            return None
        return self.answer()

    def answer(self) -> LoopSnapshot | None:
        """The newest snapshot, for a consumer that took this doorbell out of its own
        queue: it rings again at the next one."""
        self._rung = False
        return self._snapshots.latest

    def close(self) -> None:
        """No more wake-ups."""
        self._snapshots._forget(self)


class Snapshots:
    """Where the loop's snapshots are handed over: the newest (:attr:`latest`) and the
    doorbells of the consumers that wait for them (:meth:`subscribe`).  The loop's own
    process has :class:`LoopHandover`; the consumers' process its mirror
    (:class:`~ucom_tools.ops.remote.mirror.Mirror`)."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        """The loop's period."""
        self._latest: LoopSnapshot | None = None
        self._reads = 1
        """How often :attr:`latest` was read (the loop notes when it changes)."""
        self._bells: tuple[Doorbell, ...] = ()

    @property
    def latest(self) -> LoopSnapshot | None:
        """The newest snapshot (None before the first)."""
        self._reads += 1
        return self._latest

    def subscribe(self, rate_hz: float | None = None,
                  into: queue.SimpleQueue[Any] | None = None) -> Doorbell:
        """A doorbell that wakes its consumer with every snapshot, or at about
        ``rate_hz``; it rings into ``into`` where given (see :class:`Doorbell`)."""
        bell = Doorbell(self, 0.0 if rate_hz is None else 1.0 / rate_hz, into)
        self._bells = (*self._bells, bell)
        return bell

    def _forget(self, bell: Doorbell) -> None:
        self._bells = tuple(b for b in self._bells if b is not bell)

    def _deliver(self, snap: LoopSnapshot) -> None:
        """``snap`` is the newest from now on; the doorbells ring."""
        self._latest = snap
        tolerance = self.period_s / 2
        for bell in self._bells:
            bell._ring(snap.clock, tolerance)

    def next_deadline(self) -> float | None:
        """When the loop sends its next cycle (``time.monotonic()``), for threads of its
        process that keep out of its way then; None where that is not known."""
        return None


class LoopHandover(Snapshots):
    """The hand-over of one running part (see the module docstring); one per part
    (:meth:`of`)."""

    def __init__(self, part: RemoteLoop, rate_hz: float = RATE_HZ) -> None:
        super().__init__(part.period_s)
        self.part = part
        self._loop_hz = 1.0 / part.period_s
        self.rate_hz = 0.0
        self._every = 1
        self._countdown = 1
        self._reads_seen = 0
        self._lease = 0
        """Publications left before the hand-over stops for want of readers."""
        self.want(rate_hz)
        self.taken: list[Callable[[LoopSnapshot], None]] = []
        """Called with every snapshot on the thread that took it (the loop's): a consumer
        of every snapshot that lives on the loop's thread itself, as the hand-over to the
        consumers' process (:mod:`~ucom_tools.ops.remote.feed`).  It must not wait."""
        self._number = 0
        self._cycles_seen = 0
        self._late = LateChunks()
        self.new_late: tuple[float, ...] = ()
        """The lateness of the cycles since the snapshot before the last one (what the
        last one added)."""
        self._events: Tail[BoardEvent] = Tail()
        self._writes: Tail[WriteEvent] = Tail()
        self._faults: Tail[BoardFault] = Tail()
        self.new_events: tuple[BoardEvent, ...] = ()
        self.new_writes: tuple[WriteEvent, ...] = ()
        self.new_faults: tuple[BoardFault, ...] = ()
        """What the last snapshot added (for a consumer that forwards only that)."""
        part.each_cycle.append(self.on_cycle)

    @classmethod
    def of(cls, part: RemoteLoop, rate_hz: float = RATE_HZ) -> LoopHandover:
        """The hand-over of ``part`` (made at the first call), publishing at least at
        ``rate_hz``.  Call it before the loop runs (or on its thread)."""
        h = _HANDOVERS.get(part)
        if h is None:
            h = _HANDOVERS[part] = cls(part, rate_hz)
        else:
            h.want(rate_hz)
        return h

    def want(self, rate_hz: float) -> None:
        """Publish at least at ``rate_hz`` (at most the loop's rate): the rate becomes the
        loop's divided by a whole number of cycles."""
        every = max(1, int(self._loop_hz / max(rate_hz, 1e-9) + 1e-9))
        if self.rate_hz and every >= self._every:
            return
        self._every = every
        self.rate_hz = self._loop_hz / every
        self._countdown = min(self._countdown, every)

    def subscribe(self, rate_hz: float | None = None,
                  into: queue.SimpleQueue[Any] | None = None) -> Doorbell:
        """A doorbell that wakes its consumer with every snapshot, or at about ``rate_hz``
        (the hand-over publishes at least that often from now on); it rings into ``into``
        where given (see :class:`Doorbell`)."""
        if rate_hz is not None:
            self.want(rate_hz)
        return super().subscribe(rate_hz, into)

    def next_deadline(self) -> float | None:
        """When the loop sends its next cycle (``time.monotonic()``), for threads that keep
        out of its way then; None in virtual time or when it does not run."""
        return self.part.next_deadline

    # ------------------------------------------------------------------ the loop's thread
    def on_cycle(self) -> None:
        """Every cycle, on the loop's thread (``each_cycle``): a snapshot when one is due
        and someone reads them."""
        self._countdown -= 1
        if self._countdown > 0:
            return
        self._countdown = self._every
        if self._reads != self._reads_seen:
            self._reads_seen = self._reads
            self._lease = max(1, round(READ_LEASE_S * self.rate_hz))
        if self._lease > 0 or self._bells or self.taken:
            self._lease -= 1
            self.publish()

    def publish(self) -> LoopSnapshot:
        """Take a snapshot and hand it over (the loop's thread, or any thread once the
        loop has ended: :meth:`final`)."""
        snap = self._take(self.part)
        self._deliver(snap)
        for taken in self.taken:
            taken(snap)
        return snap

    def final(self) -> LoopSnapshot | None:
        """After the loop ended (the boards stopped): one last snapshot of how the run
        ended, taken on the calling thread; while it runs, the latest."""
        if self.part.running:
            return self.latest
        return self.publish()

    def _stamp(self) -> float:
        """Now on the base of the frames' time stamps (the first bus's)."""
        for h in self.part.robot.buses.values():
            return h.link.dispatcher.stamp()
        return time.time()  # pragma: no cover - a part has a bus

    def _take(self, part: RemoteLoop) -> LoopSnapshot:
        stats = part.stats
        new = stats.cycles - self._cycles_seen
        if new < 0 or stats.cycles == 0:  # a new run of the loop
            self._late.clear()
            new = stats.cycles
        self._cycles_seen = stats.cycles
        chunk: tuple[float, ...] = ()
        if new > 0:
            late = stats.late
            chunk = tuple(itertools.islice(reversed(late), min(new, len(late))))[::-1]
            self._late.add(chunk)
        self.new_late = chunk
        figures = LoopFigures(stats.period_s, stats.cycles, stats.missed,
                              stats.longest_gap_s, stats.started_clock, stats.ended_clock,
                              self._late.chunks)
        self.new_events = self._events.update(part.events)
        self.new_writes = self._writes.update(getattr(part, "writes", ()))
        self.new_faults = self._faults.update(faults_of(part))
        self._number += 1
        return LoopSnapshot(
            self._number, part._clock(), self._stamp(), time.monotonic(), part.running,
            part.snapshot(),
            figures, self._events.items, self._events.total, self._writes.items,
            self._writes.total, self._faults.items, self._faults.total, lost_of(part),
            {n: (h.link.clock(), h.link.dispatcher.bits, h.link.bitrate)
             for n, h in part.robot.buses.items()})


_HANDOVERS: weakref.WeakKeyDictionary[RemoteLoop, LoopHandover] = weakref.WeakKeyDictionary()
"""The hand-over of each part that has one (:meth:`LoopHandover.of`)."""

__all__ = ["KEPT", "RATE_HZ", "READ_LEASE_S", "Doorbell", "LateChunks", "LoopFigures",
           "LoopHandover", "LoopSnapshot", "Tail", "faults_of", "lost_of"]
