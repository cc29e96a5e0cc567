"""The mapping check: does a tree block describe the program a board runs?

A tree maps the program's generic edge names, in the program's order (CI, then SO, then
PAR), to robot-wide names (``man/ucom-tree.5``).  Before the PC configures a running board
it compares the block with the edges the board described (MCA DumpIO Descr): every index
must carry the same generic name and kind, and the counts must agree.  A tree written for
another program fails at its first differing edge, named with its line.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from ucom_tools.config.attrtree.model import Board, Kind
from ucom_tools.programs import known
from ucom_tools.programs.model import EdgeKind, ProgramSpec

_KIND = {EdgeKind.CI: Kind.CI, EdgeKind.SO: Kind.SO, EdgeKind.PAR: Kind.PAR}


@dataclass(frozen=True)
class Mismatch:
    """The first difference between a tree block and a board's edge list."""

    message: str
    line: int
    """Line of the tree's mapping (0: the block as a whole)."""


def compare(board: Board, edges: Sequence[tuple[EdgeKind, str]]) -> Mismatch | None:
    """Compare a tree block with a program's edges (kind, generic name) in tree order;
    None when they agree."""
    for n, (kind, name) in enumerate(edges):
        if n >= len(board.edges):
            return Mismatch(f"the tree has {len(board.edges)} edges; the program has "
                            f"{len(edges)} (index {n}, {kind.name} '{name}', is missing)",
                            board.line)
        e = board.edges[n]
        if e.generic != name or e.kind is not _KIND[kind]:
            return Mismatch(f"index {n}: the tree maps {e.kind.value} '{e.generic}', the "
                            f"program has {kind.name} '{name}' there", e.line)
    if len(board.edges) > len(edges):
        extra = board.edges[len(edges)]
        return Mismatch(f"the tree has {len(board.edges)} edges; the program has "
                        f"{len(edges)} (index {extra.index}, '{extra.generic}', is extra)",
                        extra.line)
    return None


def spec_edges(spec: ProgramSpec) -> list[tuple[EdgeKind, str]]:
    return [(e.kind, e.name) for e in spec.edges]


def program_of(board: Board) -> ProgramSpec | None:
    """The known program whose edges the block maps, if any."""
    for spec in known().values():
        if compare(board, spec_edges(spec)) is None:
            return spec
    return None
