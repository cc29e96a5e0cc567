"""What changed between two attribute trees (``ucom tree diff``), for reviews.

Boards are matched by number, edges by index (the program's numbering).  The result is
empty exactly when both trees hold the same data: the same boards, prefixes, edges and
default texts; comments, layout and the order of default lines do not count.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from ucom_tools.config.attrtree.model import BoardBlock, Edge, Tree


class ChangeKind(StrEnum):
    BOARD_ADDED = "board-added"
    BOARD_REMOVED = "board-removed"
    PREFIX_CHANGED = "prefix-changed"
    EDGE_ADDED = "edge-added"
    EDGE_REMOVED = "edge-removed"
    KIND_CHANGED = "kind-changed"
    GENERIC_CHANGED = "generic-changed"
    RENAMED = "renamed"
    """The unique name changed."""
    DEFAULT_ADDED = "default-added"
    DEFAULT_REMOVED = "default-removed"
    DEFAULT_CHANGED = "default-changed"


@dataclass(frozen=True)
class Change:
    """One difference; ``old``/``new`` are texts (None where a side has nothing)."""

    kind: ChangeKind
    board: int
    index: int | None = None
    """The edge's index, None for board-level changes."""
    name: str | None = None
    """The edge's unique name (in B, or in A when removed), or the board's prefix."""
    old: str | None = None
    new: str | None = None


def diff(a: Tree, b: Tree) -> tuple[Change, ...]:
    """The changes that turn ``a`` into ``b``: by board number, then by edge index."""
    out: list[Change] = []
    numbers = list(a.numbers) + [n for n in b.numbers if n not in a.numbers]
    for n in numbers:
        if n not in b.numbers:
            p = a.board(n).prefix
            out.append(Change(ChangeKind.BOARD_REMOVED, n, name=p, old=p))
        elif n not in a.numbers:
            p = b.board(n).prefix
            out.append(Change(ChangeKind.BOARD_ADDED, n, name=p, new=p))
        else:
            out += _board(a.board(n), b.board(n))
    return tuple(out)


def _board(a: BoardBlock, b: BoardBlock) -> list[Change]:
    out: list[Change] = []
    n = a.number
    if a.prefix != b.prefix:
        out.append(Change(ChangeKind.PREFIX_CHANGED, n, name=b.prefix, old=a.prefix,
                          new=b.prefix))
    for i in range(max(len(a.edges), len(b.edges))):
        if i >= len(b.edges):
            e = a.edges[i]
            out.append(Change(ChangeKind.EDGE_REMOVED, n, i, e.unique, old=_edge_text(e)))
        elif i >= len(a.edges):
            e = b.edges[i]
            out.append(Change(ChangeKind.EDGE_ADDED, n, i, e.unique, new=_edge_text(e)))
        else:
            out += _edge(n, a.edges[i], b.edges[i])
    return out


def _edge(n: int, a: Edge, b: Edge) -> list[Change]:
    out: list[Change] = []
    i, name = a.index, b.unique
    if a.kind is not b.kind:
        out.append(Change(ChangeKind.KIND_CHANGED, n, i, name, a.kind.value, b.kind.value))
    if a.generic != b.generic:
        out.append(Change(ChangeKind.GENERIC_CHANGED, n, i, name, a.generic, b.generic))
    if a.unique != b.unique:
        out.append(Change(ChangeKind.RENAMED, n, i, name, a.unique, b.unique))
    old = a.default.text if a.default else None
    new = b.default.text if b.default else None
    if old != new:
        kind = (ChangeKind.DEFAULT_ADDED if old is None else
                ChangeKind.DEFAULT_REMOVED if new is None else ChangeKind.DEFAULT_CHANGED)
        out.append(Change(kind, n, i, name, old, new))
    return out


def _edge_text(e: Edge) -> str:
    text = f"{e.kind} {e.generic} ==> {e.unique}"
    return text + (f" = {e.default.text}" if e.default else "")
