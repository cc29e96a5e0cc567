"""The console's per-board operations (options 1, 3, 4, 7-17, 21) on an open robot.

Every function returns rows of plain result dataclasses, one per (bus, board); those
that address boards by seq ID raise :class:`NotInitialised` (naming the bus) when no board
of a bus has one yet, and the caller says what to do about it (the command line and the
console word it their ways).  An operation on every board of a bus whose topology is known
also returns a failed row for each expected board that did not answer.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from ucom_tools.errors import InputError, UcomError, UcomTimeoutError
from ucom_tools.ops.enumerate import describe_missing, missing_expected
from ucom_tools.ops.robot import BusHandle, Robot
from ucom_tools.protocol.bootloader import Reply
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import BoardState, StatusOp, Target
from ucom_tools.wire.ids import ALL, Address, IdType
from ucom_tools.wire.info import BoardInfo


class NotInitialised(UcomError):
    """No board of ``bus`` has a seq ID: the init chain has not run since power-on."""

    def __init__(self, bus: str) -> None:
        super().__init__(f"{bus}: no board has a seq ID yet")
        self.bus = bus


@dataclass(frozen=True)
class BoardRef:
    """Which boards a command is for: ``all``, ``N`` (seq ID), ``FN`` (fixed ID), with an
    optional ``BUS:`` prefix."""

    bus: str | None
    address: Address

    @property
    def is_all(self) -> bool:
        return self.address.is_broadcast

    def __str__(self) -> str:
        return (f"{self.bus}:" if self.bus else "") + str(self.address)


_REF = re.compile(r"^(?:(?P<bus>[^:\s]+):)?(?P<id>all|[fF]?\d{1,2})$")


def parse_ref(text: str, *, allow_all: bool = True, key: str = "BOARD") -> BoardRef:
    """The boards ``text`` names; :class:`~ucom_tools.errors.InputError` under ``key`` (the
    argument's name) when it names none."""
    m_ = _REF.match(text.strip())
    if not m_:
        raise InputError(f"{text!r} is not a board: expected a seq ID 1-31, F1-F31 for a fixed"
                         " ID" + (", or all" if allow_all else "") + ", optionally BUS:..",
                         key=key)
    ident = m_.group("id").lower()
    if ident == "all":
        if not allow_all:
            raise InputError("this command takes one board, not all", key=key)
        return BoardRef(m_.group("bus"), ALL)
    fixed = ident.startswith("f")
    number = int(ident[1:] if fixed else ident)
    if not 1 <= number <= 31:
        raise InputError(f"board number {number} is out of range 1-31", key=key)
    return BoardRef(m_.group("bus"), Address(IdType.FIXED if fixed else IdType.SEQUENTIAL,
                                             number))


@dataclass(frozen=True)
class Row:
    """One board's answer to a command; ``address`` None for an expected board that did not
    answer (``placement`` names it)."""

    bus: str
    address: Address | None
    ok: bool
    detail: str
    state: BoardState | None = None
    info: BoardInfo | None = None
    serial: int | None = None
    reports: tuple[str, ...] = field(default=())
    placement: str | None = None


def _buses(robot: Robot, ref: BoardRef | None, bus: str | None) -> list[BusHandle]:
    name = (ref.bus if ref is not None else None) or bus
    return robot.select(name)


def _require_init(h: BusHandle, ref: BoardRef) -> None:
    """Raise :class:`NotInitialised` when no board of the bus has a seq ID."""
    if ref.address.id_type is IdType.FIXED:
        return
    if h.client.info_many(ALL):
        return
    raise NotInitialised(h.name)


def _missing(h: BusHandle, ref: BoardRef) -> Row:
    _require_init(h, ref)
    return Row(h.name, ref.address, False, f"no board with {_label(ref.address)} on {h.name}")


def _absent(h: BusHandle, rows: list[Row]) -> list[Row]:
    """Failed rows for the boards the topology expects on ``h`` that are not among
    ``rows`` (only once some board answered: before init no board can)."""
    if not rows or h.expected is None:
        return []
    expected = len(h.expected.boards)
    answered = [r for r in rows if r.address is not None]
    return [Row(h.name, None, False, describe_missing(h.name, spec, expected),
                placement=spec.placement)
            for spec in missing_expected(h, [r.serial for r in answered], len(answered))]


def _label(a: Address) -> str:
    return f"fixed ID {a.number}" if a.id_type is IdType.FIXED else f"seq ID {a.number}"


def _reply_row(h: BusHandle, r: Reply) -> Row:
    msg = r.message
    if isinstance(msg, m.Ready):
        return Row(h.name, r.address, True, "ok", msg.state, reports=r.reports)
    return Row(h.name, r.address, False, msg.describe(), reports=r.reports)


# ----------------------------------------------------------------------------- options
def reset(robot: Robot, ref: BoardRef | None = None, *, bus: str | None = None,
          clear_autostart: bool = False) -> list[Row]:
    """Options 1, 9 and 21: reset, and list who answered (= who is alive)."""
    rows = []
    target = ref or BoardRef(None, ALL)
    for h in _buses(robot, ref, bus):
        replies = h.client.reset(target.address, clear_autostart=clear_autostart)
        if not replies and not target.is_all:
            rows.append(_missing(h, target))
            continue
        bus_rows = []
        for r in replies:
            assert isinstance(r.message, m.Ready)
            bus_rows.append(Row(h.name, r.address, True, "reset", r.message.state,
                                serial=r.message.value32))
        rows += bus_rows + (_absent(h, bus_rows) if target.is_all else [])
    return rows


def info(robot: Robot, ref: BoardRef, *, bus: str | None = None) -> list[Row]:
    """Option 3 (one board) and 13 (Count: every board, ``ref`` = all)."""
    rows = []
    for h in _buses(robot, ref, bus):
        infos = h.client.info_many(ref.address)
        if not infos and not ref.is_all:
            rows.append(_missing(h, ref))
        bus_rows = [Row(h.name, address, True, "ok", inf.state, inf, inf.serial)
                    for address, inf in sorted(infos.items(), key=lambda kv: kv[0].number)]
        rows += bus_rows + (_absent(h, bus_rows) if ref.is_all else [])
    return rows


def set_status(robot: Robot, ref: BoardRef, op: StatusOp, value: int, *,
               bus: str | None = None) -> list[Row]:
    """Options 4 (ProgEnable), 8 (AutoStart), 10/11 (init pins), 12 (seq ID)."""
    rows = []
    for h in _buses(robot, ref, bus):
        replies = h.client.set_status(ref.address, op, value)
        if not replies:
            if ref.is_all:
                _require_init(h, ref)
            else:
                rows.append(_missing(h, ref))
            continue
        bus_rows = [_reply_row(h, r) for r in replies]
        rows += bus_rows + (_absent(h, bus_rows) if ref.is_all else [])
    return rows


def set_seqid(robot: Robot, ref: BoardRef, new: int, *, bus: str | None = None
              ) -> list[Row]:
    """Option 12: give the board with seq ID ``ref`` the seq ID ``new``.

    Refused (:class:`~ucom_tools.errors.InputError`, nothing sent) when another board of
    that bus already holds ``new``: two boards with one seq ID would answer with the same
    identifiers and drop out of every list.  The change is confirmed by the board's Info
    at the new number (its serial), so a lost answer is not a failure."""
    if ref.is_all or ref.address.id_type is not IdType.SEQUENTIAL:
        raise InputError("SetSeqID changes the seq ID of one board: give its seq ID",
                         key="OLD")
    rows = []
    for h in _buses(robot, ref, bus):
        infos = h.client.info_many(ALL)
        old = infos.get(ref.address)
        if old is None:
            rows.append(_missing(h, ref))
            continue
        if new == ref.address.number:
            rows.append(Row(h.name, ref.address, True, "already has this seq ID", old.state,
                            old, old.serial))
            continue
        holder = infos.get(Address(IdType.SEQUENTIAL, new))
        if holder is not None:
            raise InputError(
                f"seq ID {new} is already held by the board with serial "
                f"0x{holder.serial:08X} on {h.name}; nothing was sent. Two boards with one "
                "seq ID would answer with the same identifiers; give another number, or "
                "move that board first", key="NEW")
        replies = h.client.set_status(ref.address, StatusOp.SEQ_ID, new)
        if replies:
            rows += [_reply_row(h, r) for r in replies]
            continue
        try:
            now = h.client.info(Address(IdType.SEQUENTIAL, new))
        except UcomTimeoutError:
            rows.append(Row(h.name, ref.address, False, f"did not take seq ID {new}",
                            old.state, old, old.serial))
            continue
        ok = now.serial == old.serial
        rows.append(Row(h.name, Address(IdType.SEQUENTIAL, new), ok,
                        "ok" if ok else "another board answers at the new seq ID",
                        now.state, now, now.serial))
    return rows


def start(robot: Robot, ref: BoardRef, target: Target = Target.FLASH, *,
          bus: str | None = None) -> list[Row]:
    """Option 7: start the program in flash (or ExtRAM)."""
    rows = []
    for h in _buses(robot, ref, bus):
        results = h.client.start(ref.address, target)
        if not results:
            if ref.is_all:
                _require_init(h, ref)
            else:
                rows.append(_missing(h, ref))
            continue
        bus_rows = []
        for r in results:
            detail = "; ".join(e.describe() for e in r.errors) if r.errors else (
                "started" if r.started else "did not start")
            bus_rows.append(Row(h.name, r.address, r.ok, detail, r.state, reports=r.reports))
        rows += bus_rows + (_absent(h, bus_rows) if ref.is_all else [])
    return rows


@dataclass(frozen=True)
class ProbeResult:
    """Options 14/15 on one bus: who answered as first (last) board."""

    bus: str
    last: bool
    answers: tuple[m.InitAck, ...]
    info: BoardInfo | None

    @property
    def broken(self) -> bool:
        return len(self.answers) > 1


def probe(robot: Robot, *, last: bool = False, bus: str | None = None) -> list[ProbeResult]:
    out = []
    for h in robot.select(bus):
        answers = h.client.probe(last=last)
        inf = None
        if len(answers) == 1 and answers[0].seq_id:
            try:
                inf = h.client.info(Address(IdType.SEQUENTIAL, answers[0].seq_id))
            except UcomTimeoutError:
                inf = None
        out.append(ProbeResult(h.name, last, tuple(answers), inf))
    return out


def dsp_list(robot: Robot, *, bus: str | None = None) -> list[Row]:
    """Options 16 + 17: build and print the list of active boards (Info broadcast)."""
    return info(robot, BoardRef(None, ALL), bus=bus)


def board_status(robot: Robot, ref: BoardRef, *, bus: str | None = None) -> list[
        tuple[str, m.StatusReport]]:
    out = []
    for h in _buses(robot, ref, bus):
        out.append((h.name, h.client.status(ref.address)))
    return out
