"""``ucom params dump|load``: a robot's live PAR and CI values as attribute trees, and the
report of ``ucom flash --keep-params`` (tables, ``--json``)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import click
from rich.console import Console
from rich.markup import escape

from ucom_tools.cli.exitcodes import EXIT_FAILED
from ucom_tools.cli.options import connection_json, connection_options, json_option, robot
from ucom_tools.cli.output import emit_json, json_number, stderr, stdout
from ucom_tools.cli.tables import FitTable, shown_path
from ucom_tools.config import attrtree
from ucom_tools.config import topology as topology_mod
from ucom_tools.config.attrtree import TreeEdgeKind
from ucom_tools.ops import params as ops
from ucom_tools.ops import params_dump, params_keep
from ucom_tools.ops.robot import ConnectSpec


@click.group("params")
def params() -> None:
    """Live parameters: the PAR and CI values a robot's boards hold, read back into
    attribute trees and written from them (ucom-tree(5))."""


# ----------------------------------------------------------------------------- JSON
def _value_json(v: ops.EdgeValue) -> dict[str, Any]:
    return {"kind": v.kind.value, "index": v.index, "generic": v.generic, "unique": v.unique,
            "raw": v.raw, "value": json_number(v.text), "text": v.text, "unit": v.unit,
            "default": json_number(v.default), "default_text": v.default,
            "changed": v.changed}


def read_json(r: ops.BoardRead) -> dict[str, Any]:
    return {"bus": r.bus, "seq_id": r.board, "where": r.where, "placement": r.placement,
            "prefix": r.prefix,
            "tree": str(r.tree), "block": r.block, "ok": r.ok, "error": r.error or None,
            "line": r.line or None, "skipped": r.skipped or None,
            "values": [_value_json(v) for v in r.values]}


def load_json(b: ops.BoardLoad) -> dict[str, Any]:
    return {"bus": b.bus, "seq_id": b.board, "where": b.where, "placement": b.placement,
            "prefix": b.prefix, "tree": str(b.tree), "block": b.block, "ok": b.ok,
            "written": b.written,
            "not_taken": [{"unique": x.unique, "sent": x.sent, "read": x.read}
                          for x in b.not_taken],
            "error": b.error or None, "line": b.line or None, "held": b.held or None}


def kept_json(k: params_keep.KeepResult) -> dict[str, Any]:
    """The ``keep_params`` object of ``ucom flash --keep-params --json``."""
    return {"ok": k.ok, "directory": str(k.directory) if k.directory else None,
            "boards": [{"bus": b.bus, "seq_id": b.board, "where": b.where, "prefix": b.prefix,
                        "outcome": b.outcome, "detail": b.detail, "values": b.values,
                        "changed": b.changed} for b in k.boards]}


# ----------------------------------------------------------------------------- tables
def _of_robot(spec: ConnectSpec, robot_name: str, bus_name: str | None) -> ConnectSpec:
    """The connection to ROBOT's buses: a network or hardware interface without -c opens
    the robot's buses by name (``--bus NAME``: that one), as 'ucom remote' does."""
    if spec.virtual:
        return spec
    return replace(spec, topology=spec.topology or robot_name, only=bus_name)


def _fail_line(where: str, error: str, at: str) -> str:
    return f"[red]{escape(where)}: {escape(error)}[/]" + (f" [dim]({escape(at)})[/]" if at else "")


def _read_table(c: Console, readout: ops.Readout) -> None:
    t = FitTable(f"{escape(readout.topology.name)}: live values")
    for col, drop in (("bus", 0), ("board", 0), ("placement", 1), ("prefix", 0), ("PAR", 0),
                      ("CI", 0), ("differ from tree", 0), ("no tree default", 2), ("result", 0)):
        t.add_column(col, drop=drop)
    for r in readout.boards:
        par = sum(v.kind is TreeEdgeKind.PAR for v in r.values)
        t.add_row(r.bus, str(r.board), escape(r.placement), escape(r.prefix),
                  str(par) if r.ok else "", str(len(r.values) - par) if r.ok else "",
                  str(sum(v.changed and v.default is not None for v in r.values))
                  if r.ok else "",
                  str(sum(v.default is None for v in r.values)) if r.ok else "",
                  "[green]read[/]" if r.ok else "[red]failed[/]" if r.error else
                  f"[dim]skipped: {escape(r.skipped)}[/]")
    c.print(t)
    if any(v.changed for r in readout.boards for v in r.values):
        c.print("[dim]differ from tree: live values other than the default their tree gives "
                "(a program started for the dump holds its power-on values; 'ucom params "
                "load' writes the tree's); no tree default: edges their tree gives no "
                "default for[/]")


def print_kept(c: Console, k: params_keep.KeepResult) -> None:
    """What ``flash --keep-params`` kept, per board."""
    style = {"kept": "green", "skipped": "dim", "failed": "red", "untouched": "yellow"}
    for b in k.boards:
        differ = f" ({b.changed} of {b.values} differ from its tree)" \
            if b.outcome == "kept" else ""
        c.print(f"[{style[b.outcome]}]params {b.outcome}:[/] {escape(b.where)}: "
                f"{escape(b.detail)}{differ}", soft_wrap=True)
    if k.directory is not None:
        c.print(f"[yellow]the values read before programming are in {escape(str(k.directory))}"
                "; load them with 'ucom params load ROBOT FILE...'[/]", soft_wrap=True)


# ----------------------------------------------------------------------------- dump
@params.command("dump")
@click.argument("robot_name", metavar="ROBOT")
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path),
              metavar="FILE_OR_DIR",
              help="Where to write: a directory when the robot has several tree files "
                   "(one file each, same base names; made if missing), else a file.")
