"""The loop's conversations as a part of their own (:mod:`ucom_tools.ops.remote.
conversations`): which one is handed control, what an ended one tells the loop, and the
writes of one edge one after the other, the last one asked for winning."""

from __future__ import annotations

from typing import Any

from ucom_tools.edgelists.model import EdgeKind, EdgeSpec
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.remote.conversations import Conversations
from ucom_tools.wire import mca


class _Talk:
    """A conversation that ends after ``steps`` turns."""

    def __init__(self, bus: str, board: int, *, steps: int = 1, ok: bool = True,
                 is_rejoin: bool = True, ref: Any = None, raw: int = 0,
                 answered: float | None = None, log: list[str] | None = None) -> None:
        self.bus, self.board, self.ref, self.raw = bus, board, ref, raw
        self.is_rejoin, self.answered, self.ok = is_rejoin, answered, ok
        self.how = "" if ok else "no answer"
        self.left = steps
        self.cancelled = False
        self.log = log if log is not None else []

    @property
    def done(self) -> bool:
        return self.left <= 0

    def busy(self) -> bool:
        return False

    def step(self, budget: float | None) -> None:
        self.log.append(f"{self.bus}{self.board}")
        self.left -= 1

    def cancel(self) -> None:
        self.cancelled = True


class _Loop:
    """What the loop is told (its state, as the part calls it back)."""

    def __init__(self, virtual: bool = True) -> None:
        self.forgotten: list[str] = []
        self.ended: list[_Talk] = []
        self.values: dict[EdgeRef, int] = {}
        self.failed: list[tuple[EdgeRef, int, str]] = []
        self.talks = Conversations(virtual, self.ended.append, self.values.get,
                                   self.values.__setitem__, self.forgotten.append)
        self.talks.par_failed = lambda ref, raw, how: self.failed.append((ref, raw, how))


def _ref() -> EdgeRef:
    spec = EdgeSpec(EdgeKind.PAR, "Gain", width=2, signed=True)
    return EdgeRef("CAN0", 1, "CAN0 board 1", "P", "P Gain", "Gain", mca.Kind.PAR, 0, spec)


def test_a_rejoin_that_ended_is_handed_to_the_loop_and_its_client_forgets() -> None:
    loop = _Loop()
    log: list[str] = []
    loop.talks.rejoiner = lambda bus, n, delay: _Talk(bus, n, steps=2, log=log)
    loop.talks.rejoin("CAN0", 1, 0.0)
    loop.talks.rejoin("CAN1", 2, 0.001)
    loop.talks.step(0, 0.0)
    assert loop.ended == [] and len(loop.talks.under_way) == 2
    loop.talks.step(1, 0.0)
    assert [(t.bus, t.board) for t in loop.ended] == [("CAN0", 1), ("CAN1", 2)]
    assert loop.talks.under_way == []
    assert log == ["CAN01", "CAN12", "CAN01", "CAN12"]  # virtual time: in order, each turn
    assert loop.forgotten == ["CAN0", "CAN1", "CAN0", "CAN1"]  # after every turn, each


def test_on_the_wall_clock_each_cycle_another_one_has_the_first_turn() -> None:
    loop = _Loop(virtual=False)
    log: list[str] = []
    loop.talks.rejoiner = lambda bus, n, delay: _Talk(bus, n, steps=9, log=log)
    loop.talks.rejoin("CAN0", 1, 0.0)
    loop.talks.rejoin("CAN1", 2, 0.0)
    loop.talks.step(1, float("inf"))
    assert log == ["CAN12", "CAN01"]
    log.clear()
    loop.talks.step(0, 0.0)  # no time left before the next deadline: nobody's turn
    assert log == []


def test_a_rejoin_not_yet_answered_is_called_off_one_answered_finishes() -> None:
    loop = _Loop()
    talks: list[_Talk] = []

    def start(bus: str, n: int, delay: float) -> _Talk:
        talks.append(_Talk(bus, n, answered=None if n == 1 else 0.5))
        return talks[-1]

    loop.talks.rejoiner = start
    loop.talks.rejoin("CAN0", 1, 0.0)
    loop.talks.rejoin("CAN0", 2, 0.0)
    assert loop.talks.call_off("CAN0", 1) is True
    assert talks[0].cancelled and talks[0] not in loop.talks.under_way
    assert loop.talks.call_off("CAN0", 2) is False
    assert not talks[1].cancelled and talks[1] in loop.talks.under_way
    assert loop.talks.call_off("CAN1", 7) is True  # none under way


def test_writes_of_one_edge_go_one_after_the_other_the_last_one_winning() -> None:
    loop = _Loop()
    ref = _ref()
    loop.values[ref] = 5
    started: list[int] = []

    def write(r: EdgeRef, raw: int) -> _Talk:
        started.append(raw)
        return _Talk("CAN0", 1, is_rejoin=False, ref=r, raw=raw)

    assert loop.talks.write_later(ref, 10) is False  # no writer yet: written at once
    loop.talks.par_writer = write
    assert loop.talks.write_later(ref, 10) is True
    assert loop.talks.write_later(ref, 11) is True
    assert loop.talks.write_later(ref, 12) is True
    assert started == [10]
    loop.talks.step(0, 0.0)
    assert started == [10, 12]  # 11 was overtaken
    loop.talks.step(1, 0.0)
    assert loop.talks.under_way == [] and loop.failed == [] and loop.ended == []


def test_a_write_that_fails_puts_the_value_before_back_and_is_reported() -> None:
    loop = _Loop()
    ref = _ref()
    loop.values[ref] = 5
    loop.talks.par_writer = lambda r, raw: _Talk("CAN0", 1, ok=False, is_rejoin=False,
                                                  ref=r, raw=raw)
    loop.talks.write_later(ref, 10)
    loop.values[ref] = 10  # the PC holds the value asked for meanwhile
    loop.talks.step(0, 0.0)
    assert loop.values[ref] == 5
    assert loop.failed == [(ref, 10, "no answer")]


def test_the_end_cancels_every_conversation_under_way() -> None:
    loop = _Loop()
    made: list[_Talk] = []
    loop.talks.rejoiner = lambda bus, n, delay: made.append(_Talk(bus, n)) or made[-1]
    loop.talks.rejoin("CAN0", 1, 0.0)
    loop.talks.rejoin("CAN1", 1, 0.0)
    loop.talks.end()
    assert loop.talks.under_way == [] and all(t.cancelled for t in made)
