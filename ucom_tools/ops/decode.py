"""Decoding a CAN trace into the UCoM conversation it carries (``ucom decode``).

:func:`decode_frames` takes python-can messages (read from any log python-can reads, or
recorded by a test) and returns a :class:`Conversation`: per bus (the frames' channel;
frames without one are bus ``CAN``) and per board the messages in the order they were
on the bus, each decoded with the project's codecs (``man/ucom-protocol.7``), and the
protocol violations found on the way.  Pure: the result depends on the frames alone
(and on the attribute trees, when given).

What the conversation shows beyond single frames:

- multi-frame answers assembled: the 10 Info frames into one record, Text reports into
  their message, MCA DumpIO Descr segments into the edge's record;
- programming as progress: one line per BLOCK frame with the data frames that followed
  it (slots, and resends of frames already seen), a summary at each END;
- the run time with names: with the robot's attribute trees (:func:`load_trees`) MCA
  values carry their robot-wide unique names; values are decoded with the edge records
  seen in the trace (MCA DumpIO Descr), else with the program the board's tree maps;
  process-data maps are learned from the Admin Data SO_MAP/CI_MAP frames of the trace;
  cyclic frames (SO and CI maps, MCA Alive) are summarised per map.

The rules checked (:data:`RULES`): every frame decodes (a FrameError names the field);
every request a board answers is answered, and within the board's time of TIMEOUTS
(``ucom_tools.protocol.timeouts``) plus the wire time of the frames on the bus in
between, doubled as the host's deadlines double it, plus ``margin``; programming data
frames come in sequence (a slot inside the block the last BLOCK frame opened, rising);
an SO map keeps arriving at its period while its board's exchange runs.

As a library (a test that recorded its frames with a dispatcher tap)::

    conv = decode_frames(frames, load_trees(["armar3"]))
    assert conv.ok, conv.render(timeline=True)   # the decoded trace, readable
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, fields, is_dataclass
from datetime import datetime
from decimal import Decimal
from enum import Enum
from pathlib import Path
from typing import Any

import can

from ucom_tools.config.attrtree import Kind as TreeKind
from ucom_tools.config.attrtree.match import program_of
from ucom_tools.config.attrtree.robot import BoundBoard, RobotTrees
from ucom_tools.errors import FrameError, InputError
from ucom_tools.ops.record import DEFAULT_BUS, channel_names
from ucom_tools.programs import known
from ucom_tools.programs.model import ProgramSpec
from ucom_tools.protocol.link import SHARED_BUS_FACTOR
from ucom_tools.protocol.timeouts import DEFAULT, Timeouts
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.canbits import worst_frame_bits
from ucom_tools.wire.codes import (
    ErrorCode,
    InitAckKind,
    InitOp,
    MetaField,
    ReadyReason,
    ReportChannel,
    ResultStatus,
    StatusOp,
    Target,
)
from ucom_tools.wire.ids import Address, Direction, Function, IdType, function_direction
from ucom_tools.wire.info import INFO_FRAMES, BoardInfo
from ucom_tools.wire.transfer import decode_date

PC_TO_BOARD = "PC -> board"
BOARD_TO_PC = "board -> PC"
DEFAULT_BITRATE = 1_000_000
DEFAULT_MARGIN = 0.002
BACKWARDS_S = 0.05
"""How far a frame may be stamped before one written earlier on its bus (a recorder writes
frames as its threads take them; a paced server's clock may lag by milliseconds) before
the trace is taken to mix time bases (``time-backwards``)."""
"""Seconds every answer deadline adds for the recording itself: a sent frame is stamped
when the host handed it to its interface, a received one by the interface."""
STARTUP = 0.001
"""A started program decides within this time whether it fits (TIMEOUTS)."""
MAP_PERIODS_LATE = 3
"""An SO map is reported as stopped when no frame of it came for this many periods
(plus :data:`MAP_SLACK` and the margin)."""
MAP_SLACK = 0.005

RULES = {
    "malformed": "a frame that does not decode (the field is named)",
    "foreign-frame": "an extended, remote or CAN FD frame: not part of the protocol",
    "late": "an answer later than the board's time (TIMEOUTS) after its request",
    "unanswered": "a request whose answer never came",
    "data-out-of-sequence": "a Program data frame outside the block the last BLOCK frame "
                            "opened, or whose slot does not rise",
    "so-map-stopped": "an SO map that stopped arriving at its period while its board's "
                      "exchange ran",
    "time-backwards": "a frame stamped more than 50 ms (or the margin, if larger) before "
                      "one written before it on the same bus: the trace mixes time bases "
                      "(its order and every deadline after it are doubtful)",
}
"""Every rule a :class:`Violation` names, and what it means."""


# ============================================================================ results
@dataclass
class Message:
    """One line of a conversation: a frame, or several assembled into one message
    (an Info record, a text, an edge record, a block of programming data, a map's
    frames)."""

    t: float
    """Seconds since the trace's first frame."""
    index: int
    """Position of the (first) frame in the trace, from 0."""
    bus: str
    board: str
    """Whose conversation: a seq ID ("3"), a fixed ID ("F5"), "all" (broadcast),
    "unnumbered", "SO map N" / "CI map N" (process data), "bus" (error frames)."""
    dir: str
    """:data:`PC_TO_BOARD`, :data:`BOARD_TO_PC` or "-"."""
    function: str
    """The function's name as in Tab. B.4."""
    text: str
    fields: dict[str, Any] = field(default_factory=dict)
    frames: int = 1
    """How many frames this message stands for."""
    raw: str = ""
    """The first frame, candump style (``0C1#00010010D92172BB``)."""
    members: list[int] = field(default_factory=list)
    """The positions in the trace of the frames it stands for (``index`` the first)."""

    def to_json(self) -> dict[str, Any]:
        return {"t": round(self.t, 6), "index": self.index, "dir": self.dir,
                "function": self.function, "text": self.text, "fields": self.fields,
                "frames": self.frames, "frame": self.raw}


@dataclass(frozen=True)
class Violation:
    """A protocol violation: which frame (index in the trace, time), where, which rule
    (:data:`RULES`) and what exactly."""

    t: float
    index: int
    bus: str
    board: str
    rule: str
    message: str

    def to_json(self) -> dict[str, Any]:
        return {"t": round(self.t, 6), "index": self.index, "bus": self.bus,
                "board": self.board, "rule": self.rule, "message": self.message}

    def __str__(self) -> str:
        return (f"#{self.index} {self.t:.6f} s {self.bus} board {self.board}: "
                f"{self.rule}: {self.message}")


@dataclass
class BusConversation:
    """The messages of one bus, in bus order (:attr:`messages`), and by board
    (:meth:`boards`)."""

    name: str
    messages: list[Message] = field(default_factory=list)
    frames: int = 0

    def boards(self) -> dict[str, list[Message]]:
        """Board -> its messages, boards in the order "all", seq IDs, fixed IDs,
        "unnumbered", SO maps, CI maps, "bus"."""
        out: dict[str, list[Message]] = {}
        for msg in self.messages:
            out.setdefault(msg.board, []).append(msg)
        return dict(sorted(out.items(), key=lambda kv: _board_order(kv[0])))

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "frames": self.frames,
                "boards": [{"board": b, "messages": [x.to_json() for x in msgs]}
                           for b, msgs in self.boards().items()]}


def _board_order(board: str) -> tuple[int, int, str]:
    if board == "all":
        return (0, 0, board)
    if board.isdigit():
        return (1, int(board), board)
    if board.startswith("F") and board[1:].isdigit():
        return (2, int(board[1:]), board)
    for n, prefix in enumerate(("SO map ", "CI map "), 4):
        if board.startswith(prefix) and board[len(prefix):].isdigit():
            return (n, int(board[len(prefix):]), board)
    return (3 if board == "unnumbered" else 6, 0, board)


@dataclass
class Conversation:
    """What :func:`decode_frames` makes of a trace: one :class:`BusConversation` per
    bus (in order of first appearance) and every :class:`Violation` (in trace order)."""

    buses: list[BusConversation]
    violations: list[Violation]
    frames: int
    """Frames in the trace."""
    start: float | None
    """Timestamp of the trace's first frame (``t`` counts from it); None when empty."""

    @property
    def ok(self) -> bool:
        """No violation found."""
        return not self.violations

    def bus(self, name: str) -> BusConversation:
        for b in self.buses:
            if b.name == name:
                return b
        raise KeyError(name)

    def messages(self, *, bus: str | None = None, board: str | None = None,
                 function: str | None = None) -> list[Message]:
        """Messages of one bus, board or function (all when None), in bus order."""
        return [msg for b in self.buses if bus is None or b.name == bus
                for msg in b.messages
                if (board is None or msg.board == board)
                and (function is None or msg.function == function)]

    def to_json(self) -> dict[str, Any]:
        """``{"buses": [{"name", "frames", "boards": [{"board", "messages": [{"t",
        "index", "dir", "function", "text", "fields", "frames", "frame"}]}]}],
        "violations": [{"t", "index", "bus", "board", "rule", "message"}], "frames"}``."""
        return {"frames": self.frames, "buses": [b.to_json() for b in self.buses],
                "violations": [v.to_json() for v in self.violations]}

    def render(self, *, timeline: bool = False, bus: str | None = None,
               board: str | None = None) -> str:
        """The conversation as text: per bus, per board (``timeline``: one list per bus in
        bus order, with a board column), then the violations.  ``bus`` and ``board``
        show only those."""
        lines: list[str] = []
        for b in self.buses:
            if bus is not None and b.name != bus:
                continue
            lines.append(f"bus {b.name}: {b.frames} frames")
            if timeline:
                for msg in b.messages:
                    if board is None or msg.board == board:
                        lines.append("  " + _line(msg, with_board=True))
            else:
                for name, msgs in b.boards().items():
                    if board is not None and name != board:
                        continue
                    lines.append(f"  board {name}")
                    lines.extend("    " + _line(msg) for msg in msgs)
            lines.append("")
        shown = [v for v in self.violations
                 if (bus is None or v.bus == bus) and (board is None or v.board == board)]
        if shown:
            lines.append(f"violations: {len(shown)}")
            lines.extend(f"  {v}" for v in shown)
        else:
            lines.append("violations: none")
        return "\n".join(lines) + "\n"

    def __str__(self) -> str:
        return self.render(timeline=True)


