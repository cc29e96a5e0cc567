"""The state of one bus while its frames are read in bus order, and the bookkeeping of
requests and answers every part of the decoder uses: messages, violations, deadlines."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ucom_tools.config.attrtree.match import program_of
from ucom_tools.config.attrtree.robot import BoundBoard, RobotTrees
from ucom_tools.edgelists import known
from ucom_tools.edgelists.model import ProgramSpec
from ucom_tools.protocol.link import SHARED_BUS_FACTOR
from ucom_tools.protocol.timeouts import Timeouts
from ucom_tools.trace.conversation import (
    BusConversation,
    Message,
    Violation,
)
from ucom_tools.trace.state import (
    DEFAULT_BITRATE,
    Expect,
    Periodic,
    SoMap,
    TracedBoard,
    Transfer,
    expected_answer,
)
from ucom_tools.trace.text import (
    _ms,
    jsonable,
)
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.canbits import worst_frame_bits
from ucom_tools.wire.ids import ANSWER


class Decoder:
    """What every bus of one trace shares: the trees, the deadlines' parameters, the
    violations found, the programs bound to boards."""

    def __init__(self, trees: RobotTrees | None, bitrate: int | None, margin: float,
                 timeouts: Timeouts) -> None:
        self.trees = trees
        self.bitrate = bitrate
        self.margin = margin
        self.timeouts = timeouts
        self.violations: list[Violation] = []
        self.cycle_edges = {s.cycle_edge for s in known().values() if s.cycle_edge}
        self._programs: dict[int, ProgramSpec | None] = {}

    def bitrate_of(self, bus: str) -> int:
        if self.bitrate:
            return self.bitrate
        if self.trees is not None:
            for b in self.trees.topology.buses:
                if b.name == bus:
                    return b.bitrate
        return DEFAULT_BITRATE

    def program(self, bound: BoundBoard) -> ProgramSpec | None:
        key = id(bound.board)
        if key not in self._programs:
            self._programs[key] = program_of(bound.board)
        return self._programs[key]



# ============================================================================ decoder
class BusState:
    """The state of one bus while its frames are read in bus order, and what the parts
    of the decoder (:class:`~ucom_tools.trace.decode.BusDecoder`) call of each other."""

    def __init__(self, owner: Decoder, name: str) -> None:
        self.owner = owner
        self.name = name
        self.conv = BusConversation(name)
        self.bitrate = owner.bitrate_of(name)
        self.frame_time = [worst_frame_bits(n) / self.bitrate for n in range(9)]
        self.pos = -1
        self.ids: list[int] = []
        """Identifier of every data frame of the bus so far (by position) ..."""
        self.wire: list[float] = []
        """... its worst-case time on the wire ..."""
        self.senders: list[str] = []
        """... and who sent it (a board's label, or "PC")."""
        self.horizon = 0.0
        self.boards: dict[str, TracedBoard] = {}
        self.expects: list[Expect] = []
        self.init_missed: dict[int, list[Expect]] = {}
        self.chain: list[int] = []
        """Seq IDs the Init Acks assigned since the last BEGIN."""
        self.transfer: Transfer | None = None
        self.so_maps: dict[int, SoMap] = {}
        self.ci_maps: dict[int, dict[str, tuple[int, ...]]] = {}
        self.ci_msgs: dict[int, Message] = {}
        self.so_msgs: dict[int, Message] = {}
        self.periodic: dict[int, Periodic] = {}
        self.alive_msg: dict[str, Message] = {}
        self.alive_last: dict[str, float] = {}
        self.last_t = 0.0
        self.t = 0.0
        self.index = 0
        self.raw = ""

    # ------------------------------------------------------------------ output
    def board(self, label: str) -> TracedBoard:
        b = self.boards.get(label)
        if b is None:
            b = self.boards[label] = TracedBoard(label)
        return b

    def add(self, board: str, function: str, text: str, fields_: dict[str, Any] | None = None,
            *, direction: str = "-") -> Message:
        msg = Message(self.t, self.index, self.name, board, direction, function, text,
                      jsonable(fields_ or {}), 1, self.raw, [self.index])
        self.conv.messages.append(msg)
        return msg

    def violation(self, rule: str, message: str, board: str = "-", *,
                  t: float | None = None, index: int | None = None) -> None:
        self.owner.violations.append(Violation(
            self.t if t is None else t, self.index if index is None else index, self.name,
            board, rule, message))

    # ------------------------------------------------------------------ timing
    def allowed(self, e: Expect, answer_id: int | None = None,
                sender: str | None = None) -> float:
        """By when the answer to ``e`` (identifier ``answer_id`` from ``sender``; by
        default the answer it waits for) must have arrived, as of the current frame: the
        request's end on the wire, the board's time, and twice the wire time of what can
        hold the answer up (CAN arbitration): every frame since the request with a lower
        identifier or from the same board (a node sends its frames in order), plus one
        frame already on the wire; and the margin."""
        if answer_id is None:
            answer_id = expected_answer(e)
            sender = e.target
        wire = self.frame_time[8]
        ids, times, senders = self.ids, self.wire, self.senders
        for p in range(e.pos + 1, self.pos + 1):
            if ids[p] < answer_id or (sender is not None and senders[p] == sender):
                wire += times[p]
        return max(e.base, e.t) + e.board_time + SHARED_BUS_FACTOR * wire + \
            self.owner.margin

    def expect(self, what: str, function: int, target: str | None, board_time: float,
               accepts: Callable[[str, object], bool], *, needed: int | None = 1,
               optional: bool | None = None, key: tuple[Any, ...] = (),
               init_number: int | None = None, answer_fn: int | None = None,
               on_answer: Callable[[str, object, float], None] | None = None) -> Expect:
        """A request waiting for its answer from ``target`` (None: any board; a broadcast
        is ``optional`` unless said otherwise).  An open request with the same function,
        target and ``key`` is closed: it was asked again."""
        full_key = (function, target, *key)
        for old in self.expects:
            if not old.done and old.key == full_key:
                self.close(old, f"asked again {_ms(self.t - old.t)} later")
        e = Expect(self.index, self.t, self.pos, self.horizon, board_time, what, function,
                    target, accepts, needed,
                    optional=target is None if optional is None else optional,
                    key=full_key, init_number=init_number, on_answer=on_answer,
                    answer_fn=ANSWER[function] if answer_fn is None else answer_fn)
        self.expects.append(e)
        return e

    def close(self, e: Expect, why: str) -> None:
        """``e`` gets no more answers: a violation when its answer (or part of it) did not
        come although it was due."""
        if e.done:
            return
        e.done = True
        if self.t <= self.allowed(e):
            return  # asked again (or the trace ended) before the answer was due
        if e.optional or e.got:
            if e.needed is None or e.needed <= 1:
                return
            for b, got in e.per_board.items():
                if got < e.needed:
                    self.violation("unanswered", f"{e.what}: board {b} sent {got} of "
                                   f"{e.needed} answer frames ({why})", b, t=e.t,
                                   index=e.index)
            return
        if e.init_number is not None:  # the chain's end looks the same: see _init_ack
            self.init_missed.setdefault(e.init_number, []).append(e)
            return
        self.violation("unanswered", f"{e.what} was not answered ({why})", e.target or "all",
                       t=e.t, index=e.index)

    def answer(self, board: str, message: object, *, error: m.Error | None = None
               ) -> Expect | None:
        """The open request ``message`` from ``board`` answers (checked for lateness),
        None when it answers none."""
        self.expects = [e for e in self.expects if not e.done]
        # a board's answer belongs to what it was asked, oldest first; then to a
        # broadcast, the latest first (an older one's answers have come)
        targeted = [e for e in self.expects if not e.optional]
        broadcast = [e for e in reversed(self.expects) if e.optional]
        for e in targeted + broadcast:
            if e.target is not None and e.target != board:
                continue
            if error is not None:
                if error.function != e.function:
                    continue
            elif not e.accepts(board, message):
                continue
            e.got += 1
            e.per_board[board] = e.per_board.get(board, 0) + 1
            limit = self.allowed(e, self.ids[self.pos], board)
            if self.t > limit and not e.late:
                e.late = True
                self.violation("late", f"{e.what}: answer {_ms(self.t - e.t)} after the "
                               f"request, due within {_ms(limit - e.t)} (the board's "
                               f"{_ms(e.board_time)} and the frames on the bus)", board)
            if error is not None or (e.needed is not None and e.got >= e.needed):
                e.done = not e.optional
            if e.on_answer is not None:
                e.on_answer(board, message, self.t)
            return e
        return None

    # ------------------------------------------------------------------ the parts'
    # (each defined by one part of BusDecoder, called by another)
    def _stop_exchange(self, bd: TracedBoard, until: float) -> None:
        raise NotImplementedError  # trace.runtime

    def _run_exchange(self, bd: TracedBoard, since: float) -> None:
        raise NotImplementedError  # trace.runtime

    def _values_text(self, bd: TracedBoard | None, kind: mca.Kind, index: int, data: bytes
                     ) -> tuple[str, list[dict[str, Any]]]:
        raise NotImplementedError  # trace.runtime

    def _flush_info(self, bd: TracedBoard) -> None:
        raise NotImplementedError  # trace.boot

    def _flush_text(self, bd: TracedBoard) -> None:
        raise NotImplementedError  # trace.boot
