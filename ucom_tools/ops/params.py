"""A robot's live parameters: every PAR and CI value its boards hold, read back into
attribute trees (``ucom params dump``), written from trees (``ucom params load``), and
kept across a reflash (``ucom flash --keep-params``).

Every board is brought up by :meth:`RemotePart.check <ucom_tools.ops.remote.RemotePart>`
(program started if needed, edges described and compared with the board's tree block):
a board whose edges differ from its tree is read or written not at all.  Values travel
raw (MCA Dump CI / acknowledged MCA writes, ``man/ucom-protocol.7``, RUN TIME) and are
converted exactly with the edge's exponent (:mod:`ucom_tools.ops.edges`).

A dumped tree is the robot's tree in canonical form (:func:`attrtree.dumps
<ucom_tools.config.attrtree.dumps>`) with a default for every PAR and CI edge: the live
value, written as the tree wrote it when that text denotes the same number (``0x444``,
``0.0005``), else as the exact decimal, or as hex for an edge whose name ends in
``(BitMask)``.  Loading such a tree gives every board exactly the values it had.

This module reads and writes the values; the dumped trees' files are
:mod:`~ucom_tools.ops.params_dump`'s, keeping them across a reflash
:mod:`~ucom_tools.ops.params_keep`'s.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import TYPE_CHECKING

from ucom_tools.config.attrtree import BoundBoard, RobotTrees, TreeEdgeKind, Value
from ucom_tools.config.topology import BoardKey, Topology
from ucom_tools.edgelists.model import EdgeSpec
from ucom_tools.errors import BoardError, InputError, UcomTimeoutError
from ucom_tools.ops.edges import spec_of
from ucom_tools.ops.exchange import defaults_raw, on_board, write_runs
from ucom_tools.ops.remote import RemotePart
from ucom_tools.ops.remote.report import BoardCheck
from ucom_tools.ops.robot import Robot
from ucom_tools.protocol.mca import BoardEdges, McaClient
from ucom_tools.wire import mca
from ucom_tools.wire.codes import BoardState
from ucom_tools.wire.ids import ALL, seq

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey

KINDS = (TreeEdgeKind.CI, TreeEdgeKind.PAR)
"""The kinds a board holds values of that the PC sets (SO values are measurements)."""
RUNNING = (BoardState.RUNNING_FLASH, BoardState.RUNNING_EXTRAM)
BITMASK = "(BitMask)"
"""Edges whose name ends so are bit masks: their values are written in hex."""


# ----------------------------------------------------------------------------- robot
def on_bus(trees: RobotTrees, bus: str | None) -> RobotTrees:
    """The boards of ``trees`` on ``bus`` (all when None); InputError when none is."""
    if bus is None:
        return trees
    boards = tuple(b for b in trees.boards if b.bus == bus)
    if not boards:
        have = sorted({b.bus for b in trees.boards})
        raise InputError(f"no board of {trees.topology.name} with an attribute tree is on "
                         f"bus {bus!r} (buses with trees: {', '.join(have)})", key="bus")
    return replace(trees, boards=boards)


def _part_of(robot: Robot, trees: RobotTrees) -> Robot:
    """The buses of ``robot`` that ``trees`` has boards on, each expecting the boards of
    the trees' topology (placements, positions); InputError for a bus the connection
    does not have."""
    topology = trees.topology
    buses = {}
    for name in dict.fromkeys(b.bus for b in trees.boards):
        h = robot.buses.get(name)
        if h is None:
            have = ", ".join(robot.buses) or "none"
            every = ", ".join(dict.fromkeys(b.bus for b in trees.boards))
            hint = (f": it needs a channel for each of its buses ({every}), or bus "
                    f"{next(iter(robot.buses))} chosen alone" if robot.buses else "")
            raise InputError(f"{topology.name} ({topology.source}) has boards on bus "
                             f"{name}; the connection has {have}{hint}", key="bus")
        buses[name] = replace(h, expected=topology.bus(name))
    return replace(robot, buses=buses, topology=topology)


def running(robot: Robot, trees: RobotTrees) -> tuple[set[BoardKey], dict[
        BoardKey, str]]:
    """Which boards of ``trees`` run a program now (init chain and Info, nothing
    started): (bus, seq ID) of those, and why each other board does not count."""
    part = _part_of(robot, trees)
    found: set[BoardKey] = set()
    why: dict[BoardKey, str] = {}
    for name, h in part.buses.items():
        init = h.client.init_chain()
        infos = h.client.info_many(ALL, expect=[seq(n) for n in init.numbers])
        states = {a.number: inf.state for a, inf in infos.items()}
        for b in trees.boards:
            if b.bus != name:
                continue
            n = b.spec.position + 1
            if n not in init.numbers:
                why[(name, n)] = "did not answer the init chain"
            elif n not in states:
                why[(name, n)] = "its Info did not arrive"
            elif states[n] not in RUNNING:
                why[(name, n)] = f"runs no program ({states[n].text})"
            else:
                found.add((name, n))
    return found, why


# ----------------------------------------------------------------------------- values
def value_text(raw: int, edge_spec: EdgeSpec, original: Value | None = None) -> str:
    """How a dumped tree writes ``raw``: the original text when it denotes the same raw
    number, else hex for a bit mask, else the exact decimal (no exponent, no trailing
    zeros)."""
    if original is not None:
        try:
            if edge_spec.raw(original.text) == raw:
                return original.text
        except (ValueError, InvalidOperation):
            pass
    if edge_spec.name.endswith(BITMASK) and edge_spec.exponent == 0:
        return f"-0x{-raw:X}" if raw < 0 else f"0x{raw:X}"
    return format(edge_spec.value(raw).normalize(), "f")


@dataclass(frozen=True)
class EdgeValue:
    """One PAR or CI value a board holds."""

    kind: TreeEdgeKind
    index: int
    """The tree index (counting CI, SO, PAR)."""
    generic: str
    unique: str
    raw: int
    text: str
    """As a dumped tree writes it."""
    unit: str
    default: str | None
    """The default of the board's tree (None: it has none)."""

    @property
    def value(self) -> Decimal:
        return Decimal(int(self.text, 16) if "0x" in self.text else self.text)

    @property
    def changed(self) -> bool:
        """The board holds another value than its tree's default (or the tree has none)."""
        return self.default != self.text