def _line(msg: Message, *, with_board: bool = False) -> str:
    who = f"{msg.board:>10}  " if with_board else ""
    arrow = {PC_TO_BOARD: "PC>", BOARD_TO_PC: "<B "}.get(msg.dir, " - ")
    return f"{msg.t:11.6f}  {who}{arrow} {msg.function:<24} {msg.text}".rstrip()


# ============================================================================ helpers
def jsonable(value: Any) -> Any:
    """``value`` as JSON: enums by name, bytes as hex, datetimes ISO, dataclasses as
    objects, Decimals as exact text."""
    if isinstance(value, Enum):
        return value.name
    if isinstance(value, bytes | bytearray):
        return bytes(value).hex(" ").upper()
    if isinstance(value, datetime):
        return value.isoformat()
    if isinstance(value, Decimal):
        return format(value, "f")
    if isinstance(value, bool | int | float | str) or value is None:
        return value
    if is_dataclass(value) and not isinstance(value, type):
        return {f.name: jsonable(getattr(value, f.name)) for f in fields(value)}
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [jsonable(v) for v in value]
    return str(value)


def raw_text(msg: can.Message) -> str:
    """``ID#DATA`` as candump prints it (``R`` for a remote frame)."""
    ident = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
    if msg.is_remote_frame:
        return f"{ident}#R"
    return f"{ident}#{bytes(msg.data).hex().upper()}"


def _ranges(numbers: Iterable[int]) -> str:
    """1, 2, 3, 5 -> '1-3, 5'."""
    out: list[str] = []
    nums = sorted(set(numbers))
    i = 0
    while i < len(nums):
        j = i
        while j + 1 < len(nums) and nums[j + 1] == nums[j] + 1:
            j += 1
        out.append(str(nums[i]) if i == j else f"{nums[i]}-{nums[j]}")
        i = j + 1
    return ", ".join(out)


def _to(board: str) -> str:
    return " to every board" if board == "all" else f" to board {board}"


def _ms(seconds: float) -> str:
    return f"{seconds * 1000:.3f} ms"


def bus_name(channel: Any, trees: RobotTrees | None = None) -> str:
    """The bus a frame's channel names (:func:`~ucom_tools.ops.record.channel_names`,
    the one rule for reading and writing; for a single channel, without the rule's
    look at the whole trace)."""
    buses = [b.name for b in trees.topology.buses] if trees is not None else []
    return channel_names([channel], buses)[channel]


# ============================================================================ edges
@dataclass(frozen=True)
class _Edge:
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
class _Expect:
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


_ANSWERS: dict[int, int] = {
    Function.RESET: Function.READY, Function.XRESET: Function.READY,
    Function.SET_STATUS: Function.READY, Function.START: Function.READY,
    Function.INFO_REQUEST: Function.INFO, Function.INIT_REQUEST: Function.INIT_ACK,
    Function.REPORT_REQUEST: Function.REPORT_3, Function.PROGRAM: Function.READY,
    Function.MCA_CONTROLLER_INPUT: Function.MCA_READY, Function.MCA_PARAMETER:
    Function.MCA_READY, Function.MCA_START: Function.MCA_READY,
    Function.MCA_ADMIN_DATA: Function.MCA_READY,
    Function.MCA_DUMPIO_DESCR_REQUEST: Function.MCA_DUMPIO_DESCR,
    Function.MCA_DUMP_CI: Function.MCA_DSP_CI,
}
"""The function that answers each request (Program: PREPARE's; END waits for Program
Finished, a Report Request for the Report of its channel)."""


def _answer_id(e: _Expect) -> int:
    """The identifier of the answer ``e`` waits for; from an unknown board the lowest
    priority of that function."""
    target = e.target or ""
    if target.isdigit():
        return (e.answer_fn << 6) | int(target)
    if target.startswith("F") and target[1:].isdigit():
        return (e.answer_fn << 6) | 0x20 | int(target[1:])
    return (e.answer_fn << 6) | 0x3F


@dataclass
class _Board:
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
    edges: dict[tuple[mca.Kind, int], _Edge | None] = field(default_factory=dict)
    """:meth:`_BusDecoder._edge`'s cache."""


@dataclass
class _SoMap:
    number: int
    board: str
    edges: tuple[int, ...]
    period: int
    defined: float
    last: float | None = None
    reported: bool = False


@dataclass
class _Periodic:
    """A process-data summary while the trace is read."""

    agg: Message
    last_t: float = 0.0
    items: list[tuple[str, _Edge | None, int, dict[str, Any]]] = field(default_factory=list)
    data: bytes = b""
    ranges: dict[str, tuple[Decimal, Decimal]] = field(default_factory=dict)


@dataclass
class _Transfer:
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


