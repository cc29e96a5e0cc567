"""What the run time reports: the boards' checks against their trees, the events they
sent while running (Errors, watchdog stops), writes from the network, the loop's
figures, and a run's summary of what the joints did (``ucom remote``)."""

from __future__ import annotations

import itertools
from collections import deque
from dataclasses import dataclass, field
from decimal import Decimal

from ucom_tools.config.attrtree.match import Mismatch
from ucom_tools.errors import (
    UcomError,
)
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.wire.codes import ErrorCode

Value = int | Decimal
"""An edge's value: an int, or an exact Decimal where the edge has decimals."""

JITTER_SAMPLES = 100_000
"""Lateness samples kept for the percentiles (the last 100 s at 1 kHz)."""


class MappingError(UcomError):
    """Boards whose edges differ from their trees (or that did not come up): nothing was
    started.  ``report`` lists every difference."""

    def __init__(self, report: CheckReport) -> None:
        bad = [b for b in report.boards if not b.ok]
        empty = [b for b in bad if b.no_program]
        parts = [] if not empty else [
            f"{len(empty)} board(s) hold no program to start" + (
                "" if len(empty) == len(report.boards) else
                f" ({', '.join(b.where for b in empty)})")]
        others = [b for b in bad if not b.no_program]
        if others:
            parts.append(f"{len(others)} board(s) do not match their trees: "
                         + "; ".join(_where_and(b.where, b.summary()) for b in others))
        super().__init__("; ".join(parts))
        self.report = report
        self.no_program = len(empty) == len(bad)
        """Every board that failed holds no program (nothing else is wrong)."""


def _where_and(where: str, text: str) -> str:
    """``where: text``, unless ``text`` names the board itself already."""
    return text if text.startswith(where) else f"{where}: {text}"


@dataclass(frozen=True)
class BoardEvent:
    """An Error a board sent while the exchange ran (a watchdog that stopped its motors,
    a cycle overrun, a refused CI map, ...)."""

    time: float
    """Seconds since the exchange started (the bus clock)."""
    bus: str
    board: int
    where: str
    code: ErrorCode
    text: str

    @property
    def stopped_motors(self) -> bool:
        """The board's watchdog stopped its motors (it stays stopped until started)."""
        return self.code is ErrorCode.WATCHDOG


@dataclass(frozen=True)
class RawSnapshot:
    """:meth:`RemotePart.snapshot`: the raw values at one moment, decoded elsewhere."""

    clock: float
    frames: dict[str, dict[int, bytes]]
    """Bus -> SO map number -> the map's latest frame data."""
    stamps: dict[str, dict[int, float]]
    ci: dict[str, dict[tuple[int, int], int]]
    par: dict[EdgeRef, int]


@dataclass(frozen=True)
class WriteEvent:
    """A value set, or a stop asked for, from the network (``ucom/<robot>/set``): kept in
    :attr:`RemotePart.writes` with where it came from and what came of it."""

    time: float
    """Seconds since the exchange started (the bus clock)."""
    name: str
    """The edge's name as it was asked for ('' for a stop)."""
    value: str
    """The value as it was asked for ('stop' for a stop)."""
    origin: str
    """Who asked, as the asking client says it (host, process, user) and its Zenoh id."""
    result: str
    """'done', or why it was refused (the range, the closest names)."""

    @property
    def done(self) -> bool:
        return self.result == "done"


class RemoteStop(UcomError):
    """The boards were asked to stop from the network (``ucom/<robot>/stop``, allowed with
    ``--allow-writes``): raised out of :meth:`RemotePart.cycle`; leaving the part stops
    every board."""

    def __init__(self, origin: str) -> None:
        super().__init__(f"stopped from the network by {origin}")
        self.origin = origin


@dataclass(frozen=True)
class BoardCheck:
    """One board of the robot against its tree block."""

    bus: str
    board: int
    where: str
    prefix: str
    tree_file: str
    program: str = ""
    """The program's edge counts, 'CI/SO/PAR' (empty when it did not answer)."""
    differences: tuple[Mismatch, ...] = ()
    error: str = ""
    """Why the board could not be checked (did not start, did not answer)."""
    no_program: bool = False
    """It could not start a program: it holds none (its flash or ExtRAM empty)."""

    @property
    def ok(self) -> bool:
        return not self.error and not self.differences

    def summary(self) -> str:
        if self.error:
            return self.error
        if self.differences:
            n = len(self.differences)
            return f"{n} difference{'s' * (n != 1)}, first: {self.differences[0].message}"
        return "matches"


@dataclass(frozen=True)
class CheckReport:
    boards: tuple[BoardCheck, ...]

    @property
    def ok(self) -> bool:
        return all(b.ok for b in self.boards)


@dataclass
class LoopStats:
    """The PC loop: cycles, lateness (how long after its deadline a cycle sent), misses."""

    period_s: float
    cycles: int = 0
    missed: int = 0
    """Cycles that could not be sent at all: the loop came more than a period late."""
    longest_gap_s: float = 0.0
    """The longest time between the sends of two cycles (about one period while the loop
    keeps up).  No MCA Alive went out meanwhile: a gap as long as the boards' watchdog
    time stops them, and then the PC's loop, not the bus or the boards, was away."""
    late: deque[float] = field(default_factory=lambda: deque(maxlen=JITTER_SAMPLES))
    started_wall: float = 0.0
    started_clock: float = 0.0
    ended_clock: float | None = None
    """When the loop ended (the boards' stop began); None while it runs."""

    def percentile(self, p: float, last: int | None = None) -> float:
        """Lateness in seconds that ``p`` % of the cycles stayed under (of the ``last``
        cycles only, if given: a view that shows it while the loop runs sorts a few
        thousand, not the whole record, and so never holds the GIL for long)."""
        if not self.late:
            return 0.0
        samples = self.late if last is None else itertools.islice(reversed(self.late), last)
        ordered = sorted(samples)
        return ordered[min(len(ordered) - 1, int(p / 100 * len(ordered)))]

    def rate(self, now: float) -> float:
        """Cycles per second of the bus clock from the start to ``now``, or to the loop's
        end once it ended (the boards' stop afterwards is no time of the loop's)."""
        end = now if self.ended_clock is None else self.ended_clock
        span = end - self.started_clock
        return self.cycles / span if span > 0 else 0.0


@dataclass
class Trace:
    """What one value did during a run: first, last, smallest, largest, changes."""

    first: Value
    last: Value
    low: Value
    high: Value
    changes: int = 0


class Summary:
    """Follows every value a :class:`RemotePart` reports (``on_values``): what the
    joints did, for the end of a run."""

    def __init__(self) -> None:
        self.traces: dict[EdgeRef, Trace] = {}

    def __call__(self, t: float, ref: EdgeRef, value: Value) -> None:
        tr = self.traces.get(ref)
        if tr is None:
            self.traces[ref] = Trace(value, value, value, value)
            return
        if value != tr.last:
            tr.changes += 1
            tr.last = value
            tr.low = min(tr.low, value)
            tr.high = max(tr.high, value)


