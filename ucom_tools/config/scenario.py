"""Injected faults of the virtual fleet, and the scenario files that time them.

An *injected fault* is something that happens to the hardware of a virtual robot while it
runs (``ucom(1)``, SCENARIOS): a board loses power (``power-off``), its DSP resets
(``reset``), its CAN controller goes bus-off (``bus-off``), a bus's cable to the PC is cut
(``cable``), the emergency stop cuts every board's power (``estop``).  Not to be confused
with a mutant board's *defect* (:mod:`ucom_tools.config.mutants`, ``--defect``), a
protocol deviation a board has for life.

A scenario is a TOML file, one ``[[fault]]`` table per fault::

    [[fault]]
    at = 0.5            # seconds after the first MCA Alive on the bus
    kind = "power-off"
    bus = "CAN0"
    board = 3           # the seq ID: the chain position, from 1
    for = 1.0           # seconds until it ends

This module is the pure model and parser (:class:`InjectedFault`, :class:`Scenario`),
checked against a topology (:meth:`Scenario.check`); every mistake is an
:class:`~ucom_tools.errors.InputError` naming the file, its line and the key.  The virtual
fleet applies the faults (:mod:`ucom_tools.virtual.injected`).
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field, replace
from enum import StrEnum
from pathlib import Path
from typing import Any, Final

from ucom_tools import fileio
from ucom_tools.config.topology import MAX_BOARDS, Topology
from ucom_tools.errors import InputError


class FaultKind(StrEnum):
    """What an injected fault does (``ucom(1)``, SCENARIOS)."""

    POWER_OFF = "power-off"
    """One board loses power for ``for`` seconds."""
    RESET = "reset"
    """One board's DSP resets: silent for the reset time plus ``for`` (default 0)."""
    BUS_OFF = "bus-off"
    """One board's CAN controller is off the bus for ``for`` seconds."""
    CABLE = "cable"
    """One bus's frames are lost between the PC and the boards for ``for`` seconds."""
    ESTOP = "estop"
    """Every board of the robot loses power for ``for`` seconds."""

    @property
    def target(self) -> str:
        """What it acts on: ``board``, ``bus`` or ``robot``."""
        return _TARGETS[self]

    @property
    def default_for(self) -> float | None:
        """``for`` when none is given (None: it must be given)."""
        return 0.0 if self is FaultKind.RESET else None


_TARGETS: Final = {FaultKind.POWER_OFF: "board", FaultKind.RESET: "board",
                   FaultKind.BUS_OFF: "board", FaultKind.CABLE: "bus",
                   FaultKind.ESTOP: "robot"}
ROBOT: Final = "robot"
"""The target of the whole robot (``estop``)."""
MAX_SECONDS: Final = 86_400.0
"""The longest ``at`` and ``for`` (a day): a longer one is a mistake."""
KINDS: Final = ", ".join(k.value for k in FaultKind)


