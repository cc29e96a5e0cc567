"""What the decoder keeps while it reads a bus: requests waiting for their answers, the
boards, process-data maps, cyclic frames and the programming transfer; the deadline
constants."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from decimal import Decimal
from typing import Any

from ucom_tools.config.attrtree.robot import BoundBoard
from ucom_tools.edgelists.model import ProgramSpec
from ucom_tools.trace.conversation import Message
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import (
    MetaField,
)
from ucom_tools.wire.ids import Function

DEFAULT_BITRATE = 1_000_000
DEFAULT_MARGIN = 0.002
"""Seconds every answer deadline adds for the recording itself: a sent frame is stamped
when the host handed it to its interface, a received one by the interface."""
BACKWARDS_S = 0.05
"""How far a frame may be stamped before one written earlier on its bus (a recorder writes
frames as its threads take them; a paced server's clock may lag by milliseconds) before
the trace is taken to mix time bases (``time-backwards``)."""
MAP_PERIODS_LATE = 3
"""An SO map is reported as stopped when no frame of it came for this many periods
(plus :data:`MAP_SLACK` and the margin)."""
MAP_SLACK = 0.005


# ============================================================================ edges
@dataclass(frozen=True)
class Edge:
    """What the decoder knows of one edge of a board: enough to turn raw bytes into a
    value with a name."""

    kind: mca.Kind
    index: int
    name: str
    """The program's (generic) name; ``CI 3`` when unknown."""
    unique: str | None
    prefix: str | None
    width: int
    signed: bool
    exponent: int
    unit: str

    @property
    def label(self) -> str:
        return self.unique or self.name

    def value(self, raw: int) -> Decimal:
        return Decimal(raw).scaleb(self.exponent)

    def text(self, raw: int) -> str:
        v = format(self.value(raw), "f")
        return f"{self.label}={v}" + (f" {self.unit}" if self.unit else "")

    def json(self, raw: int) -> dict[str, Any]:
        return {"kind": self.kind.name, "index": self.index, "name": self.name,
                "unique": self.unique, "prefix": self.prefix, "raw": raw,
                "value": format(self.value(raw), "f"), "unit": self.unit}


# ============================================================================ state
@dataclass
class Expect:
    """A request waiting for its answer."""

    index: int
    t: float
    pos: int
    """Position of the request among the bus's frames."""
    base: float
    """When the request had crossed the wire at the latest (the host's frames ahead of
    it included)."""
    board_time: float
    what: str
    function: int
    target: str | None
    """The board expected to answer; None: any board."""
    accepts: Callable[[str, object], bool]
    needed: int | None = 1
    """Answer frames that complete it; None: one or more (the count is not known)."""
    optional: bool = False
    """A broadcast: every board may answer, none must (no "unanswered"); but a board that
    answers must answer whole."""
    got: int = 0
    per_board: dict[str, int] = field(default_factory=dict)
    done: bool = False
    late: bool = False
    key: tuple[Any, ...] = ()
    """A request with the same key (asked again) closes this one."""
    init_number: int | None = None
    on_answer: Callable[[str, object, float], None] | None = None
    answer_fn: int = Function.READY
    """The function of the answer it waits for (its identifier sets its bus priority)."""


def expected_answer(e: Expect) -> int:
    """The identifier of the answer ``e`` waits for; from an unknown board the lowest
    priority of that function."""
    target = e.target or ""
    if target.isdigit():
        return (e.answer_fn << 6) | int(target)
    if target.startswith("F") and target[1:].isdigit():
        return (e.answer_fn << 6) | 0x20 | int(target[1:])
    return (e.answer_fn << 6) | 0x3F


@dataclass
class TracedBoard:
    label: str
    serial: int | None = None
    counts: tuple[int, int, int] | None = None
    records: dict[tuple[mca.Kind, int], mca.EdgeRecord] = field(default_factory=dict)
    segments: dict[tuple[mca.Kind, int], tuple[Message, dict[int, bytes]]] = field(
        default_factory=dict)
    info: tuple[Message, dict[int, bytes]] | None = None
    text: tuple[Message, list[bytes]] | None = None
    running: bool | None = None
    """Does a program run (None: not known from the trace)."""
    exchange_since: float | None = None
    """The exchange is RUNNING since (None: not running)."""
    cycle_us: float = 1000.0
    prog_enabled: bool = False
    bound: BoundBoard | None = None
    bound_done: bool = False
    spec: ProgramSpec | None = None
    resets_itself: bool = False
    edges: dict[tuple[mca.Kind, int], Edge | None] = field(default_factory=dict)
    """:meth:`BusDecoder._edge`'s cache."""


@dataclass
class SoMap:
    number: int
    board: str
    edges: tuple[int, ...]
    period: int
    defined: float
    last: float | None = None
    reported: bool = False


@dataclass
class Periodic:
    """A process-data summary while the trace is read."""

    agg: Message
    last_t: float = 0.0
    items: list[tuple[str, Edge | None, int, dict[str, Any]]] = field(default_factory=list)
    data: bytes = b""
    ranges: dict[str, tuple[Decimal, Decimal]] = field(default_factory=dict)


@dataclass
class Transfer:
    msg: Message
    begin: m.ProgramBegin
    meta: dict[int, bytes] = field(default_factory=dict)
    boards: set[str] = field(default_factory=set)
    verified: set[str] = field(default_factory=set)
    block: m.ProgramBlock | None = None
    block_msg: Message | None = None
    last_slot: int = -1
    block_slots: list[int] = field(default_factory=list)
    block_resent: int = 0
    seen: dict[int, set[int]] = field(default_factory=dict)
    blocks_sent: int = 0
    data_frames: int = 0
    resent: int = 0
    rounds: int = 0

    @property
    def words(self) -> int | None:
        raw = self.meta.get(MetaField.SIZE)
        return int.from_bytes(raw, "big") if raw is not None else None