# ============================================================================ decoder
class _BusDecoder:
    """The state of one bus while its frames are read in bus order."""

    def __init__(self, owner: _Decoder, name: str) -> None:
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
        self.boards: dict[str, _Board] = {}
        self.expects: list[_Expect] = []
        self.init_missed: dict[int, list[_Expect]] = {}
        self.chain: list[int] = []
        """Seq IDs the Init Acks assigned since the last BEGIN."""
        self.transfer: _Transfer | None = None
        self.so_maps: dict[int, _SoMap] = {}
        self.ci_maps: dict[int, dict[str, tuple[int, ...]]] = {}
        self.ci_msgs: dict[int, Message] = {}
        self.so_msgs: dict[int, Message] = {}
        self.periodic: dict[int, _Periodic] = {}
        self.alive_msg: dict[str, Message] = {}
        self.alive_last: dict[str, float] = {}
        self.last_t = 0.0
        self.t = 0.0
        self.index = 0
        self.raw = ""

    # ------------------------------------------------------------------ output
    def board(self, label: str) -> _Board:
        b = self.boards.get(label)
        if b is None:
            b = self.boards[label] = _Board(label)
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

    # ------------------------------------------------------------------ frames
    def feed(self, index: int, msg: can.Message, t: float) -> None:
        self.index, self.t, self.raw = index, t, raw_text(msg)
        self.last_t = max(self.last_t, t)
        self.conv.frames += 1
        if msg.is_error_frame:
            self.add("bus", "error frame", "an error frame on the bus")
            return
        if msg.is_extended_id or msg.is_remote_frame or msg.is_fd:
            what = ("an extended-identifier" if msg.is_extended_id else
                    "a remote" if msg.is_remote_frame else "a CAN FD")
            self.add("bus", "foreign frame", f"{what} frame {self.raw}")
            self.violation("foreign-frame", f"{what} frame {self.raw}: the protocol uses "
                           "CAN 2.0A data frames with 11-bit identifiers only", "bus")
            return
        data = bytes(msg.data)
        self.pos += 1
        code = msg.arbitration_id >> 6
        direction = function_direction(code)
        if direction is Direction.HOST_TO_BOARD:
            self.horizon = max(self.horizon, t) + self.frame_time[min(len(data), 8)]
        board = self._label(msg.arbitration_id, direction, len(data))
        self.ids.append(msg.arbitration_id)
        self.wire.append(self.frame_time[min(len(data), 8)])
        self.senders.append("PC" if direction is Direction.HOST_TO_BOARD else board)
        address: Address
        message: object
        try:
            if code in m.BOOTLOADER_FUNCTIONS:
                address, message = m.decode(msg.arbitration_id, data)
            elif code in mca.MCA_FUNCTIONS:
                mca_address, message = mca.decode(msg.arbitration_id, data)
                address = mca_address or Address(IdType.FIXED, msg.arbitration_id & 0x1F)
            else:
                raise FrameError("function", f"code {code} is unassigned")
        except FrameError as err:
            name = Function(code).label if code <= 27 else f"function {code}"
            arrow = {Direction.HOST_TO_BOARD: PC_TO_BOARD,
                     Direction.BOARD_TO_HOST: BOARD_TO_PC}.get(direction, "-")
            self.add(board, name, f"malformed {self.raw}: {err}", {"field": err.field,
                     "error": err.message}, direction=arrow)
            self.violation("malformed", f"{name} {self.raw}: {err.field}: {err.message}",
                           board)
            return
        if direction is Direction.HOST_TO_BOARD:
            self._host(board, address, message)
        else:
            self._from_board(board, address, message)

    def _label(self, arbitration_id: int, direction: Direction, dlc: int) -> str:
        code, number, fixed = arbitration_id >> 6, arbitration_id & 0x1F, \
            bool(arbitration_id & 0x20)
        if code == Function.PROGRAM and dlc == 8:
            return "all"  # a data frame's low bits are its slot, not a board
        if fixed and code == Function.MCA_SENSOR_OUTPUT:
            return f"SO map {number}"
        if fixed and code == Function.MCA_CONTROLLER_INPUT:
            return f"CI map {number}"
        if number == 0 and not fixed:
            return "all" if direction is not Direction.BOARD_TO_HOST else "unnumbered"
        return f"F{number}" if fixed else str(number)

    # ------------------------------------------------------------------ timing
    def allowed(self, e: _Expect, answer_id: int | None = None,
                sender: str | None = None) -> float:
        """By when the answer to ``e`` (identifier ``answer_id`` from ``sender``; by
        default the answer it waits for) must have arrived, as of the current frame: the
        request's end on the wire, the board's time, and twice the wire time of what can
        hold the answer up (CAN arbitration): every frame since the request with a lower
        identifier or from the same board (a node sends its frames in order), plus one
        frame already on the wire; and the margin."""
        if answer_id is None:
            answer_id = _answer_id(e)
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
               on_answer: Callable[[str, object, float], None] | None = None) -> _Expect:
        """A request waiting for its answer from ``target`` (None: any board; a broadcast
        is ``optional`` unless said otherwise).  An open request with the same function,
        target and ``key`` is closed: it was asked again."""
        full_key = (function, target, *key)
        for old in self.expects:
            if not old.done and old.key == full_key:
                self.close(old, f"asked again {_ms(self.t - old.t)} later")
        e = _Expect(self.index, self.t, self.pos, self.horizon, board_time, what, function,
                    target, accepts, needed,
                    optional=target is None if optional is None else optional,
                    key=full_key, init_number=init_number, on_answer=on_answer,
                    answer_fn=_ANSWERS[function] if answer_fn is None else answer_fn)
        self.expects.append(e)
        return e

    def close(self, e: _Expect, why: str) -> None:
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
               ) -> _Expect | None:
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

    def finish(self) -> None:
        """The trace ended: requests still waiting, maps that stopped."""
        self.t = self.last_t
        for e in self.expects:
            if not e.done:
                self.close(e, "the trace ends")
        for b in self.boards.values():
            self._flush_partial(b)
        for so in self.so_maps.values():
            self._check_map_end(so, self.last_t)
        self._summarise()

    # ------------------------------------------------------------------ requests
    def _host(self, board: str, address: Address, message: object) -> None:
        if isinstance(message, m.ProgramFrame):
            self._program(message, None if board == "all" else board)
            return
        label = Function(message.FUNCTION).label  # type: ignore[attr-defined]
        target = None if board == "all" else board
        t = self.owner.timeouts
        if isinstance(message, m.Reset | m.XReset):
            self.add(board, label, "", direction=PC_TO_BOARD)
            self._reset(target)
            self.expect(f"{label}{_to(board)}", message.FUNCTION, target, t.reset,
                        lambda _b, a: isinstance(a, m.Ready) and a.reason is ReadyReason.BOOT)
        elif isinstance(message, m.SetStatus):
            self._set_status(board, target, message)
        elif isinstance(message, m.InfoRequest):
            self.add(board, label, "" if target else "every board with a number",
                     direction=PC_TO_BOARD)
            self.expect(f"Info Request{_to(board)}", Function.INFO_REQUEST, target,
                        t.reply, lambda _b, a: isinstance(a, m.InfoFrame),
                        needed=INFO_FRAMES)
        elif isinstance(message, m.ReportRequest):
            self._report_request(board, target, message)
        elif isinstance(message, m.InitRequest):
            self._init_request(message)
        elif isinstance(message, m.Start):
            self._start(board, target, message)
        else:
            self._mca_request(board, target, message)

    def _reset(self, target: str | None) -> None:
        for b in self.boards.values():
            if target is None or b.label == target:
                b.running = False
                self._stop_exchange(b, self.t)
                b.prog_enabled = False
                for e in self.expects:  # a reset board answers nothing it was asked
                    if not e.done and e.target == b.label and \
                            e.function not in (Function.RESET, Function.XRESET):
                        self.close(e, "the board was reset")

    def _set_status(self, board: str, target: str | None, msg: m.SetStatus) -> None:
        self.add(board, "SetStatus", f"{msg.op.name} {msg.value}",
                 {"op": msg.op, "value": msg.value}, direction=PC_TO_BOARD)
        answerer = str(msg.value) if msg.op is StatusOp.SEQ_ID and target is not None \
            else target
        want = (int(msg.op) << 8) | msg.value

        def done(b: str, _a: object, _t: float) -> None:
            if msg.op is StatusOp.PROG_ENABLE:
                self.board(b).prog_enabled = bool(msg.value)

        self.expect(f"SetStatus {msg.op.name}{_to(board)}", Function.SET_STATUS,
                    answerer, self.owner.timeouts.reply,
                    lambda _b, a: isinstance(a, m.Ready) and a.reason is ReadyReason.STATUS
                    and a.value16 == want, key=(msg.op, msg.value), on_answer=done)

    def _report_request(self, board: str, target: str | None, msg: m.ReportRequest) -> None:
        text = msg.channel.name
        needed = 1
        if msg.channel is ReportChannel.MEMORY:
            text += f" {msg.space.name}:{msg.address:04X}, {msg.count} words"
            needed = max(1, math.ceil(msg.count / 3))
        self.add(board, "Report Request", text, {"channel": msg.channel, "space": msg.space,
                 "address": msg.address, "count": msg.count}, direction=PC_TO_BOARD)
        function = Function.report(msg.channel) if msg.channel <= 3 else None
        self.expect(f"Report Request {msg.channel.name}{_to(board)}",
                    Function.REPORT_REQUEST, target, self.owner.timeouts.reply,
                    lambda _b, a: function is not None and
                    getattr(a, "FUNCTION", None) is function, needed=needed,
                    key=(msg.channel, msg.address),
                    answer_fn=function if function is not None else Function.ERROR)

    def _init_request(self, msg: m.InitRequest) -> None:
        text = msg.op.name + (f" {msg.number}" if msg.op is InitOp.NEXT else "")
        fields_: dict[str, Any] = {"op": msg.op, "number": msg.number}
        if msg.op is InitOp.BEGIN:
            self.chain = []
        elif msg.op is InitOp.END:
            text += (f": the chain has seq IDs {_ranges(self.chain)}" if self.chain else
                     ": no board answered")
            fields_["chain"] = list(self.chain)
        self.add("all", "Init Request", text, fields_, direction=PC_TO_BOARD)
        t = self.owner.timeouts
        if msg.op in (InitOp.BEGIN, InitOp.NEXT):
            n = 1 if msg.op is InitOp.BEGIN else msg.number
            self.expect(f"Init Request {text} (seq ID {n})", Function.INIT_REQUEST, None,
                        t.init_step, lambda _b, a: isinstance(a, m.InitAck) and
                        a.kind is InitAckKind.ASSIGNED and a.seq_id == n, optional=False,
                        key=(n,), init_number=n)
        elif msg.op is InitOp.END:
            # the questions nobody answered were the chain's end, not lost answers
            for e in self.expects:
                if e.init_number is not None and not e.done:
                    self.close(e, "the chain ended")
            self.init_missed.clear()
        elif msg.op in (InitOp.PROBE_FIRST, InitOp.PROBE_LAST):
            kind = InitAckKind.FIRST if msg.op is InitOp.PROBE_FIRST else InitAckKind.LAST
            self.expect(f"Init Request {text}", Function.INIT_REQUEST, None, t.probe,
                        lambda _b, a: isinstance(a, m.InitAck) and a.kind is kind,
                        needed=None, key=(kind,))

    def _start(self, board: str, target: str | None, msg: m.Start) -> None:
        self.add(board, "Start", msg.target.name.lower(), {"target": msg.target},
                 direction=PC_TO_BOARD)
        reply = self.owner.timeouts.reply
        was_stopped = {b.label for b in self.boards.values()
                       if (target is None or b.label == target) and b.running is False}
        start_t, start_index, start_pos, start_base = self.t, self.index, self.pos, self.horizon

        def started(b: str, a: object, _t: float) -> None:
            if not isinstance(a, m.Ready):
                return
            bd = self.board(b)
            if b in was_stopped:  # a program comes up: it announces itself (RUN TIME)
                e = _Expect(start_index, start_t, start_pos, start_base, reply + STARTUP,
                            f"program start on board {b} (its unsolicited MCA Ready)",
                            Function.START, b, lambda _x, y: isinstance(y, mca.McaReady)
                            and y.answers == Function.MCA_READY, key=(Function.START, b, "up"),
                            answer_fn=Function.MCA_READY)
                self.expects.append(e)
            bd.running = True
            bd.records.clear()
            bd.edges.clear()

        self.expect(f"Start{_to(board)}", Function.START, target, reply,
                    lambda _b, a: isinstance(a, m.Ready) and a.reason is ReadyReason.STARTED,
                    key=(msg.target,), on_answer=started)

    # ------------------------------------------------------------------ programming
    def _program(self, msg: m.ProgramFrame, target: str | None) -> None:
        """A Program frame (``target``: the board a control frame addressed; None:
        broadcast, as the host normally sends them)."""
        if isinstance(msg, m.ProgramData):
            self._data(msg)
            return
        tr = self.transfer
        t = self.owner.timeouts
        if isinstance(msg, m.ProgramBegin):
            self._end_block()
            text = (f"BEGIN {msg.target.name.lower()}, {msg.blocks} blocks, entry "
                    f"P:{msg.entry:04X}")
            tr = self.transfer = _Transfer(self.add("all", "Program", text, {
                "op": "BEGIN", "target": msg.target, "blocks": msg.blocks,
                "entry": msg.entry}, direction=PC_TO_BOARD), msg)
            tr.boards = {b.label for b in self.boards.values() if b.prog_enabled}
            return
        if isinstance(msg, m.ProgramMeta):
            if tr is not None:
                tr.meta[msg.field] = msg.value
                tr.msg.fields.update(_meta_fields(tr.meta))
            self.add("all", "Program", "META " + _meta_text(msg), {
                "op": "META", "field": msg.field, "value": msg.value}, direction=PC_TO_BOARD)
            return
        if isinstance(msg, m.ProgramErase):
            last = msg.first_page + msg.count - 1
            self.add("all", "Program", f"ERASE {msg.space.name}: pages {msg.first_page}-"
                     f"{last} ({msg.count})", {"op": "ERASE", "space": msg.space,
                     "first_page": msg.first_page, "count": msg.count},
                     direction=PC_TO_BOARD)
            return
        if isinstance(msg, m.ProgramPrepare):
            self.add(target or "all", "Program", f"PREPARE ({msg.pages} pages)", {
                "op": "PREPARE", "pages": msg.pages}, direction=PC_TO_BOARD)
            targets = [target] if target else \
                sorted(tr.boards - tr.verified) if tr is not None else []
            for b in targets or [None]:  # type: ignore[list-item]
                self.expect(f"Program PREPARE ({msg.pages} pages)" +
                            _to(b or "all"), Function.PROGRAM, b,
                            t.reply + msg.pages * t.erase_per_page,
                            lambda _b, a: isinstance(a, m.Ready) and
                            a.reason is ReadyReason.ERASED, key=("prepare",))
            return
        if isinstance(msg, m.ProgramBlock):
            self._block(msg)
            return
        if isinstance(msg, m.ProgramEnd):
            self._end_block()
            if tr is None:
                self.add(target or "all", "Program", "END (no transfer begun in the trace)",
                         {"op": "END"}, direction=PC_TO_BOARD)
                self._expect_result(target, t.verify(0x10000))
                return
            if target is not None:
                self.add(target, "Program", "END", {"op": "END"}, direction=PC_TO_BOARD)
                self._expect_result(target, t.verify(tr.words or 0x10000))
                return
            tr.rounds += 1
            self.add("all", "Program", f"END (round {tr.rounds}): {tr.blocks_sent} BLOCK "
                     f"frames, {tr.data_frames} data frames, {tr.resent} resent", {
                         "op": "END", "round": tr.rounds, "blocks_sent": tr.blocks_sent,
                         "data_frames": tr.data_frames, "resent": tr.resent},
                     direction=PC_TO_BOARD)
            words = tr.words if tr.words is not None else 0x10000
            for b in sorted(tr.boards - tr.verified) or [None]:  # type: ignore[list-item]
                self._expect_result(b, t.verify(words))
            return
        # ABORT
        self._end_block()
        self.add(target or "all", "Program", "ABORT", {"op": "ABORT"}, direction=PC_TO_BOARD)
        if target is None:
            self.transfer = None

    def _expect_result(self, board: str | None, board_time: float) -> None:
        tr = self.transfer

        def result(b: str, a: object, _t: float) -> None:
            if isinstance(a, m.ProgramResult):
                if a.status is ResultStatus.VERIFIED and tr is not None:
                    tr.verified.add(b)
                    self.board(b).prog_enabled = False
                for e in self.expects:
                    if e.key == (Function.PROGRAM, b, "end") and not e.done:
                        e.needed = 1 + a.reports

        self.expect("Program END" + (f"{_to(board)}" if board else ""),
                    Function.PROGRAM, board, board_time,
                    lambda _b, a: isinstance(a, m.ProgramResult | m.ProgramMissing
                                             | m.ProgramPartial), key=("end",),
                    answer_fn=Function.PROGRAM_FINISHED, on_answer=result)

    def _block(self, msg: m.ProgramBlock) -> None:
        self._end_block()
        tr = self.transfer
        again = tr is not None and msg.index in tr.seen
        text = (f"BLOCK {msg.index} {msg.space.name}:{msg.address:04X}, {msg.frames} frames, "
                f"CRC 0x{msg.crc:04X}" + (" (again)" if again else ""))
        bmsg = self.add("all", "Program", text, {
            "op": "BLOCK", "index": msg.index, "space": msg.space, "address": msg.address,
            "frames": msg.frames, "crc": msg.crc, "again": again}, direction=PC_TO_BOARD)
        if tr is None:
            return
        tr.block, tr.block_msg, tr.last_slot = msg, bmsg, -1
        tr.block_slots, tr.block_resent = [], 0
        tr.blocks_sent += 1
        tr.seen.setdefault(msg.index, set())

    def _data(self, msg: m.ProgramData) -> None:
        tr = self.transfer
        block = tr.block if tr is not None else None
        if tr is None or block is None:
            self.add("all", "Program", f"data frame, slot {msg.slot}, with no block open",
                     {"op": "DATA", "slot": msg.slot}, direction=PC_TO_BOARD)
            self.violation("data-out-of-sequence", f"data frame at slot {msg.slot} with no "
                           "block open (no BLOCK frame since the transfer began)", "all")
            return
        if msg.slot >= block.frames:
            self.violation("data-out-of-sequence", f"data frame at slot {msg.slot} is outside "
                           f"block {block.index} (its BLOCK frame announced {block.frames} "
                           f"frames, slots 0-{block.frames - 1})", "all")
        elif msg.slot <= tr.last_slot:
            self.violation("data-out-of-sequence", f"data frame at slot {msg.slot} after slot "
                           f"{tr.last_slot} in block {block.index}: slots rise within a block",
                           "all")
        else:
            tr.last_slot = msg.slot
        seen = tr.seen[block.index]
        if msg.slot in seen:
            tr.resent += 1
            tr.block_resent += 1
        seen.add(msg.slot)
        tr.block_slots.append(msg.slot)
        tr.data_frames += 1
        assert tr.block_msg is not None
        tr.block_msg.frames += 1
        tr.block_msg.members.append(self.index)

    def _end_block(self) -> None:
        tr = self.transfer
        if tr is None or tr.block is None or tr.block_msg is None:
            return
        b, bmsg = tr.block, tr.block_msg
        n = len(tr.block_slots)
        missing = b.frames - len(tr.seen[b.index] & set(range(b.frames)))
        text = f": {n} data frame{'' if n == 1 else 's'}" + \
            (f" (slots {_ranges(tr.block_slots)})" if n else "")
        if tr.block_resent:
            text += f", {tr.block_resent} resent"
        if missing:
            text += f", {missing} not sent yet"
        bmsg.text += text
        bmsg.fields.update({"data_frames": n, "slots": _ranges(tr.block_slots),
                            "resent": tr.block_resent, "not_sent": missing})
        tr.block = tr.block_msg = None

    # ------------------------------------------------------------------ run time
    def _mca_request(self, board: str, target: str | None, msg: object) -> None:
        reply = self.owner.timeouts.reply
        bd = self.boards.get(board) if target else None
        if isinstance(msg, mca.MapFrame):
            self._ci_map(msg)
            return
        if isinstance(msg, mca.Alive):
            self._alive(board)
            return
        fn = int(msg.FUNCTION)  # type: ignore[attr-defined]
        label = Function(fn).label

        def acked(first: int) -> Callable[[str, object], bool]:
            return lambda _b, a: isinstance(a, mca.McaReady) and a.answers == fn and \
                a.echo[0] == first

        if isinstance(msg, mca.EdgeWrite):
            text, values = self._values_text(bd, msg.kind, msg.index, msg.data)
            self.add(board, label, text, {"kind": msg.kind, "index": msg.index,
                     "data": msg.data, "values": values}, direction=PC_TO_BOARD)
            if bd is not None and msg.kind is mca.Kind.PAR:
                self._maybe_cycle(bd, msg.index, msg.data)
            self.expect(f"{label} {msg.kind.name} {msg.index}{_to(board)}", fn, target,
                        reply, acked(msg.index), key=(msg.index, msg.data))
        elif isinstance(msg, mca.McaStart):
            self.add(board, label, msg.op.name, {"op": msg.op}, direction=PC_TO_BOARD)
            if msg.op is mca.StartOp.STOP:
                for b in self.boards.values():
                    if target is None or b.label == target:
                        self._stop_exchange(b, self.t)
            t0 = self.t

            def state(b: str, a: object, _t: float) -> None:
                if isinstance(a, mca.McaReady) and msg.op is mca.StartOp.START and \
                        a.state is mca.RunState.RUNNING:
                    self._run_exchange(self.board(b), t0)

            self.expect(f"{label} {msg.op.name}{_to(board)}", fn, target, reply,
                        acked(int(msg.op)), key=(msg.op,), on_answer=state)
        elif isinstance(msg, mca.DescrRequest):
            what = "every edge" if msg.kind is None else f"{msg.kind.name} {msg.index}"
            self.add(board, label, what, {"kind": msg.kind, "index": msg.index},
                     direction=PC_TO_BOARD)
            kind, index = msg.kind, msg.index
            have: set[tuple[mca.Kind, int]] = set()

            def described(b: str, a: object, _t: float) -> None:
                # complete with the last record the board's counts announce
                bd_ = self.board(b)
                if not isinstance(a, mca.DescrSegment) or not a.last:
                    return
                have.add((a.kind, a.index))
                wanted = {(kind, index)} if kind is not None else {
                    (k, i) for k, n in zip(mca.Kind, bd_.counts or (), strict=False)
                    for i in range(n)} if bd_.counts is not None else None
                if wanted is not None and wanted <= have:
                    for e in self.expects:
                        if e.key == (fn, target, kind, index):
                            e.done = True

            self.expect(f"{label} ({what}){_to(board)}", fn, target, reply,
                        lambda _b, a: isinstance(a, mca.DescrSegment) and
                        (kind is None or (a.kind is kind and a.index == index)),
                        needed=None, key=(kind, index), on_answer=described)
        elif isinstance(msg, mca.DumpRequest):
            last = msg.index + msg.count - 1
            self.add(board, label, f"{msg.kind.name} {msg.index}-{last} ({msg.count} values)",
                     {"kind": msg.kind, "index": msg.index, "count": msg.count},
                     direction=PC_TO_BOARD)
            kind = msg.kind
            self.expect(f"{label} {kind.name} {msg.index}-{last}{_to(board)}", fn,
                        target, reply, lambda _b, a: isinstance(a, mca.DumpValues) and
                        a.kind is kind, needed=self._dump_frames(bd, msg),
                        key=(kind, msg.index, msg.count))
        elif isinstance(msg, mca.AdminData):
            self._admin(board, target, msg, acked)
        else:
            self.add(board, label, "", direction=PC_TO_BOARD)

    def _admin(self, board: str, target: str | None, msg: mca.AdminData,
               acked: Callable[[int], Callable[[str, object], bool]]) -> None:
        bd = self.boards.get(board) if target else None
        fields_: dict[str, Any] = {"op": msg.op}
        if msg.op is mca.AdminOp.ALIVE:
            text = f"ALIVE: watchdog {msg.alive_ms} ms"
            fields_["watchdog_ms"] = msg.alive_ms
        elif msg.op is mca.AdminOp.SO_MAP:
            names = [self._edge_label(bd, mca.Kind.SO, i) for i in msg.edges
                     if i != mca.NO_EDGE]
            text = f"SO_MAP map {msg.map_no}, every {msg.period} cycles: {', '.join(names)}"
            fields_.update(map=msg.map_no, period=msg.period, edges=list(msg.edges),
                           names=names)
            self.so_msgs.pop(msg.map_no, None)
            if target is not None:
                edges = tuple(i for i in msg.edges if i != mca.NO_EDGE)
                old = self.so_maps.get(msg.map_no)
                if old is not None:
                    self._check_map_end(old, self.t)
                if msg.period == 0:
                    self.so_maps.pop(msg.map_no, None)
                else:
                    self.so_maps[msg.map_no] = _SoMap(msg.map_no, target, edges, msg.period,
                                                      self.t)
        elif msg.op is mca.AdminOp.CI_MAP:
            slots = [self._edge_label(bd, mca.Kind.CI, i) if i != mca.NO_EDGE else "-"
                     for i in msg.edges]
            text = f"CI_MAP map {msg.map_no}: slots {', '.join(slots)}"
            fields_.update(map=msg.map_no, slots=list(msg.edges), names=slots)
            self.ci_msgs.pop(msg.map_no, None)
            if target is not None:
                users = self.ci_maps.setdefault(msg.map_no, {})
                if all(i == mca.NO_EDGE for i in msg.edges):
                    users.pop(target, None)
                else:
                    users[target] = tuple(msg.edges)
        else:
            text = "CLEAR_MAPS"
            if target is not None:
                for no, so in list(self.so_maps.items()):
                    if so.board == target:
                        self._check_map_end(so, self.t)
                        del self.so_maps[no]
                for users in self.ci_maps.values():
                    users.pop(target, None)
        self.add(board, "MCA Admin Data", text, fields_, direction=PC_TO_BOARD)
        first = msg.args[0] if msg.args else 0
        self.expect(f"MCA Admin Data {msg.op.name}{_to(board)}",
                    Function.MCA_ADMIN_DATA, target, self.owner.timeouts.reply,
                    lambda _b, a: isinstance(a, mca.McaReady) and
                    a.answers == Function.MCA_ADMIN_DATA and a.echo == bytes((msg.op, first)),
                    key=(msg.op, first))

    def _alive(self, board: str) -> None:
        msg = self.alive_msg.get(board)
        last = self.alive_last.get(board)
        self.alive_last[board] = self.t
        if msg is None or last is None or self.t - last > 1.0:
            self.alive_msg[board] = self.add(board, "MCA Alive", "1 frame", {
                "frames": 1, "first_t": self.t, "last_t": self.t}, direction=PC_TO_BOARD)
            return
        msg.frames += 1
        msg.members.append(self.index)
        first = msg.fields["first_t"]
        every = (self.t - first) / (msg.frames - 1)
        msg.fields.update(frames=msg.frames, last_t=self.t, every_ms=round(every * 1000, 3))
        msg.text = f"{msg.frames} frames until {self.t:.6f} s, every {every * 1000:.3f} ms"

    def _ci_map(self, msg: mca.MapFrame) -> None:
        users = self.ci_maps.get(msg.map_no, {})
        items: list[tuple[str, _Edge | None, int, dict[str, Any]]] = []
        for board, slots in sorted(users.items(), key=lambda kv: _board_order(kv[0])):
            bd = self.boards.get(board)
            for slot, index in enumerate(slots):
                if index == mca.NO_EDGE or 2 * slot + 2 > len(msg.data):
                    continue
                raw_bytes = msg.data[2 * slot:2 * slot + 2]
                edge = self._edge(bd, mca.Kind.CI, index)
                raw = int.from_bytes(raw_bytes, "big", signed=edge.signed if edge else True)
                items.append((f"{board}:{edge.label if edge else f'CI {index}'}", edge, raw,
                              {"board": board, "slot": slot, "index": index}))
        self._periodic(f"CI map {msg.map_no}", msg, items, PC_TO_BOARD, self.ci_msgs,
                       msg.map_no)

    def _periodic(self, board: str, msg: mca.MapFrame,
                  items: list[tuple[str, _Edge | None, int, dict[str, Any]]],
                  direction: str, store: dict[int, Message], number: int) -> Message:
        """Process data summarised: one message per map (until the map is defined anew)
        with its frame count, interval, last values and their ranges (its text is
        written when the trace ends: :meth:`_summarise`)."""
        agg = store.get(number)
        if agg is None or agg.board != board:
            agg = store[number] = self.add(board, Function(msg.function).label, "", {
                "map": number, "first_t": round(self.t, 6)}, direction=direction)
            self.periodic[id(agg)] = _Periodic(agg)
        else:
            agg.frames += 1
            agg.members.append(self.index)
        state = self.periodic[id(agg)]
        state.last_t, state.items, state.data = self.t, items, msg.data
        ranges = state.ranges
        for key, edge, raw, _ in items:
            value = edge.value(raw) if edge is not None else Decimal(raw)
            lo_hi = ranges.get(key)
            if lo_hi is None:
                ranges[key] = (value, value)
            elif value < lo_hi[0] or value > lo_hi[1]:
                ranges[key] = (min(lo_hi[0], value), max(lo_hi[1], value))
        return agg

    def _summarise(self) -> None:
        """The texts and fields of the process-data summaries."""
        for state in self.periodic.values():
            agg, ranges = state.agg, state.ranges
            last: list[dict[str, Any]] = []
            texts: list[str] = []
            for key, edge, raw, extra in state.items:
                if edge is None:
                    last.append({**extra, "raw": raw})
                    text = f"{key}=raw {raw}"
                else:
                    last.append({**extra, **edge.json(raw)})
                    text = f"{key}={edge.value(raw):f}" + (f" {edge.unit}" if edge.unit
                                                           else "")
                lo, hi = ranges[key]
                if lo != hi:
                    text += f" ({lo:f}..{hi:f})"
                texts.append(text)
            agg.fields.update(frames=agg.frames, last_t=round(state.last_t, 6),
                              values=jsonable(last),
                              ranges={k: [format(lo, "f"), format(hi, "f")]
                                      for k, (lo, hi) in ranges.items()},
                              data=state.data.hex(" ").upper())
            every = ""
            if agg.frames > 1:
                period = (state.last_t - agg.fields["first_t"]) / (agg.frames - 1)
                agg.fields["every_ms"] = round(period * 1000, 3)
                every = f", every {period * 1000:.3f} ms"
            shown = "; ".join(texts) if texts else \
                f"values {state.data.hex(' ').upper()} (map not defined in the trace)"
            owner = f"board {agg.fields['board']}, " if "board" in agg.fields else ""
            agg.text = (f"{owner}{agg.frames} frame{'s' if agg.frames != 1 else ''} until "
                        f"{state.last_t:.6f} s{every}; last: {shown}")

    def _so_map(self, board_label: str, msg: mca.MapFrame) -> None:
        so = self.so_maps.get(msg.map_no)
        items: list[tuple[str, _Edge | None, int, dict[str, Any]]] = []
        if so is not None:
            bd = self.boards.get(so.board)
            edges = [self._edge(bd, mca.Kind.SO, i) for i in so.edges]
            known_edges = [e for e in edges if e is not None]
            if len(known_edges) == len(edges):
                try:
                    raws = mca.unpack_values([(e.width, e.signed) for e in known_edges],
                                             msg.data)
                except FrameError:
                    raws = []
                items = [(e.label, e, raw, {}) for e, raw in zip(known_edges, raws,
                                                                  strict=False)]
            self._check_map_gap(so)
            so.last = self.t
            agg = self.so_msgs.get(msg.map_no)
            if agg is None or agg.board != board_label:
                agg = None
            if agg is None:
                self.so_msgs.pop(msg.map_no, None)
        agg = self._periodic(board_label, msg, items, BOARD_TO_PC, self.so_msgs, msg.map_no)
        if so is not None and "board" not in agg.fields:
            agg.fields.update(board=so.board, edges=list(so.edges))

    # ------------------------------------------------------------------ SO map periods
    def _interval(self, so: _SoMap) -> float:
        bd = self.boards.get(so.board)
        cycle = bd.cycle_us if bd is not None else 1000.0
        return so.period * cycle / 1e6

    def _tolerance(self, so: _SoMap) -> float:
        return MAP_PERIODS_LATE * self._interval(so) + MAP_SLACK + self.owner.margin

    def _map_ref(self, so: _SoMap) -> float | None:
        """Since when a frame of ``so`` is due: its last frame, the exchange's start or
        the map's definition, whichever was last; None while its board does not run."""
        bd = self.boards.get(so.board)
        if bd is None or bd.exchange_since is None:
            return None
        return max(x for x in (so.last, bd.exchange_since, so.defined) if x is not None)

    def _check_map_gap(self, so: _SoMap) -> None:
        ref = self._map_ref(so)
        if ref is None or so.reported:
            return
        gap = self.t - ref
        if gap > self._tolerance(so):
            so.reported = True
            self.violation("so-map-stopped", f"SO map {so.number} of board {so.board}: no "
                           f"frame for {_ms(gap)} (since {ref:.6f} s), its period is "
                           f"{_ms(self._interval(so))}", so.board)

    def _check_map_end(self, so: _SoMap, until: float) -> None:
        ref = self._map_ref(so)
        if ref is None or so.reported:
            return
        gap = until - ref
        if gap > self._tolerance(so):
            so.reported = True
            self.violation("so-map-stopped", f"SO map {so.number} of board {so.board}: no "
                           f"frame since {ref:.6f} s, {_ms(gap)} before its exchange ended "
                           f"or the trace did; its period is {_ms(self._interval(so))}",
                           so.board, t=until)

    def _run_exchange(self, bd: _Board, since: float) -> None:
        if bd.exchange_since is None:
            bd.exchange_since = since
            for so in self.so_maps.values():
                if so.board == bd.label:
                    so.reported = False
        else:  # START again: every map starts its period afresh
            bd.exchange_since = since

    def _stop_exchange(self, bd: _Board, until: float) -> None:
        if bd.exchange_since is None:
            return
        for so in self.so_maps.values():
            if so.board == bd.label:
                self._check_map_end(so, until)
        bd.exchange_since = None

    # ------------------------------------------------------------------ edges
    def _bind(self, bd: _Board | None) -> None:
        if bd is None or bd.bound_done:
            return
        trees = self.owner.trees
        bd.bound_done = True
        if trees is None or not bd.label.isdigit():
            return
        mine = [b for b in trees.boards if b.bus == self.name]
        found = [b for b in mine if bd.serial is not None and b.spec.serial == bd.serial]
        if not found:
            found = [b for b in mine if b.spec.position == int(bd.label) - 1]
        bd.edges.clear()
        if found:
            bd.bound = found[0]
            bd.spec = self.owner.program(found[0])

    def _edge(self, bd: _Board | None, kind: mca.Kind, index: int) -> _Edge | None:
        """What is known of an edge of board ``bd`` (cached until its records or binding
        change)."""
        if bd is None:
            return None
        self._bind(bd)
        key = (kind, index)
        if key in bd.edges:
            return bd.edges[key]
        edge = bd.edges[key] = self._edge_of(bd, kind, index)
        return edge

    def _edge_of(self, bd: _Board, kind: mca.Kind, index: int) -> _Edge | None:
        unique = prefix = None
        if bd.bound is not None:
            block = bd.bound.board
            of_kind = block.of_kind(TreeKind[kind.name])
            if index < len(of_kind):
                unique, prefix = of_kind[index].unique, block.prefix
        rec = bd.records.get((kind, index))
        if rec is not None:
            return _Edge(kind, index, rec.name, unique, prefix, rec.width, rec.signed,
                         rec.exponent, rec.unit)
        if bd.spec is not None:
            edges = bd.spec.of(kind)  # type: ignore[arg-type]
            if index < len(edges):
                e = edges[index]
                return _Edge(kind, index, e.name, unique, prefix, e.width, e.signed,
                             e.exponent, e.unit)
        return None

    def _edge_label(self, bd: _Board | None, kind: mca.Kind, index: int) -> str:
        e = self._edge(bd, kind, index)
        return e.label if e is not None else f"{kind.name} {index}"

    def _values_text(self, bd: _Board | None, kind: mca.Kind, index: int, data: bytes
                     ) -> tuple[str, list[dict[str, Any]]]:
        """The values of consecutive edges from ``index`` in ``data``, as text and JSON;
        raw bytes when the edges are not known."""
        edges: list[_Edge] = []
        size = 0
        while size < len(data):
            e = self._edge(bd, kind, index + len(edges))
            if e is None:
                break
            edges.append(e)
            size += e.width
        if not edges or size != len(data):
            return (f"{kind.name} {index}: {data.hex(' ').upper()}", [])
        raws = mca.unpack_values([(e.width, e.signed) for e in edges], data)
        return (f"{kind.name} {index}: " + ", ".join(e.text(r) for e, r in
                                                    zip(edges, raws, strict=True)),
                [e.json(r) for e, r in zip(edges, raws, strict=True)])

    def _dump_frames(self, bd: _Board | None, msg: mca.DumpRequest) -> int | None:
        """MCA DSP CI frames that answer ``msg`` (a new frame when the next value would
        pass 6 bytes); None when the widths are not known."""
        frames, size = 0, 0
        for i in range(msg.index, msg.index + msg.count):
            e = self._edge(bd, msg.kind, i)
            if e is None:
                return None
            if frames == 0 or size + e.width > 6:
                frames, size = frames + 1, 0
            size += e.width
        return frames or None

    def _maybe_cycle(self, bd: _Board, index: int, data: bytes) -> None:
        """A PAR write that sets the program's cycle time changes its SO map periods."""
        pos = 0
        i = index
        while pos < len(data):
            e = self._edge(bd, mca.Kind.PAR, i)
            if e is None:
                return
            if e.name in self.owner.cycle_edges and e.unit in ("ms", "us"):
                raw = int.from_bytes(data[pos:pos + e.width], "big", signed=e.signed)
                us = float(e.value(raw)) * (1000 if e.unit == "ms" else 1)
                if us > 0:
                    bd.cycle_us = us
            pos += e.width
            i += 1

    # ------------------------------------------------------------------ answers
    def _from_board(self, board: str, address: Address, message: object) -> None:
        if isinstance(message, mca.MapFrame):
            self._so_map(board, message)
            return
        bd = self.board(board)
        fn = Function(message.FUNCTION)  # type: ignore[attr-defined]
        if isinstance(message, m.Error):
            self._error(bd, message)
        elif isinstance(message, m.InitAck):
            self._init_ack(bd, message)
        elif isinstance(message, m.InfoFrame):
            self._info(bd, message)
        elif isinstance(message, m.TextReport):
            self._text(bd, message)
        elif isinstance(message, mca.DescrSegment):
            self._segment(bd, message)
        else:
            text, fields_ = self._describe(bd, message)
            self.add(board, fn.label, text, fields_, direction=BOARD_TO_PC)
            itself = bd.resets_itself and isinstance(message, m.Ready) and \
                message.reason is ReadyReason.BOOT
            self._state_of(bd, message)
            if not itself:  # after VERSION_MISMATCH the board resets unasked
                self.answer(board, message)

    def _state_of(self, bd: _Board, message: object) -> None:
        if isinstance(message, m.Ready):
            if message.reason is ReadyReason.BOOT:
                bd.running = False
                bd.prog_enabled = False
                self._stop_exchange(bd, self.t)
                bd.resets_itself = False
        elif isinstance(message, mca.McaReady):
            bd.running = True
            bd.counts = (message.ci, message.so, message.par)
            if message.state is mca.RunState.RUNNING:
                self._run_exchange(bd, bd.exchange_since or self.t)
            else:
                self._stop_exchange(bd, self.t)

    def _error(self, bd: _Board, err: m.Error) -> None:
        about = {0xFF: "no frame", mca.PROCESS_DATA | Function.MCA_CONTROLLER_INPUT:
                 "a CI map frame"}.get(err.function)
        if about is None and err.function <= 31:
            about = f"{Function(err.function).label}" if err.function <= 27 else \
                f"function {err.function}"
        text = f"{err.code.name}: {err.describe()}"
        if about:
            text += f" [about: {about}]"
        self.add(bd.label, "Error", text, {"code": err.code, "function": err.function,
                 "detail": err.detail}, direction=BOARD_TO_PC)
        if err.code is ErrorCode.WATCHDOG:
            self._stop_exchange(bd, self.t)
        elif err.code in (ErrorCode.INCOMPATIBLE, ErrorCode.VERSION_MISMATCH):
            bd.running = False
            bd.resets_itself = err.code is ErrorCode.VERSION_MISMATCH
            for e in self.expects:  # the program is not up: it announces nothing
                if not e.done and e.key == (Function.START, bd.label, "up"):
                    e.got, e.done = 1, True
        elif err.code is ErrorCode.BAD_MAP and err.function == Function.MCA_ADMIN_DATA:
            so = self.so_maps.get(err.detail)
            if so is not None and so.board == bd.label:
                del self.so_maps[err.detail]
        self.answer(bd.label, err, error=err)

    def _init_ack(self, bd: _Board, ack: m.InitAck) -> None:
        version = f"{ack.bootloader_version >> 4}.{ack.bootloader_version & 15}"
        text = (f"{ack.kind.name}: seq ID {ack.seq_id or '-'}, fixed ID {ack.fixed_id or '-'}, "
                f"serial 0x{ack.serial:08X}, bootloader {version}")
        self.add(bd.label, "Init Ack", text, {"kind": ack.kind, "seq_id": ack.seq_id,
                 "fixed_id": ack.fixed_id, "bootloader": version,
                 "serial": f"0x{ack.serial:08X}"}, direction=BOARD_TO_PC)
        if ack.kind is InitAckKind.ASSIGNED and ack.seq_id:
            self.chain.append(ack.seq_id)
        if ack.seq_id:
            owner = self.board(str(ack.seq_id))
            if owner.serial != ack.serial:
                owner.bound_done = False  # bind it again, now by its serial
            owner.serial = ack.serial
            if ack.kind is InitAckKind.ASSIGNED:
                owner.running = False if owner.running is None else owner.running
        e = self.answer(bd.label, ack)
        if e is not None and e.init_number is not None:
            for missed in self.init_missed.pop(e.init_number, []):
                self.violation("unanswered", f"{missed.what} was not answered (asked again "
                               "and then answered)", str(e.init_number), t=missed.t,
                               index=missed.index)

    def _info(self, bd: _Board, frame: m.InfoFrame) -> None:
        if frame.index == 0 or bd.info is None:
            self._flush_info(bd)
            msg = self.add(bd.label, "Info", "(incomplete)", {}, direction=BOARD_TO_PC)
            msg.frames = 0
            msg.members.clear()
            bd.info = (msg, {})
        msg, bodies = bd.info
        if frame.index in bodies:  # a new record without its frame 0
            self._flush_info(bd)
            msg = self.add(bd.label, "Info", "(incomplete)", {}, direction=BOARD_TO_PC)
            msg.frames = 0
            msg.members.clear()
            bd.info = (msg, bodies := {})
        bodies[frame.index] = frame.body
        msg.frames += 1
        msg.members.append(self.index)
        self.answer(bd.label, frame)
        if len(bodies) == INFO_FRAMES:
            bd.info = None
            try:
                info = BoardInfo.from_frames(bodies)
            except FrameError as err:
                msg.text = f"malformed record: {err}"
                self.violation("malformed", f"Info record: {err.field}: {err.message}",
                               bd.label)
                return
            msg.text, msg.fields = _info_text(info), jsonable(_info_fields(info))
            bd.serial = info.serial
            bd.running = info.state.name.startswith("RUNNING")

    def _flush_info(self, bd: _Board) -> None:
        if bd.info is None:
            return
        msg, bodies = bd.info
        lacking = [i for i in range(INFO_FRAMES) if i not in bodies]
        msg.text = f"incomplete record: frames {_ranges(lacking)} missing"
        msg.fields = {"missing": lacking}
        bd.info = None

    def _text(self, bd: _Board, piece: m.TextReport) -> None:
        if piece.index == 0 or bd.text is None:
            self._flush_text(bd)
            msg = self.add(bd.label, "Report 2", "", {}, direction=BOARD_TO_PC)
            msg.frames = 0
            msg.members.clear()
            bd.text = (msg, [])
        msg, pieces = bd.text
        if piece.index != len(pieces):
            pieces.append(b"\x00?")  # a gap: shown, the text goes on
        pieces.append(piece.text)
        msg.frames += 1
        msg.members.append(self.index)
        text = b"".join(p for p in pieces if p != b"\x00?").decode("latin-1")
        gaps = sum(1 for p in pieces if p == b"\x00?")
        msg.text = f"text: {text!r}" + (" (incomplete: pieces missing)" if gaps else
                                        "" if piece.last else " (more to come)")
        msg.fields = {"text": text, "complete": piece.last and not gaps}
        self.answer(bd.label, piece)
        if piece.last:
            bd.text = None

    def _flush_text(self, bd: _Board) -> None:
        if bd.text is not None:
            msg, _ = bd.text
            msg.text = msg.text.replace(" (more to come)", " (incomplete: the last piece "
                                        "did not arrive)")
            bd.text = None

    def _segment(self, bd: _Board, seg: mca.DescrSegment) -> None:
        key = (seg.kind, seg.index)
        entry = bd.segments.get(key)
        if entry is None or (seg.segment == 0 and 0 in entry[1]):
            msg = self.add(bd.label, "MCA DumpIO Descr", f"{seg.kind.name} {seg.index}: "
                           "(incomplete record)", {"kind": seg.kind, "index": seg.index},
                           direction=BOARD_TO_PC)
            msg.frames = 0
            msg.members.clear()
            entry = bd.segments[key] = (msg, {})
        msg, parts = entry
        parts[seg.segment] = seg.data
        msg.frames += 1
        msg.members.append(self.index)
        self.answer(bd.label, seg)
        if seg.last and all(i in parts for i in range(seg.segment + 1)):
            del bd.segments[key]
            try:
                rec = mca.EdgeRecord.decode(b"".join(parts[i] for i in range(seg.segment + 1)))
            except FrameError as err:
                msg.text = f"{seg.kind.name} {seg.index}: malformed record: {err}"
                self.violation("malformed", f"MCA DumpIO Descr {seg.kind.name} {seg.index}: "
                               f"{err.field}: {err.message}", bd.label)
                return
            bd.records[key] = rec
            bd.edges.pop(key, None)
            edge = self._edge(bd, seg.kind, seg.index)
            name = rec.name + (f" = {edge.unique}" if edge is not None and edge.unique
                               and edge.unique != rec.name else "")
            lo, hi = (Decimal(x).scaleb(rec.exponent) for x in (rec.minimum, rec.maximum))
            msg.text = (f"{seg.kind.name} {seg.index} '{name}': {'s' if rec.signed else 'u'}"
                        f"{rec.width}, exponent {rec.exponent}, {lo:f}..{hi:f}"
                        + (f" {rec.unit}" if rec.unit else ""))
            msg.fields = jsonable({"kind": seg.kind, "index": seg.index, "name": rec.name,
                                   "unique": edge.unique if edge else None,
                                   "width": rec.width, "signed": rec.signed,
                                   "exponent": rec.exponent, "minimum": rec.minimum,
                                   "maximum": rec.maximum, "unit": rec.unit})

    def _flush_partial(self, bd: _Board) -> None:
        self._flush_info(bd)
        self._flush_text(bd)

    def _describe(self, bd: _Board, message: object) -> tuple[str, dict[str, Any]]:
        """Text and fields of a single-frame board message."""
        if isinstance(message, m.Ready):
            return _ready_text(message), {"reason": message.reason, "state": message.state,
                                          "value16": message.value16,
                                          "value32": message.value32}
        if isinstance(message, m.ProgramResult):
            text = (f"RESULT {message.status.name}: {message.status.text}, ProgID "
                    f"0x{message.progid:08X}")
            if message.reports:
                text += f", {message.reports} reports follow"
            return text, {"kind": "RESULT", "status": message.status,
                          "progid": f"0x{message.progid:08X}", "reports": message.reports}
        if isinstance(message, m.ProgramMissing):
            last = message.first + message.count - 1
            return (f"MISSING blocks {message.first}-{last} ({message.count})",
                    {"kind": "MISSING", "first": message.first, "count": message.count})
        if isinstance(message, m.ProgramPartial):
            last = message.first + message.count - 1
            return (f"PARTIAL block {message.block}: slots {message.first}-{last}",
                    {"kind": "PARTIAL", "block": message.block, "first": message.first,
                     "count": message.count})
        if isinstance(message, m.StatusReport):
            return (f"STATUS {message.state.name}, pins 0x{message.pins:X}, LEDs "
                    f"0x{message.leds:X}, TEC {message.tec}, REC {message.rec}, seq ID "
                    f"{message.seq_id}, overruns {message.overruns}", jsonable(message))
        if isinstance(message, m.MemoryReport):
            words = " ".join(f"{w:04X}" for w in message.words)
            return f"MEMORY {message.address:04X}: {words}", jsonable(message)
        if isinstance(message, m.AppReport):
            try:
                app = mca.AppStatus.decode(message.data)
            except FrameError:
                return f"APPLICATION {message.data.hex(' ').upper()}", {"data": message.data}
            return (f"APPLICATION {app.state.name}, load {app.load_permille / 10:.1f} %, cycle "
                    f"{app.cycle_us} us, {app.overruns} overruns, flags 0x{app.flags:02X}",
                    jsonable(app))
        if isinstance(message, mca.McaReady):
            answers = "unsolicited (the program is up)" if message.answers == \
                Function.MCA_READY else (Function(message.answers).label
                                         if message.answers <= 27 else str(message.answers))
            text = (f"{message.state.name}, answers {answers}, echo "
                    f"{message.echo.hex(' ').upper()}, edges {message.ci} CI / {message.so} "
                    f"SO / {message.par} PAR")
            flags = [n for bit, n in ((mca.FLAG_OVERRUN, "overrun"),
                                      (mca.FLAG_LATCHED_BY_WATCHDOG, "latched"))
                     if message.flags & bit]
            if flags:
                text += f", flags {'+'.join(flags)}"
            return text, jsonable(message)
        if isinstance(message, mca.DumpValues):
            text, values = self._values_text(bd, message.kind, message.index, message.data)
            return text, {"kind": message.kind.name, "index": message.index,
                          "data": jsonable(message.data), "values": values}
        return "", jsonable(message)