@dataclass(frozen=True)
class InjectedFault:
    """One injected fault: its kind, where (``bus`` and ``board`` as :attr:`kind` needs:
    a board, a bus, or neither for the robot), how long (``for_s``) and, in a scenario,
    when (``at_s`` after the first MCA Alive on the bus) and the file's line."""

    kind: FaultKind
    bus: str | None = None
    board: int | None = None
    """The board's seq ID = its chain position, from 1."""
    for_s: float = 0.0
    at_s: float = 0.0
    line: int | None = field(default=None, compare=False)

    @property
    def target(self) -> str:
        """``CAN0/3`` (a board), ``CAN0`` (a bus) or ``robot``."""
        if self.bus is None:
            return ROBOT
        return self.bus if self.board is None else f"{self.bus}/{self.board}"

    def check(self, topology: Topology) -> None:
        """The bus and board exist in ``topology``; :class:`InputError` naming what does
        (key ``bus`` or ``board``) otherwise."""
        if self.bus is None:
            return
        names = [b.name for b in topology.buses]
        if self.bus not in names:
            raise InputError(f"no bus {self.bus!r} in {topology.name}; its buses: "
                             + ", ".join(names), key="bus")
        if self.board is None:
            return
        boards = topology.bus(self.bus).boards
        if not 1 <= self.board <= len(boards):
            listed = ", ".join(f"{b.position + 1} ({b.placement})" for b in boards)
            raise InputError(f"no board {self.board} on {self.bus}; its boards: "
                             + (listed or "none"), key="board")

    def describe(self, topology: Topology, reset_s: float = 0.0) -> str:
        """What applying it does, in a sentence: ``CAN0 board 3 (head right) powered off
        for 1 s``.  ``reset_s``: the boards' reset time (a reset's silence)."""
        seconds = _seconds(self.for_s)
        if self.kind is FaultKind.ESTOP:
            count = sum(len(b.boards) for b in topology.buses)
            buses = ", ".join(b.name for b in topology.buses)
            return (f"emergency stop: all {count} boards of {topology.name} ({buses}) "
                    f"powered off for {seconds}")
        if self.kind is FaultKind.CABLE:
            return f"{self.bus} cut from the PC for {seconds}"
        where = self.target
        if self.bus is not None and self.board is not None:
            placement = topology.bus(self.bus).boards[self.board - 1].placement
            where = f"{self.bus} board {self.board} ({placement})"
        if self.kind is FaultKind.POWER_OFF:
            return f"{where} powered off for {seconds}"
        if self.kind is FaultKind.RESET:
            return f"{where} reset: silent for {_seconds(reset_s + self.for_s)}"
        return f"{where} bus-off for {seconds}"

    def as_dict(self) -> dict[str, Any]:
        return {"kind": self.kind.value, "target": self.target, "bus": self.bus,
                "board": self.board, "for_s": self.for_s}


def _seconds(value: float) -> str:
    return f"{value:g} s"


def parse_target(text: str) -> tuple[str | None, int | None]:
    """``CAN0/3`` or ``CAN0:3`` (as every other command names a board) -> (``CAN0``, 3);
    ``CAN0`` -> (``CAN0``, None); ``robot`` -> (None, None); :class:`InputError` (key
    ``TARGET``) when malformed."""
    if text == ROBOT:
        return None, None
    bus, sep, board = text.partition("/")
    if not sep and ":" in text:
        bus, sep, board = text.rpartition(":")
    if not bus or not _NAME.fullmatch(bus):
        raise InputError(f"{text!r}: expected BUS/BOARD (e.g. CAN0/3 or CAN0:3), BUS (e.g. "
                         f"CAN0) or {ROBOT}", key="TARGET")
    if not sep:
        return bus, None
    if not board.isdigit() or not 1 <= int(board) <= MAX_BOARDS:
        raise InputError(f"{text!r}: the board after the bus is its seq ID, 1-{MAX_BOARDS}",
                         key="TARGET")
    return bus, int(board)


_NAME: Final = re.compile(r"[A-Za-z0-9_.-]+")
"""A bus name as a target may give it (a topology's bus names are such words)."""


def injected(kind: str, target: str, for_s: float | None) -> InjectedFault:
    """The fault ``kind`` on ``target`` (:func:`parse_target`) for ``for_s`` seconds
    (None: the kind's default), as ``ucom fleet fault`` and its wire give it;
    :class:`InputError` naming ``KIND``, ``TARGET`` or ``for_s`` when they do not fit."""
    try:
        fault_kind = FaultKind(kind)
    except ValueError:
        raise InputError(f"{kind!r} is no fault kind; kinds: {KINDS}", key="KIND") from None
    bus, board = parse_target(target)
    wanted = fault_kind.target
    got = ROBOT if bus is None else "bus" if board is None else "board"
    if got != wanted:
        example = {"board": "BUS/BOARD, e.g. CAN0/3", "bus": "BUS, e.g. CAN0",
                   "robot": ROBOT}[wanted]
        raise InputError(f"{kind} acts on a {wanted}: give {example}, not {target!r}",
                         key="TARGET")
    seconds = _duration(fault_kind, for_s, "for_s")
    return InjectedFault(fault_kind, bus, board, seconds)


