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

from ucom_tools.config.attrtree.model import BoardBlock, TreeEdgeKind
from ucom_tools.edgelists import known
from ucom_tools.edgelists.model import EdgeKind, ProgramSpec

_KIND = {EdgeKind.CI: TreeEdgeKind.CI, EdgeKind.SO: TreeEdgeKind.SO, EdgeKind.PAR: TreeEdgeKind.PAR}


@dataclass(frozen=True)
class Mismatch:
    """The first difference between a tree block and a board's edge list."""

    message: str
    line: int
    """Line of the tree's mapping (0: the block as a whole)."""


def differences(board: BoardBlock, edges: Sequence[tuple[EdgeKind, str]]) -> list[Mismatch]:
    """Every difference between a tree block and a program's edges (kind, generic name),
    index by index: a different edge (named, or of another kind, or moved: the order
    differs), an edge the tree lacks, an edge the board lacks."""
    out: list[Mismatch] = []
    where = {name: n for n, (_, name) in enumerate(edges)}
    for n in range(max(len(board.edges), len(edges))):
        e = board.edges[n] if n < len(board.edges) else None
        if n >= len(edges):
            assert e is not None
            out.append(Mismatch(f"index {n}: the tree maps {e.kind.value} '{e.generic}'; the "
                                "board has no such edge (its program has "
                                f"{len(edges)} edges)", e.line))
            continue
        kind, name = edges[n]
        if e is None:
            out.append(Mismatch(f"index {n}: the board has {kind.name} '{name}'; the tree "
                                f"does not map it (it has {len(board.edges)} edges)",
                                board.line))
        elif e.generic != name or e.kind is not _KIND[kind]:
            moved = where.get(e.generic)
            why = f" ('{e.generic}' is index {moved} on the board: the order differs)" \
                if moved is not None and moved != n else ""
            out.append(Mismatch(f"index {n}: the tree maps {e.kind.value} '{e.generic}', the "
                                f"board has {kind.name} '{name}' there{why}", e.line))
    return out


def compare(board: BoardBlock, edges: Sequence[tuple[EdgeKind, str]]) -> Mismatch | None:
    """The first difference between a tree block and a program's edges (kind, generic
    name) in tree order; None when they agree."""
    found = differences(board, edges)
    return found[0] if found else None


def spec_edges(spec: ProgramSpec) -> list[tuple[EdgeKind, str]]:
    return [(e.kind, e.name) for e in spec.edges]


def program_of(board: BoardBlock) -> ProgramSpec | None:
    """The known program whose edges the block maps, if any."""
    for spec in known().values():
        if compare(board, spec_edges(spec)) is None:
            return spec
    return None