@click.option("--force", is_flag=True, help="Replace files that exist.")
@connection_options
@json_option
@click.pass_context
def dump_cmd(ctx: click.Context, robot_name: str, output: Path, force: bool, spec: ConnectSpec,
             bus_name: str | None, as_json: bool) -> None:
    """Read every live PAR and CI value of ROBOT's boards into attribute trees.

    Per board with a tree: its program is started if needed (a board in its bootloader
    then holds its program's power-on values), its edges are described and compared with
    its tree block, and every PAR and CI value is read back.  The trees are written as
    the robot's trees in canonical form with a default for every PAR and CI edge: the
    live value, in the tree's own text where that is the same number (0x444, 0.0005),
    else the exact decimal (hex for a (BitMask) edge); 'ucom params load' of them gives
    the boards exactly these values again.

    All or nothing: when a board cannot be read (its edges differ from its tree, it does
    not answer) nothing is written and the exit code is 1, naming the board and the
    first difference.  A file that exists is refused (exit code 3, nothing read) unless
    --force; each file is replaced atomically.

    ROBOT is the robot's topology (a bundled name such as armar3, or a topology file): it
    says which attribute tree each board has.  The bus comes from the connection options
    (--virtual NAME, or -i/-c/--host/--port)."""
    topo = topology_mod.load(robot_name)
    trees = attrtree.bind_present(topo)
    targets = params_dump.dump_targets(trees, output, force=force, bus=bus_name)
    with robot(_of_robot(spec, robot_name, bus_name)) as r:
        readout = ops.read_values(r, trees, bus=bus_name)
    written = params_dump.write_dump(readout, targets) if readout.ok else []
    if as_json:
        emit_json({"robot": topo.name, "topology": topo.source, "output": str(output),
                   "ok": readout.ok, "written": [str(p) for p in written],
                   "files": [{"tree": d.tree.source, "file": str(d.path)} for d in targets],
                   "boards": [read_json(b) for b in readout.boards],
                   "connection": connection_json(spec)})
    else:
        _read_table(stdout(), readout)
        for p in written:
            stdout().print(f"[green]wrote[/] {escape(str(p))}", soft_wrap=True)
    if not readout.ok:
        for b in readout.failed:
            stderr().print(_fail_line(b.where, b.error, b.at), soft_wrap=True)
        stderr().print(f"[red]nothing written: {len(readout.failed)} board(s) could not be "
                       "read[/]")
        ctx.exit(EXIT_FAILED)


# ----------------------------------------------------------------------------- load
@params.command("load")
@click.argument("robot_name", metavar="ROBOT")
@click.argument("files", nargs=-1, type=click.Path())
@connection_options
@json_option
@click.pass_context
def load_cmd(ctx: click.Context, robot_name: str, files: tuple[str, ...], spec: ConnectSpec,
             bus_name: str | None, as_json: bool) -> None:
    """Write the PAR and CI defaults of attribute trees to ROBOT's running boards.

    FILES (default: the robot's own trees) bind to boards by their Prefix: the board
    whose tree in ROBOT has that prefix gets the block; boards no file names are left
    alone.  First every board is checked (program started if needed, edges compared with
    the block: a difference is exit code 1 and nothing is written to any board) and
    every value converted for its edge (one that does not fit is exit code 3 naming
    FILE:LINE, nothing sent).  Then the values are written, each acknowledged, and read
    back: a board that does not hold them afterwards makes the exit code 1.

    ROBOT is the robot's topology (a bundled name such as armar3, or a topology file): it
    says which attribute tree each board has.  The bus comes from the connection options
    (--virtual NAME, or -i/-c/--host/--port)."""
    topo = topology_mod.load(robot_name)
    trees = attrtree.bind_present(topo)
    if files:
        trees = attrtree.with_files(trees, files, only=True)
    with robot(_of_robot(spec, robot_name, bus_name)) as r:
        result = ops.load_values(r, trees, bus=bus_name)
    if as_json:
        emit_json({"robot": topo.name, "topology": topo.source,
                   "files": list(files) or [t.source for t in trees.trees],
                   "ok": result.ok, "sent": result.sent,
                   "boards": [load_json(b) for b in result.boards],
                   "connection": connection_json(spec)})
    else:
        _load_table(stdout(), result)
    if not result.ok:
        for b in result.failed:
            if b.error:
                stderr().print(_fail_line(b.where, b.error, b.at), soft_wrap=True)
            for x in b.not_taken:
                stderr().print(f"[red]{escape(b.where)}: {escape(x.unique)} reads {x.read} "
                               f"(raw) after {x.sent} was written[/]", soft_wrap=True)
        names = ", ".join(b.where for b in result.failed)
        stderr().print(f"[red]{'not loaded' if result.sent else 'nothing written'}: "
                       f"{escape(names)}[/]", soft_wrap=True)
        ctx.exit(EXIT_FAILED)


def _load_table(c: Console, result: ops.LoadResult) -> None:
    t = FitTable(f"{escape(result.topology.name)}: values loaded")
    for col, drop in (("bus", 0), ("board", 0), ("placement", 1), ("prefix", 0), ("tree", 0),
                      ("written", 0), ("result", 0)):
        t.add_column(col, drop=drop)
    for b in result.boards:
        if b.ok:
            verdict = "[green]loaded, read back[/]"
        elif b.held:
            verdict = f"[yellow]{escape(b.held)}[/]"
        elif b.not_taken:
            verdict = f"[red]{len(b.not_taken)} value(s) not taken[/]"
        else:
            verdict = "[red]failed[/]"
        t.add_row(b.bus, str(b.board), escape(b.placement), escape(b.prefix),
                  escape(shown_path(b.tree)), str(b.written or ""), verdict)
    c.print(t)