def _meta_text(msg: m.ProgramMeta) -> str:
    if msg.field == MetaField.PROGID:
        return f"ProgID 0x{int.from_bytes(msg.value, 'big'):08X}"
    if msg.field == MetaField.SIZE:
        return f"size {int.from_bytes(msg.value, 'big')} words"
    if msg.field == MetaField.DATE:
        value = int.from_bytes(msg.value, "big")
        return f"date {decode_date(value).isoformat()}"
    text = msg.value.rstrip(b"\0").decode("latin-1")
    first = 4 * (msg.field - MetaField.NAME_0)
    return f"name[{first}:{first + 4}] {text!r}"


def _meta_fields(meta: dict[int, bytes]) -> dict[str, Any]:
    """What the META frames so far say: ProgID, size, date, name."""
    out: dict[str, Any] = {}
    if MetaField.PROGID in meta:
        out["progid"] = f"0x{int.from_bytes(meta[MetaField.PROGID], 'big'):08X}"
    if MetaField.SIZE in meta:
        out["size_words"] = int.from_bytes(meta[MetaField.SIZE], "big")
    if MetaField.DATE in meta:
        out["date"] = decode_date(int.from_bytes(meta[MetaField.DATE], "big")).isoformat()
    parts = [meta.get(MetaField.NAME_0 + i) for i in range(7)]
    if any(p is not None for p in parts):
        out["name"] = b"".join(p or b"" for p in parts).rstrip(b"\0").decode("latin-1")
    return out