def _duration(kind: FaultKind, for_s: float | None, key: str) -> float:
    """``for`` of ``kind``: given, or its default; InputError naming ``key``."""
    if for_s is None:
        if kind.default_for is None:
            raise InputError(f"{kind.value} needs a duration in seconds (how long until it "
                             "ends)", key=key)
        return kind.default_for
    if not math.isfinite(for_s) or for_s < 0 or for_s > MAX_SECONDS:
        raise InputError(f"expected seconds from 0 to {MAX_SECONDS:g}, got {for_s!r}", key=key)
    if for_s == 0 and kind.default_for is None:
        raise InputError(f"{kind.value} for 0 s does nothing: give more than 0 seconds",
                         key=key)
    return float(for_s)


@dataclass(frozen=True)
class Scenario:
    """Timed injected faults (a scenario file): each ``at_s`` after the first MCA Alive
    the fleet receives on its bus; a fault of the whole robot happens on each bus at
    ``at_s`` after that bus's own first MCA Alive (so that buses served by processes of
    their own need no coordination)."""

    faults: tuple[InjectedFault, ...]
    source: str = ""
    lines: dict[tuple[int, str], int] = field(default_factory=dict, compare=False)
    """The line of each fault's keys: (its index from 0, key)."""

    @classmethod
    def load(cls, path: str | Path) -> Scenario:
        """Read and parse the scenario file ``path`` (:class:`InputError` naming it)."""
        name = str(path)

        def refuse(text: str) -> InputError:
            return InputError(text if text != "no such file" else "no such scenario file",
                              file=name)

        data = fileio.read_input(Path(path), limit=fileio.TEXT_LIMIT, what="a scenario file",
                                 error=refuse)
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError as err:
            raise InputError(f"cannot read: {err}", file=name) from None
        return cls.parse(text, name)

    @classmethod
    def parse(cls, text: str, source: str = "<scenario>") -> Scenario:
        """A scenario from TOML ``text``; :class:`InputError` naming ``source``, the line
        and the key of the first mistake."""
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            m = re.search(r"line (\d+)", str(err))
            raise InputError(f"not valid TOML: {err}", file=source,
                             line=int(m.group(1)) if m else None) from None
        lines = _lines(text)
        for key in data:
            if key not in ("fault", "description"):
                raise InputError("unknown key; allowed: description, fault", file=source,
                                 line=lines.get(((), key)), key=key)
        if "description" in data and not isinstance(data["description"], str):
            raise InputError("expected a string", file=source,
                             line=lines.get(((), "description")), key="description")
        raw = data.get("fault")
        if not isinstance(raw, list) or not raw or not all(isinstance(f, dict) for f in raw):
            raise InputError("expected one or more [[fault]] tables", file=source,
                             line=lines.get(((), "fault")), key="fault")
        return cls(tuple(_fault(f, i, source, lines) for i, f in enumerate(raw)), source,
                   {(where[0], key): no for (where, key), no in lines.items()
                    if where and where[0] >= 0 and key})

    def check(self, topology: Topology) -> None:
        """Every bus and board named is in ``topology``; :class:`InputError` naming the
        file, the fault's line and the key otherwise."""
        for i, f in enumerate(self.faults):
            try:
                f.check(topology)
            except InputError as err:
                raise InputError(err.reason, file=self.source,
                                 line=self.lines.get((i, err.key or ""), f.line),
                                 key=f"fault[{i + 1}].{err.key}") from None

    def only(self, buses: tuple[str, ...] | list[str]) -> Scenario:
        """The faults of these buses and those of the whole robot (a process that serves
        only these buses)."""
        return replace(self, faults=tuple(f for f in self.faults
                                          if f.bus is None or f.bus in buses))

    def of_bus(self, bus: str) -> tuple[InjectedFault, ...]:
        """The faults that happen on ``bus``: its own and the whole robot's (each counted
        from this bus's first MCA Alive)."""
        return tuple(f for f in self.faults if f.bus is None or f.bus == bus)


_KEYS: Final = ("at", "kind", "bus", "board", "for")