@dataclass(frozen=True)
class BoardRead:
    """One board: its values, or why they could not be read."""

    bus: str
    board: int
    """Seq ID."""
    where: str
    placement: str
    prefix: str
    tree: Path
    block: int
    values: tuple[EdgeValue, ...] = ()
    error: str = ""
    """Why the values could not be read (the first difference from its tree, no answer)."""
    line: int = 0
    """The tree line of the first difference (0: none, or the file as a whole)."""
    skipped: str = ""
    """Why the board was not read at all (``running_only``: it runs no program)."""

    @property
    def ok(self) -> bool:
        return not self.error and not self.skipped

    @property
    def at(self) -> str:
        """``FILE:LINE`` of the first difference ("" when the tree is not at fault)."""
        return f"{self.tree}:{self.line}" if self.line else ""


@dataclass(frozen=True)
class Readout:
    topology: Topology
    boards: tuple[BoardRead, ...]

    @property
    def ok(self) -> bool:
        """Every board that was to be read was read."""
        return all(not b.error for b in self.boards)

    @property
    def read(self) -> list[BoardRead]:
        return [b for b in self.boards if b.ok]

    @property
    def failed(self) -> list[BoardRead]:
        return [b for b in self.boards if b.error]


def _first_difference(check: BoardCheck) -> tuple[str, int]:
    """Why a board failed its check (without the board's name), and the tree line."""
    if check.error:
        error = check.error
        return error.removeprefix(f"{check.where}: "), 0
    first = check.differences[0]
    n = len(check.differences)
    return (f"its program's edges differ from its tree ({n} difference{'s' * (n != 1)}), "
            f"first: {first.message}"), first.line


def _board_read(b: BoundBoard, check: BoardCheck) -> BoardRead:
    return BoardRead(check.bus, check.board, check.where, b.spec.placement, b.board.prefix,
                     b.file, b.board.number)


def _dump_kind(client: McaClient, n: int, edges: BoardEdges, kind: mca.Kind) -> list[int]:
    records = edges.of(kind)
    return client.dump(seq(n), kind, 0, len(records), records) if records else []


def _values(b: BoundBoard, edges: BoardEdges, raws: Mapping[mca.Kind, Sequence[int]],
            ) -> tuple[EdgeValue, ...]:
    out = []
    for e, kind, i in on_board(b.board, edges):
        if e.kind not in KINDS:
            continue
        record = edges.of(kind)[i]
        edge_spec = spec_of(kind, record)
        raw = raws[kind][i]
        out.append(EdgeValue(e.kind, e.index, e.generic, e.unique, raw,
                             value_text(raw, edge_spec, e.default), record.unit,
                             e.default.text if e.default else None))
    return tuple(out)


def read_values(robot: Robot, trees: RobotTrees, *, bus: str | None = None,
                running_only: bool = False) -> Readout:
    """Every PAR and CI value of the boards of ``trees`` (on ``bus``): each board's
    program started if needed (``running_only``: boards that run none are skipped, as
    they hold no values of their own), described and checked against its tree, then read
    back.  A board that fails does not stop the others."""
    trees = on_bus(trees, bus)
    bound = {(b.bus, b.spec.position + 1): b for b in trees.boards}
    skipped: dict[BoardKey, str] = {}
    if running_only:
        found, skipped = running(robot, trees)
        trees = replace(trees, boards=tuple(b for b in trees.boards
                                            if (b.bus, b.spec.position + 1) in found))
    reads: dict[BoardKey, BoardRead] = {}
    for key, why in skipped.items():
        b = bound[key]
        reads[key] = BoardRead(b.bus, key[1], b.where, b.spec.placement, b.board.prefix,
                               b.file, b.board.number, skipped=why)
    if trees.boards:
        with RemotePart(_part_of(robot, trees), trees) as part:
            for check in part.check().boards:
                key = (check.bus, check.board)
                b = bound[key]
                base = _board_read(b, check)
                edges = part.described(check.bus, check.board)
                if not check.ok or edges is None:
                    error, line = _first_difference(check)
                    reads[key] = replace(base, error=error, line=line)
                    continue
                client = part.exchanges[check.bus].mca
                try:
                    raws = {k: _dump_kind(client, check.board, edges, k)
                            for k in (mca.Kind.CI, mca.Kind.PAR)}
                except (BoardError, UcomTimeoutError) as err:
                    reads[key] = replace(base, error=f"read-back failed: {err}")
                    continue
                reads[key] = replace(base, values=_values(b, edges, raws))
    order = list(bound)
    return Readout(trees.topology, tuple(reads[k] for k in order if k in reads))