def _ready_text(r: m.Ready) -> str:
    text = f"{r.reason.name} ({r.state.name})"
    if r.reason is ReadyReason.BOOT:
        text += f", serial 0x{r.value32:08X}"
    elif r.reason is ReadyReason.ERASED:
        text += f": receive ring {r.value16} frames, {r.value32} us per data frame"
    elif r.reason in (ReadyReason.PAUSE, ReadyReason.RESUME):
        text += f": {r.value16} frames buffered"
    elif r.reason is ReadyReason.STARTED:
        try:
            text += f": {Target(r.value16).name.lower()}"
        except ValueError:
            text += f": target {r.value16}"
    elif r.reason is ReadyReason.STATUS:
        try:
            op = StatusOp(r.value16 >> 8).name
        except ValueError:
            op = str(r.value16 >> 8)
        text += f": {op} {r.value16 & 0xFF}"
    return text


def _info_fields(info: BoardInfo) -> dict[str, Any]:
    fpga = info.fpga
    return {
        "state": info.state, "autostart": info.autostart, "prog_enable": info.prog_enable,
        "flash_valid": info.flash_valid, "extram_valid": info.extram_valid,
        "seq_id": info.seq_id, "fixed_id": info.fixed_id,
        "bootloader": f"{info.bootloader_version[0]}.{info.bootloader_version[1]}",
        "progid": f"0x{info.progid:08X}", "size_words": info.size_words,
        "programmed": info.programmed, "serial": f"0x{info.serial:08X}",
        "entry": f"P:{info.entry:04X}", "target": info.target, "name": info.name,
        "fpga": None if fpga is None else {"board_id": fpga.board_id, "app_id": fpga.app_id,
                                           "version": fpga.version},
        "measured_board_id": info.measured_board_id, "fpga_neutral": info.fpga_neutral,
        "descriptor": None if info.descriptor is None else {
            "board_id": info.descriptor.board_id, "app_id": info.descriptor.app_id,
            "fpga": f"{info.descriptor.fpga_major}.{info.descriptor.fpga_minor}",
            "version": f"{info.descriptor.version[0]}.{info.descriptor.version[1]}"},
        "descriptor_corrupt": info.descriptor_corrupt,
    }


