"""``ucom tree check|show|format|diff``: attribute trees (``man/ucom-tree.5``)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import click
from rich.markup import escape

from ucom_tools.cli.output import emit_json, stderr, stdout
from ucom_tools.cli.tables import FitTable, shown_path
from ucom_tools.config import attrtree, topology
from ucom_tools.config.attrtree import BoardBlock, Change, RobotTrees, Tree, TreeEdgeKind
from ucom_tools.errors import InputError, TreeError
from ucom_tools.ops.manifest import image_problems

EXIT_DIFFERENT = 1
"""``tree diff``: the trees differ (like diff(1))."""


@click.group("tree")
def tree() -> None:
    """Attribute trees: the per-board configuration of a UCoM program (ucom-tree(5))."""


# ----------------------------------------------------------------------------- JSON
def tree_json(t: Tree) -> dict[str, Any]:
    return {"file": t.source, "boards": [board_json(b) for b in t.boards]}


def board_json(b: BoardBlock) -> dict[str, Any]:
    return {"number": b.number, "prefix": b.prefix, "edges": [{
        "index": e.index, "kind": e.kind.value, "generic": e.generic, "unique": e.unique,
        "default": e.default.number if e.default else None,
        "default_text": e.default.text if e.default else None} for e in b.edges]}


def robot_json(r: RobotTrees, extra: list[Tree]) -> dict[str, Any]:
    trees = list(r.trees) + [t for t in extra if t.source not in {x.source for x in r.trees}]
    return {
        "topology": r.topology.name, "source": r.topology.source,
        "boards": [{"bus": b.bus, "position": b.spec.position + 1,
                    "placement": b.spec.placement, "tree": str(b.file),
                    "block": b.board.number, "prefix": b.board.prefix,
                    "edges": len(b.board.edges),
                    "defaults": len(b.board.defaults())} for b in r.boards],
        "trees": [tree_json(t) for t in trees],
    }


def change_json(c: Change) -> dict[str, Any]:
    return {"change": c.kind.value, "board": c.board, "index": c.index, "name": c.name,
            "old": c.old, "new": c.new}


# ----------------------------------------------------------------------------- check
def _summary(b: BoardBlock) -> str:
    kinds = ", ".join(f"{len(b.of_kind(k))} {k}" for k in TreeEdgeKind)
    return (f"board {b.number} '{b.prefix}': {len(b.edges)} edges ({kinds}), "
            f"{len(b.defaults(TreeEdgeKind.PAR))} PAR + "
            f"{len(b.defaults(TreeEdgeKind.CI))} CI defaults")


def _fail_all(errors: Sequence[InputError]) -> None:
    """Every error on its own line, the last through the error boundary (exit 3)."""
    for e in errors[:-1]:
        stderr().print(f"[bold red]ucom: bad input:[/] {escape(str(e))}", highlight=False,
                       soft_wrap=True)
    if errors:
        raise errors[-1]


@tree.command("check")
@click.argument("files", nargs=-1, type=click.Path())
@click.option("--topology", "robot", metavar="ROBOT",
              help="Also check every tree this robot's topology binds (a bundled name such "
                   "as armar3, or a topology file), and that every board has one.")
@click.option("--json", "as_json", is_flag=True,
              help="Print the trees as JSON (one FILE: an object; several: a list).")
def check(files: tuple[str, ...], robot: str | None, as_json: bool) -> None:
    """Parse and check attribute tree FILEs; report FILE:LINE:COL of the first mistake in
    each (exit 3).  With --topology, check a robot's trees and their binding to boards."""
    if not files and robot is None:
        raise click.UsageError("give tree FILEs, --topology ROBOT, or both")
    trees: list[Tree] = []
    errors: list[InputError] = []
    for f in files:
        try:
            trees.append(attrtree.load(f))
        except TreeError as err:
            errors.append(err)
    topo = topology.load(robot) if robot is not None else None
    result = attrtree.check(topo) if topo is not None else None
    if result is not None and topo is not None:
        errors += result.problems
        errors += image_problems(topo)  # the manifest's images too (ucom deploy)
    if errors and as_json:  # every mistake in the document, the last also as its error
        emit_json({"error": {"kind": "bad input", "message": str(errors[-1]),
                             "exit_code": 3},
                   "errors": [{"file": e.file, "line": e.line, "column": e.column,
                               "message": e.reason} for e in errors]})
    _fail_all(errors)
    if as_json:
        if result is not None:
            emit_json(robot_json(result, trees))
        else:
            emit_json(tree_json(trees[0]) if len(trees) == 1 else [tree_json(t) for t in trees])
        return
    out = stdout()
    for t in trees:
        out.print(f"[green]ok[/] {escape(t.source)}: " + "; ".join(
            escape(_summary(b)) for b in t.boards), soft_wrap=True)
    if result is not None:
        _print_robot(result)
        images = {b.image for bus in result.topology.buses for b in bus.boards if b.image}
        if images:
            out.print(f"[green]ok[/] {len(images)} image file(s) of the manifest parse and "
                      "fit their boards", soft_wrap=True)