# ----------------------------------------------------------------------------- load
def select_prefixes(trees: RobotTrees, prefixes: Iterable[str]) -> RobotTrees:
    """Only the boards of ``trees`` with these prefixes."""
    wanted = set(prefixes)
    return replace(trees, boards=tuple(b for b in trees.boards if b.board.prefix in wanted))


@dataclass(frozen=True)
class NotTaken:
    """A value a board does not hold after it was written and acknowledged."""

    unique: str
    sent: int
    read: int


@dataclass(frozen=True)
class BoardLoad:
    bus: str
    board: int
    where: str
    placement: str
    prefix: str
    tree: Path
    block: int
    written: int = 0
    """Values written (and acknowledged)."""
    not_taken: tuple[NotTaken, ...] = ()
    error: str = ""
    line: int = 0
    held: str = ""
    """Why nothing was written although the board is fine (another board failed)."""

    @property
    def ok(self) -> bool:
        return not self.error and not self.not_taken and not self.held

    @property
    def at(self) -> str:
        """``FILE:LINE`` of the first difference or the value ("" when the tree is not
        at fault)."""
        return f"{self.tree}:{self.line}" if self.line else ""


@dataclass(frozen=True)
class LoadResult:
    topology: Topology
    boards: tuple[BoardLoad, ...]
    sent: bool = field(default=False)
    """Something was written (False: a check failed first, every board is unchanged)."""

    @property
    def ok(self) -> bool:
        return bool(self.boards) and all(b.ok for b in self.boards)

    @property
    def failed(self) -> list[BoardLoad]:
        return [b for b in self.boards if b.error or b.not_taken]


def load_values(robot: Robot, trees: RobotTrees, *, bus: str | None = None,
                strict: bool = True) -> LoadResult:
    """Write the PAR and CI defaults of ``trees`` to their boards, acknowledged, then
    read them back.  Every board is checked first (program started if needed, edges
    compared with its block) and every value converted for its edge.

    ``strict`` (``ucom params load``): a board that fails the check leaves every board
    unchanged (the result says why), and a value its edge cannot carry raises
    InputError naming its file and line before anything is written.  Otherwise
    (``flash --keep-params``) each board that passes is written, whatever the others."""
    trees = on_bus(trees, bus)
    bound = {(b.bus, b.spec.position + 1): b for b in trees.boards}
    loads: dict[BoardKey, BoardLoad] = {}
    sent = False
    with RemotePart(_part_of(robot, trees), trees) as part:
        checks = part.check().boards
        plans: dict[BoardKey, list[tuple[mca.Kind, int, int, str]]] = {}
        for check in checks:
            key = (check.bus, check.board)
            b = bound[key]
            base = BoardLoad(check.bus, check.board, check.where, b.spec.placement,
                             b.board.prefix, b.file, b.board.number)
            edges = part.described(check.bus, check.board)
            if not check.ok or edges is None:
                error, line = _first_difference(check)
                loads[key] = replace(base, error=error, line=line)
                continue
            loads[key] = base
            try:
                plans[key] = defaults_raw(b.board, edges, check.where, str(b.file))
            except InputError as err:
                if strict:
                    raise
                loads[key] = replace(base, error=err.reason, line=err.line or 0)
        if strict and any(x.error for x in loads.values()):
            for key in plans:
                loads[key] = replace(loads[key], held="not written: another board failed "
                                     "its check")
            plans = {}
        for key, values in plans.items():
            name, n = key
            client = part.exchanges[name].mca
            edges = part.described(name, n)
            assert edges is not None
            try:
                for kind in (mca.Kind.PAR, mca.Kind.CI):
                    runs = [(i, raw) for k, i, raw, _ in values if k is kind]
                    if runs:
                        sent = True
                        write_runs(client, seq(n), kind, runs, edges.of(kind))
                back = {k: _dump_kind(client, n, edges, k) for k in (mca.Kind.CI, mca.Kind.PAR)}
            except (BoardError, UcomTimeoutError) as err:
                loads[key] = replace(loads[key], error=f"writing failed: {err}")
                continue
            missed = tuple(NotTaken(unique, raw, back[k][i]) for k, i, raw, unique in values
                           if back[k][i] != raw)
            loads[key] = replace(loads[key], written=len(values), not_taken=missed)
    return LoadResult(trees.topology, tuple(loads[k] for k in bound if k in loads), sent)