def _info_text(info: BoardInfo) -> str:
    flags = [name for on, name in ((info.autostart, "AutoStart"),
                                   (info.prog_enable, "ProgEnable"),
                                   (info.flash_valid, "flash valid"),
                                   (info.extram_valid, "ExtRAM loaded")) if on]
    program = (f"'{info.name}' ProgID 0x{info.progid:08X}, {info.size_words} words"
               if info.name or info.progid else "no program")
    fpga = info.fpga
    parts = [f"{info.state.name}", program, f"serial 0x{info.serial:08X}",
             f"seq ID {info.seq_id or '-'}, fixed ID {info.fixed_id or '-'}",
             "flags " + (", ".join(flags) if flags else "none"),
             "FPGA " + (f"Board-ID {fpga.board_id} App-ID {fpga.app_id} v{fpga.version}"
                        if fpga else "unreadable")
             + f", plug-on Board-ID {info.measured_board_id}"
             + (" (NEUTRAL)" if info.fpga_neutral else "")]
    if info.programmed is not None:
        parts.append(f"programmed {info.programmed.isoformat()}")
    return "; ".join(parts)


class _Decoder:
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


def decode_frames(frames: Iterable[can.Message], trees: RobotTrees | None = None, *,
                  bitrate: int | None = None, margin: float = DEFAULT_MARGIN,
                  timeouts: Timeouts = DEFAULT) -> Conversation:
    """Decode a trace into its :class:`Conversation`.

    ``frames`` in trace order (a python-can reader, or a list); each bus's frames are
    read in timestamp order (a recording may write a sent frame after a received one
    that came later), the trace order breaking ties.  ``trees`` (:func:`load_trees`)
    names values and binds boards to their programs; ``bitrate`` (default: the
    topology's bus bitrate, else 1 Mbit/s) and ``margin`` (seconds) go into every answer
    deadline, with ``timeouts`` (the boards' times, TIMEOUTS)."""
    decoder = _Decoder(trees, bitrate, margin, timeouts)
    listed = list(frames)
    start = min((f.timestamp for f in listed), default=None)
    per_bus: dict[str, list[tuple[int, can.Message]]] = {}
    names = channel_names({f.channel for f in listed},
                          [b.name for b in trees.topology.buses] if trees is not None else [])
    for i, f in enumerate(listed):
        per_bus.setdefault(names[f.channel], []).append((i, f))
    buses: list[BusConversation] = []
    for name, items in per_bus.items():
        _check_time_base(decoder, name, items, max(margin, BACKWARDS_S), start)
        items.sort(key=lambda x: (x[1].timestamp, x[0]))
        bus = _BusDecoder(decoder, name)
        assert start is not None
        for i, f in items:
            bus.feed(i, f, f.timestamp - start)
        bus.finish()
        buses.append(bus.conv)
    decoder.violations.sort(key=lambda v: (v.index, v.rule))
    return Conversation(buses, decoder.violations, len(listed), start)