def _print_robot(r: RobotTrees) -> None:
    t = FitTable(f"{r.topology.name}: attribute trees")
    for col, drop in (("bus", 0), ("pos", 1), ("placement", 4), ("tree", 0), ("block", 2),
                      ("prefix", 0), ("edges", 0), ("defaults", 3)):
        t.add_column(col, drop=drop)
    for b in r.boards:
        t.add_row(b.bus, str(b.spec.position + 1), escape(b.spec.placement),
                  escape(shown_path(b.file)), str(b.board.number), escape(b.board.prefix),
                  str(len(b.board.edges)), str(len(b.board.defaults())))
    stdout().print(t)
    stdout().print(f"[green]ok[/] {len(r.boards)} boards, {len(r.trees)} tree files")


# ----------------------------------------------------------------------------- show
@tree.command("show")
@click.argument("file", type=click.Path())
@click.option("--board", "number", type=int, metavar="N", help="Only board block N.")
def show(file: str, number: int | None) -> None:
    """A table per board of FILE: index, kind, generic and unique name, default; grouped
    CI, SO, PAR."""
    t = attrtree.load(file)
    boards = t.boards
    if number is not None:
        try:
            boards = (t.board(number),)
        except KeyError:
            raise TreeError(f"no board {number} (its boards: "
                            f"{', '.join(map(str, t.numbers))})", file=file) from None
    for b in boards:
        stdout().print(_board_table(t, b))


def _board_table(t: Tree, b: BoardBlock) -> FitTable:
    table = FitTable(f"{escape(shown_path(t.source))}: board {b.number} "
                     f"'{escape(b.prefix)}'", caption=escape(_summary(b)),
                     caption_justify="left")
    table.add_column("index", justify="right", no_wrap=True, keep=True)
    table.add_column("kind", no_wrap=True, keep=True)
    for col in ("generic", "unique", "default"):
        table.add_column(col, keep=True)
    for k in TreeEdgeKind:
        edges = b.of_kind(k)
        for i, e in enumerate(edges):
            default = e.default.text if e.default else ("" if k is TreeEdgeKind.SO else "[dim]-[/]")
            unique = escape(e.unique) if e.unique != e.generic else f"[dim]{escape(e.unique)}[/]"
            table.add_row(str(e.index), k.value, escape(e.generic), unique, default,
                          end_section=i == len(edges) - 1)
    return table


# ----------------------------------------------------------------------------- format
@tree.command("format")
@click.argument("file", type=click.Path())
@click.option("-o", "--output", "out", type=click.Path(),
              help="Write here instead of to stdout (a file atomically, may be FILE "
              "itself; a link's target; a device or FIFO written through; see ucom(1) "
              "FILES).")
def format_(file: str, out: str | None) -> None:
    """Write FILE in the canonical form: two blanks per level, one entry per line, defaults
    in index order.  Comments other than # CI, # SO, # PAR are dropped."""
    text_tree = attrtree.load(file)
    if out is None:
        click.echo(attrtree.dumps(text_tree), nl=False)
        return
    attrtree.save(text_tree, out, key="-o")


# ----------------------------------------------------------------------------- diff
@tree.command("diff")
@click.argument("a", type=click.Path())
@click.argument("b", type=click.Path())
@click.option("--json", "as_json", is_flag=True, help="Print the changes as JSON.")
@click.pass_context
def diff(ctx: click.Context, a: str, b: str, as_json: bool) -> None:
    """What changed from tree A to tree B: boards, prefixes, edges (kind, generic, unique
    name) and defaults.  Exit 0 when they hold the same data, 1 when they differ."""
    ta, tb = attrtree.load(a), attrtree.load(b)
    changes = attrtree.diff(ta, tb)
    if as_json:
        emit_json({"a": a, "b": b, "equal": not changes,
                   "changes": [change_json(c) for c in changes]})
    elif not changes:
        stdout().print(f"no differences: {escape(a)} and {escape(b)} hold the same tree",
                       soft_wrap=True)
    else:
        table = FitTable(f"{escape(a)} -> {escape(b)}: {len(changes)} change(s)")
        for col in ("board", "index", "name", "change", "old", "new"):
            table.add_column(col)
        for c in changes:
            table.add_row(str(c.board), "" if c.index is None else str(c.index),
                          escape(c.name or ""), c.kind.value,
                          "[dim]-[/]" if c.old is None else f"[red]{escape(c.old)}[/]",
                          "[dim]-[/]" if c.new is None else f"[green]{escape(c.new)}[/]")
        stdout().print(table)
    if changes:
        ctx.exit(EXIT_DIFFERENT)
