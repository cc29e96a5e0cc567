"""Init-chain enumeration with wiring diagnostics (console options 2, 14, 15, 16).

Runs the init chain on a bus, reads every board's Info, probes the init line, compares
with the boards the topology expects and explains differences: where the init line is
most likely cut, which board is unpowered, which fixed IDs clash, and which LEDs to look
at (dissertation B.2.3).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from ucom_tools.config.topology import BoardSpec, BusSpec
from ucom_tools.ops.robot import BusHandle
from ucom_tools.protocol.bootloader import ChainAck, InitResult
from ucom_tools.wire.ids import ALL, seq
from ucom_tools.wire.info import BoardInfo


@dataclass(frozen=True)
class FoundBoard:
    seq_id: int
    serial: int
    fixed_id: int
    bootloader_version: int
    position: int | None = None
    """1-based position in the expected chain (when the topology knows the serial)."""
    placement: str | None = None
    board: str | None = None
    info: BoardInfo | None = None
    duplicate: bool = False


@dataclass(frozen=True)
class Diagnosis:
    kind: str
    message: str
    leds: str = ""

    def text(self) -> str:
        return self.message + (f" LEDs: {self.leds}" if self.leds else "")


@dataclass(frozen=True)
class BusEnumeration:
    bus: str
    boards: tuple[FoundBoard, ...]
    expected: int | None
    first_answers: int
    diagnosis: tuple[Diagnosis, ...]

    @property
    def found(self) -> int:
        return len(self.boards)

    @property
    def ok(self) -> bool:
        return not self.diagnosis


def enumerate_bus(handle: BusHandle, *, with_info: bool = True) -> BusEnumeration:
    """Run the init chain on one bus and diagnose the result."""
    client = handle.client
    result = client.init_chain()
    dups = result.duplicates()
    numbered = [seq(n) for n in result.numbers if n not in dups]
    infos = client.info_many(ALL, expect=numbered) if with_info and result.acks else {}
    firsts = client.probe() if result.acks else []
    expected = handle.expected
    by_serial = expected_positions(handle)
    seen: set[int] = set()
    boards = []
    for ack in result.acks:
        if ack.serial in seen:
            continue
        seen.add(ack.serial)
        info = None if ack.seq_id in dups else infos.get(seq(ack.seq_id))
        if info is not None and info.serial != ack.serial:
            info = None
        pos = by_serial.get(ack.serial)
        if pos is None and not by_serial and expected is not None and not dups and \
                ack.seq_id <= len(expected.boards):
            pos = ack.seq_id - 1  # a sound chain numbers the boards in topology order
        spec = expected.boards[pos] if expected is not None and pos is not None else None
        boards.append(FoundBoard(
            ack.seq_id, ack.serial, ack.fixed_id, ack.bootloader_version,
            position=pos + 1 if pos is not None else None,
            placement=spec.placement if spec else None, board=spec.board if spec else None,
            info=info, duplicate=ack.seq_id in dups))
    boards.sort(key=lambda b: (b.position or 99, b.seq_id))
    diagnosis = diagnose(result, len(firsts), expected, by_serial)
    return BusEnumeration(handle.name, tuple(boards),
                          len(expected.boards) if expected is not None else None, len(firsts),
                          tuple(diagnosis))


def expected_positions(handle: BusHandle) -> dict[int, int]:
    """Serial number -> chain position of the boards the topology lets us recognise: all of
    a virtual fleet, and those of a real robot whose topology gives their serial."""
    if handle.expected is None:
        return {}
    return {b.serial: b.position for b in handle.expected.boards
            if handle.virtual or b.serial_explicit}


def missing_expected(handle: BusHandle, serials: Iterable[int | None], answered: int
                     ) -> list[BoardSpec]:
    """Boards the topology expects on this bus that did not answer: recognised by serial
    where the topology lets us recognise every board, otherwise (chain order) the
    positions after the last one that answered."""
    expected = handle.expected
    if expected is None:
        return []
    by_serial = expected_positions(handle)
    if by_serial and len(by_serial) == len(expected.boards):
        seen = {s for s in serials if s is not None}
        if seen:
            return [b for b in expected.boards if b.serial not in seen]
    return list(expected.boards[answered:])


def describe_missing(bus: str, spec: BoardSpec, expected: int) -> str:
    joints = f"; joints {', '.join(spec.joints)}" if spec.joints else ""
    return (f"expected at position {spec.position + 1} ({spec.placement}{joints}) of the "
            f"{expected} boards the topology lists on {bus}, but no board there answered")


def _where(expected: BusSpec, pos: int) -> str:
    b = expected.boards[pos]
    return f"position {pos + 1} ({b.placement})"


def diagnose(result: InitResult, first_answers: int, expected: BusSpec | None,
             by_serial: dict[int, int]) -> list[Diagnosis]:
    """Explain an init result; an empty list means the chain is as expected."""
    out: list[Diagnosis] = []
    serials = list(dict.fromkeys(a.serial for a in result.acks))
    n_found = len(serials)
    n_exp = len(expected.boards) if expected is not None else None
    heads = [a for a in result.acks if a.seq_id == 1]
    if n_found == 0:
        if n_exp == 0:
            return out
        out.append(Diagnosis(
            "no-boards", "no board answered the init chain: check power and the CAN "
            "connection (CAN HI/LO, termination) of this bus.",
            "a powered board in its bootloader lights yellow after power-on; the first "
            "board of a chain yellow only, every other one yellow and green."))
        return out
    if expected is not None and by_serial and len(by_serial) == n_exp:
        out += _diagnose_known(result, expected, by_serial, heads)
    else:
        out += _diagnose_generic(result, heads, n_found, n_exp)
    if first_answers > 1 and not any(d.kind in ("broken-line", "unpowered") for d in out):
        out.append(Diagnosis("broken-line", f"Get First: {first_answers} boards answer as "
                             "first of the chain; the init line is broken.",
                             "each board right after a break lights yellow only at power-on."))
    for fid, acks in result.fixed_id_clashes().items():
        seqs = ", ".join(str(a.seq_id) for a in acks)
        out.append(Diagnosis(
            "fixed-id-clash", f"fixed ID {fid} is used by {len(acks)} boards (seq IDs {seqs});"
            " they would send the same identifiers. Give each board its own fixed ID."))
    return out


def _diagnose_known(result: InitResult, expected: BusSpec, by_serial: dict[int, int],
                    heads: list[ChainAck]) -> list[Diagnosis]:
    out = []
    found_pos = {by_serial[a.serial] for a in result.acks if a.serial in by_serial}
    missing = [p for p in range(len(expected.boards)) if p not in found_pos]
    unknown = sorted({a.serial for a in result.acks if a.serial not in by_serial})
    explained: set[int] = set()
    for head in heads:
        p = by_serial.get(head.serial)
        if p is None or p == 0:
            continue
        if p - 1 in missing:
            q = p - 1
            while q - 1 in missing:
                q -= 1
            span = range(q, p)
            explained.update(span)
            names = ", ".join(_where(expected, x) for x in span)
            out.append(Diagnosis(
                "unpowered", f"{names} did not answer and the chain restarts after it: "
                "unpowered, or cut off from CAN and the init line.",
                f"all three dark on that board; the board at {_where(expected, p)} lights "
                "yellow only at power-on, like a first board."))
        else:
            out.append(Diagnosis(
                "broken-line", f"init line cut between {_where(expected, p - 1)} and "
                f"{_where(expected, p)}: the board at {_where(expected, p)} took seq ID 1 "
                "like the first board, and the two parts of the chain were numbered side by "
                "side.",
                f"at power-on the board at {_where(expected, p)} lights yellow only (no "
                f"green), although it is not first."))
    rest = [p for p in missing if p not in explained]
    if rest:
        names = ", ".join(_where(expected, p) for p in rest)
        out.append(Diagnosis(
            "missing", f"{names} did not answer: unpowered, not connected to this CAN bus, or "
            "its init input is held set.",
            "a board without any LED has no power; one with yellow and green that never "
            "gets a seq ID sees a set init input."))
    for s in unknown:
        out.append(Diagnosis("extra", f"a board with serial 0x{s:08X} answered that the "
                             "topology does not list."))
    if len(heads) == 1 and not missing and not unknown:
        order = [by_serial[a.serial] for a in sorted(result.acks, key=lambda a: a.seq_id)]
        if order != sorted(order):
            out.append(Diagnosis("order", "the boards answered in another order than the "
                                 "topology lists them: check which cable goes where."))
    return out


def _diagnose_generic(result: InitResult, heads: list[ChainAck], n_found: int,
                      n_exp: int | None) -> list[Diagnosis]:
    out = []
    if len(heads) > 1:
        others = ", ".join(f"0x{h.serial:08X}" for h in heads[1:])
        out.append(Diagnosis(
            "broken-line", f"{len(heads)} boards took seq ID 1: the init line is broken (or a "
            f"board is unpowered) just before the board(s) with serial {others}; the parts of "
            "the chain were numbered side by side.",
            "at power-on a board right after the break lights yellow only (no green), like "
            "the first board; an unpowered board stays dark."))
    if n_exp is not None and n_found < n_exp:
        out.append(Diagnosis(
            "missing", f"found {n_found} of {n_exp} expected boards: "
            + ("check power and wiring after the last board that answered."
               if len(heads) <= 1 else "a board without any LED has no power."),
            "a powered board that never gets a seq ID shows yellow and green."))
    elif n_exp is not None and n_found > n_exp:
        out.append(Diagnosis("extra", f"found {n_found} boards, the topology expects {n_exp}."))
    return out
