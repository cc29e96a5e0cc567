"""The run time's start-up check (``man/ucom-protocol.7``, RUN TIME, Start sequence, up
to the mapping check): on one bus, the init chain, each board's program started if
needed, its descriptions fetched and compared with its tree block; nothing is written.

:func:`check_bus` gives the :class:`~ucom_tools.ops.remote.report.BoardCheck` of every
board of the bus that has a tree, and the robot-wide names (:class:`~ucom_tools.ops.
edges.EdgeRef`) of the edges of those that match;
:meth:`RemotePart.check <ucom_tools.ops.remote.RemotePart.check>` runs it on every bus.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

from ucom_tools.config.attrtree.match import differences, program_of
from ucom_tools.config.attrtree.model import BoardBlock
from ucom_tools.config.attrtree.robot import RobotTrees
from ucom_tools.errors import BoardError, InputError, UcomTimeoutError
from ucom_tools.ops.edges import EdgeRef, spec_of
from ucom_tools.ops.exchange import BusExchange, NoProgram, edge_list, on_board
from ucom_tools.ops.remote.report import BoardCheck
from ucom_tools.ops.robot import BusHandle
from ucom_tools.protocol.mca import BoardEdges
from ucom_tools.wire.ids import seq


@dataclass
class BusCheck:
    """What the check of one bus found."""

    boards: list[BoardCheck] = field(default_factory=list)
    """Every board of the bus with a tree block, in the bus's order."""
    refs: list[EdgeRef] = field(default_factory=list)
    """The edges of the boards that match their trees, in tree order."""
    described: dict[int, BoardEdges] = field(default_factory=dict)
    """Seq ID -> the edges the board described (every board that got that far)."""
    serials: dict[int, int] = field(default_factory=dict)
    """Seq ID -> the serial number its Init Ack gave (what Init Request REJOIN names)."""


def check_bus(h: BusHandle, x: BusExchange, trees: RobotTrees) -> BusCheck:
    """The init chain of bus ``h``, then every board of it with a tree block: program
    started if needed, descriptions fetched and compared with the block.  A board that
    fails is named in its BoardCheck and does not stop the others."""
    out = BusCheck()
    chain = h.client.init_chain()
    numbers = chain.numbers
    out.serials = {a.seq_id: a.serial for a in chain.acks}
    name = h.name
    for spec in x.bus.boards:
        n = spec.position + 1
        where = x.where(n)
        try:
            block = trees.board(name, spec.position)
        except KeyError:
            continue  # no tree: not part of the run time
        base = BoardCheck(name, n, where, block.prefix, str(tree_file(trees, name,
                                                                      spec.position)))
        if n not in numbers:
            out.boards.append(_with(base, error="did not answer the init chain"))
            continue
        try:
            ready = x.start_programs([n])[n]
            edges = x.mca.describe(seq(n), (ready.ci, ready.so, ready.par))
        except (BoardError, UcomTimeoutError) as err:
            out.boards.append(_with(base, error=str(err), no_program=isinstance(err, NoProgram)))
            continue
        out.described[n] = edges
        found = tuple(differences(block, edge_list(edges)))
        if not found:
            out.refs.extend(_refs_of(name, n, where, block, edges))
        out.boards.append(_with(base, program=f"{ready.ci}/{ready.so}/{ready.par}",
                                differences=found))
    return out


def tree_file(trees: RobotTrees, bus: str, position: int) -> Path | str:
    """The file the tree block of a board comes from (a replacing file, or the
    topology's); "" when the board has none."""
    for b in trees.boards:
        if b.bus == bus and b.spec.position == position:
            return b.file
    return ""


def _with(base: BoardCheck, **changes: object) -> BoardCheck:
    return replace(base, **changes)  # type: ignore[arg-type]


def _refs_of(bus: str, n: int, where: str, block: BoardBlock, edges: BoardEdges,
             ) -> Iterator[EdgeRef]:
    """The edges of one board whose tree block matches its description."""
    for e, kind, index in on_board(block, edges):
        yield EdgeRef(bus, n, where, block.prefix, e.unique, e.generic, kind, index,
                      spec_of(kind, edges.of(kind)[index]))


def check_periods(periods: dict[str, int], trees: RobotTrees) -> None:
    """Every name of ``periods`` must be an edge of a program the robot's trees map
    (InputError, with the closest names, before anything is sent)."""
    names: set[str] = set()
    for b in trees.boards:
        program = program_of(b.board)
        if program is not None:
            names |= {e.name for e in program.edges}
    for name in periods:
        if name not in names:
            close = difflib.get_close_matches(name, sorted(names), n=3)
            hint = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
            raise InputError(f"no program edge called {name!r} (periods name the programs' "
                             f"generic edges, as in the trees' mapping tables){hint}",
                             key="periods")
