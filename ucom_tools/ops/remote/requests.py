"""What the run's consumers ask of the loop, applied on the loop's thread: a write
(:func:`apply_write`, answered by :class:`Applied`), a driving consumer's raw writes
(:class:`DriveWrites`), a stop (:func:`stop_event`), and the boards' Status reports asked
for in turn (:class:`StatusPoll`).  The consumers in another process
(:class:`~ucom_tools.ops.remote.feed.LoopFeed`) and in the loop's own
(:class:`~ucom_tools.ops.remote.feed.LocalRun`) are served by the same functions.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final

import can

from ucom_tools.errors import InputError, UcomError
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.remote.publish import lost_of
from ucom_tools.ops.remote.report import Value, WriteEvent
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import ReportChannel
from ucom_tools.wire.ids import Function, seq

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey

STATUS_PERIOD_S: Final = 1.0
"""Each board's Status report is asked for about this often, the boards in turn."""


@dataclass(frozen=True)
class Applied:
    """What came of a write asked for from outside the loop's thread: ``error`` None
    (done), 'refused' (a wrong name or value: ``message`` says why, with the range or
    the closest names) or 'failed' (the board did not acknowledge); the value as it is
    now, by the edge's shortest name."""

    error: str | None
    message: str
    name: str = ""
    value: Value | None = None
    range: str = ""
    unit: str = ""
    event: WriteEvent | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


def apply_write(part: Any, name: str, value: object, origin: str, *,
                network: bool = True) -> Applied:
    """Set ``name`` to ``value`` as a local ``--set`` does (on the loop's thread); a write
    from the ``network`` is kept in ``part.writes`` with its ``origin``."""
    try:
        ref: EdgeRef = part.set(name, value)
    except InputError as err:
        result, error, message = err.reason, "refused", err.reason
        applied = Applied(error, message)
    except UcomError as err:  # a PAR write the board did not acknowledge
        result, error, message = str(err), "failed", str(err)
        applied = Applied(error, message)
    else:
        result = "done"
        shown = part.names.name_of(ref)
        applied = Applied(None, "done", shown, part[shown], ref.describe_range(),
                          ref.spec.unit)
    if not network:
        return applied
    event = WriteEvent(round(part._clock() - part.stats.started_clock, 4), name,
                       str(value), origin, result)
    part.writes.append(event)
    return Applied(applied.error, applied.message, applied.name, applied.value,
                   applied.range, applied.unit, event)


DriveItems = list[tuple[str, int]]
"""What a consumer that drives edges (the CANopen gateway) asks the loop to set: (the
edge's robot-wide name, its raw value), in order."""


class DriveWrites:
    """The loop's side of a consumer's raw writes (:meth:`LocalRun.drive
    <ucom_tools.ops.remote.feed.LocalRun.drive>`, :meth:`Mirror.drive
    <ucom_tools.ops.remote.mirror.Mirror.drive>`): applied on the loop's thread as a
    local ``--set`` is, without an answer each (the consumer reads the outcome in the
    snapshots) and without an entry in the run's writes (a joint's target at every SYNC
    would fill them); a PAR's acknowledgement is not waited for (the loop steps its
    write beside its cycles: :mod:`ucom_tools.ops.remote.par_write`).  A write to a lost board,
    or a name or value the part refuses, is counted (:attr:`refused`, the last reason in
    :attr:`reason`)."""

    def __init__(self, part: Any) -> None:
        self.part = part
        self._refs: dict[str, EdgeRef] = {}
        self.applied = 0
        self.refused = 0
        self.reason = ""

    def apply(self, items: DriveItems) -> None:
        part, refs = self.part, self._refs
        for name, raw in items:
            try:
                ref = refs.get(name)
                if ref is None:
                    ref = refs[name] = part.names.resolve(
                        name, kinds=(mca.Kind.CI, mca.Kind.PAR))
                part.set(ref, ref.value(raw), wait=False)  # a PAR: stepped by the loop
                self.applied += 1
            except UcomError as err:  # lost board, out of range: the consumer sees it
                self.refused += 1
                self.reason = f"{name}: {err}"


def stop_event(part: Any, origin: str) -> WriteEvent:
    """A stop asked for from the network, kept in ``part.writes`` (the loop then raises
    :class:`~ucom_tools.ops.remote.report.RemoteStop`)."""
    event = WriteEvent(round(part._clock() - part.stats.started_clock, 4), "", "stop",
                       origin, "done")
    part.writes.append(event)
    return event


class StatusPoll:
    """Asks the boards for their Status reports in turn, on the loop's thread, each about
    every :data:`STATUS_PERIOD_S` (a Report Request every 91 ms on ARMAR-III's busiest
    bus: 0.1 % of its capacity); a board that is lost is skipped."""

    def __init__(self, part: Any, boards: list[BoardKey]) -> None:
        self.part = part
        self.boards = list(boards)
        self._every = max(1, round(STATUS_PERIOD_S / part.period_s / max(1, len(boards))))
        self._countdown = self._every

    def on_cycle(self) -> None:
        self._countdown -= 1
        if self._countdown > 0 or not self.boards:
            return
        self._countdown = self._every
        bus, board = self.boards[0]
        self.boards.append(self.boards.pop(0))
        h = self.part.robot.buses.get(bus)
        if h is None or (bus, board) in lost_of(self.part):
            return
        with contextlib.suppress(UcomError):  # the bus's business: the loop notices it
            h.link.send(m.ReportRequest(ReportChannel.STATUS), seq(board))


def is_status(msg: can.Message) -> bool:
    return not msg.is_extended_id and msg.arbitration_id >> 6 == Function.REPORT_0