def _fault(raw: dict[str, Any], i: int, source: str,
           lines: dict[tuple[tuple[int, ...], str], int]) -> InjectedFault:
    table_line = lines.get(((i,), ""))

    def fail(key: str, message: str) -> InputError:
        return InputError(message, file=source, line=lines.get(((i,), key), table_line),
                          key=f"fault[{i + 1}].{key}" if key else f"fault[{i + 1}]")

    for key in raw:
        if key not in _KEYS:
            raise fail(key, "unknown key; allowed: " + ", ".join(_KEYS))
    if "kind" not in raw:
        raise fail("", f"missing key 'kind' (one of {KINDS})")
    if not isinstance(raw["kind"], str) or raw["kind"] not in {k.value for k in FaultKind}:
        raise fail("kind", f"expected one of {KINDS}, got {raw['kind']!r}")
    kind = FaultKind(raw["kind"])

    def seconds(key: str) -> float | None:
        if key not in raw:
            return None
        value = raw[key]
        if isinstance(value, bool) or not isinstance(value, int | float) or \
                not math.isfinite(value) or not 0 <= value <= MAX_SECONDS:
            raise fail(key, f"expected seconds from 0 to {MAX_SECONDS:g}, got {value!r}")
        return float(value)

    at = seconds("at")
    if at is None:
        raise fail("", "missing key 'at' (seconds after the first MCA Alive on the bus)")
    try:
        for_s = _duration(kind, seconds("for"), "for")
    except InputError as err:
        raise fail("for" if "for" in raw else "", err.reason if "for" in raw else
                   f"missing key 'for': {err.reason}") from None
    wanted = kind.target
    bus: str | None = None
    board: int | None = None
    if wanted == ROBOT:
        for key in ("bus", "board"):
            if key in raw:
                raise fail(key, f"{kind.value} acts on the whole robot: no {key}")
    else:
        if "bus" not in raw:
            raise fail("", f"missing key 'bus' ({kind.value} acts on a {wanted})")
        if not isinstance(raw["bus"], str) or not raw["bus"]:
            raise fail("bus", f"expected a bus name, got {raw['bus']!r}")
        bus = raw["bus"]
        if wanted == "bus" and "board" in raw:
            raise fail("board", f"{kind.value} acts on a whole bus: no board")
        if wanted == "board":
            if "board" not in raw:
                raise fail("", f"missing key 'board' ({kind.value} acts on one board: its "
                               "seq ID, the chain position from 1)")
            value = raw["board"]
            if isinstance(value, bool) or not isinstance(value, int) or \
                    not 1 <= value <= MAX_BOARDS:
                raise fail("board", f"expected a seq ID 1-{MAX_BOARDS}, got {value!r}")
            board = value
    return InjectedFault(kind, bus, board, for_s, at, line=table_line)


_HEADER: Final = re.compile(r"^\s*\[\[\s*fault\s*\]\]")
_OTHER_HEADER: Final = re.compile(r"^\s*\[")
_TABLE: Final = re.compile(r"^\s*\[\s*fault\s*\]")
_KEY: Final = re.compile(r"^\s*([A-Za-z0-9_\-]+|\"[^\"]*\")\s*=")


def _lines(text: str) -> dict[tuple[tuple[int, ...], str], int]:
    """The line of each key: ((), key) at the top, ((i,), key) in the i-th [[fault]]
    table, ((i,), "") its header."""
    found: dict[tuple[tuple[int, ...], str], int] = {}
    where: tuple[int, ...] = ()
    count = -1
    for no, line in enumerate(text.splitlines(), 1):
        if _HEADER.match(line):
            count += 1
            where = (count,)
            found.setdefault((where, ""), no)
            found.setdefault(((), "fault"), no)
        elif _OTHER_HEADER.match(line):
            where = (-1,)
            if _TABLE.match(line):  # [fault]: one table where [[fault]] tables belong
                found.setdefault(((), "fault"), no)
        elif k := _KEY.match(line):
            found.setdefault((where, k.group(1).strip('"')), no)
    return found
