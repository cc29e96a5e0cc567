"""The result of decoding a trace: the messages per bus and board, the protocol
violations found and the rules they name; rendered as text or JSON."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

PC_TO_BOARD = "PC -> board"
BOARD_TO_PC = "board -> PC"

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