def _check_time_base(decoder: _Decoder, bus: str, items: list[tuple[int, can.Message]],
                     margin: float, start: float | None) -> None:
    """One ``time-backwards`` violation for a bus whose frames, in the order they were
    written, run back by more than ``margin`` (a recording keeps one clock: a sent frame
    may be written a little after a received one that came later, no more)."""
    latest = -math.inf
    back = 0
    first: tuple[int, can.Message, float] | None = None
    for i, f in items:
        if f.timestamp < latest - margin:
            back += 1
            if first is None:
                first = (i, f, latest - f.timestamp)
        latest = max(latest, f.timestamp)
    if first is not None:
        i, f, by = first
        decoder.violations.append(Violation(
            f.timestamp - (start or 0.0), i, bus, "-", "time-backwards",
            f"frame {i} is stamped {by:.6f} s before a frame written before it"
            + (f" ({back} such frames)" if back > 1 else "")
            + "; the trace mixes time bases"))


# ============================================================================ input
def read_trace(path: str | Path) -> list[can.Message]:
    """Every frame of a python-can log (the format by the extension: .asc, .blf, .log,
    .csv, .trc, .db, ...); InputError naming the file when it cannot be read.  Channel
    numbers count from 0 as python-can's writers take them (a .trc file's PEAK channel 1
    is channel 0)."""
    file = str(path)
    if not Path(file).is_file():
        raise InputError("no such file" if not Path(file).exists() else "not a file",
                         file=file)
    try:
        with can.LogReader(file) as reader:
            frames = list(reader)
    except InputError:
        raise
    except Exception as err:  # python-can raises anything from ValueError to struct.error
        text = str(err).strip().splitlines()
        reason = text[0] if text else type(err).__name__
        raise InputError(f"cannot read as a CAN trace: {reason}", file=file) from None
    if file.lower().endswith((".trc", ".trc.gz")):
        # PEAK counts channels from 1: python-can writes channel n as n + 1 and reads the
        # number as it stands; back to python-can's count (CAN0 is channel 0)
        for f in frames:
            if isinstance(f.channel, int) and f.channel > 0:
                f.channel -= 1
    return frames


def load_trees(args: Sequence[str]) -> RobotTrees:
    """The attribute trees of ``args``: one robot (a bundled topology name or a topology
    file whose boards name their trees) and/or tree files (``*.tree``), which replace the
    robot's blocks of the same Prefix; InputError (TreeError, TopologyError) otherwise."""
    from ucom_tools.config import topology as topo
    from ucom_tools.ops.remote import robot_trees
    from ucom_tools.ops.robot import ConnectSpec, Robot

    files = [a for a in args if a.endswith(".tree")]
    robots = [a for a in args if not a.endswith(".tree")]
    if len(robots) != 1:
        raise InputError("give one robot (a bundled topology such as armar3, or a topology "
                         "file naming its boards' trees)" + (f", not {len(robots)}: "
                                                             f"{', '.join(robots)}"
                                                             if robots else ""),
                         key="--trees")
    topology = topo.load(robots[0])
    return robot_trees(Robot(ConnectSpec(topology=robots[0]), {}, topology), files)


__all__ = ["BOARD_TO_PC", "DEFAULT_BUS", "PC_TO_BOARD", "RULES", "BusConversation",
           "Conversation", "Message", "Violation", "bus_name", "decode_frames", "jsonable",
           "load_trees", "raw_text", "read_trace"]
