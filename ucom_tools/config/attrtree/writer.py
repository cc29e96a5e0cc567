"""Writing attribute trees in the canonical form (``ucom tree format``).

Two blanks of indentation per level, one entry per line, ``Name{`` / ``}Name``, the kind
markers ``# CI``, ``# SO``, ``# PAR`` before the first edge of each kind, defaults in index
order, blocks without defaults left out, a blank line between sections, LF line ends.
Reading the output gives the same :class:`Tree` (comments other than the kind markers, and
the order of the default lines, are not kept).  :func:`save` replaces a file atomically.
"""

from __future__ import annotations

from pathlib import Path

from ucom_tools import fileio
from ucom_tools.config.attrtree.model import BoardBlock, Tree, TreeEdgeKind

INDENT = "  "


def dumps(tree: Tree) -> str:
    """The canonical text of ``tree`` (which must be valid, as :func:`parse` returns it)."""
    out = ["DSP{"]
    for i, board in enumerate(tree.boards):
        if i:
            out.append("")
        _board(out, board)
    out.append("}DSP")
    return "\n".join(out) + "\n"


def _board(out: list[str], board: BoardBlock) -> None:
    i1, i2, i3 = INDENT, INDENT * 2, INDENT * 3
    out += [f"{i1}{board.number}{{", f"{i2}Prefix : {board.prefix}", f"{i2}MappingTable{{"]
    kind: TreeEdgeKind | None = None
    for e in board.edges:
        if e.kind is not kind:
            kind = e.kind
            out.append(f"{i3}# {kind}")
        out.append(f"{i3}{e.index}:{e.generic} ==> {e.unique}")
    out.append(f"{i2}}}MappingTable")
    for kind in (TreeEdgeKind.PAR, TreeEdgeKind.CI):
        section = kind.section
        defaults = [e for e in board.edges if e.kind is kind and e.default is not None]
        if defaults and section:
            out += ["", f"{i2}{section}{{"]
            out += [f"{i3}{e.unique}:{e.default.text}" for e in defaults if e.default]
            out.append(f"{i2}}}{section}")
    out.append(f"{i1}}}{board.number}")


def save(tree: Tree, path: str | Path, *, key: str | None = None) -> None:
    """Write ``tree`` to ``path`` by the rules of ``ucom(1)``, FILES: a regular file
    atomically (a temporary file in the same directory, synced, renamed over the target,
    which keeps its permissions), a link's target in its place, a device or FIFO written
    through, ``-`` standard output."""
    fileio.write_text(path, dumps(tree), key=key, allow_stdout=True)
