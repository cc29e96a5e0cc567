"""``ucom deploy ROBOT``: bring a robot's boards to the images of its manifest.

Thin click glue around :mod:`ucom_tools.ops.deploy`: the manifest and its images are
checked before anything is opened (exit code 3), the plan is printed as a table (or
``--json``), ``--dry-run`` stops there (exit 0 when the robot matches its manifest, 1
when something would change, like ``diff``), then the deploy runs and says how every
board ended.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import click
from rich.console import Console
from rich.markup import escape

from ucom_tools.cli.exitcodes import EXIT_FAILED, EXIT_INTERRUPTED
from ucom_tools.cli.flashrun import NotBegun, run_cancellable
from ucom_tools.cli.options import connection_json, connection_options, json_option, robot
from ucom_tools.cli.output import emit_json, stderr, stdout
from ucom_tools.cli.params import _of_robot
from ucom_tools.cli.render import LEFT_WORDS
from ucom_tools.cli.tables import FitTable
from ucom_tools.config import topology as topology_mod
from ucom_tools.errors import InputError
from ucom_tools.ops import deploy as ops
from ucom_tools.ops.deploy_execute import execute
from ucom_tools.ops.robot import ConnectSpec
from ucom_tools.protocol.programmer import Cancelled
from ucom_tools.signals import interrupt_exit_code, stop_signal, stopped_how

STYLE = {ops.UP_TO_DATE: "green", ops.PROGRAM: "yellow", ops.RESTORE: "yellow",
         ops.START: "yellow", ops.REFUSED: "red", ops.SKIPPED: "dim", "done": "green",
         "failed": "red", "kept": "yellow", "verified": "green"}


def parse_boards(text: str | None, manifest: ops.Manifest) -> set[str] | None:
    """``--boards``: BUS:n keys, or seq IDs n meaning that position on every bus."""
    if text is None or text.strip().lower() == "all":
        return None
    keys = {w.key for w in manifest.boards}
    out: set[str] = set()
    for item in (x.strip() for x in text.split(",") if x.strip()):
        if ":" in item:
            if item not in keys:
                raise InputError(f"{item!r}: no board of {manifest.topology.name} with an "
                                 f"image there (boards: {', '.join(sorted(keys))})",
                                 key="--boards")
            out.add(item)
            continue
        try:
            n = int(item)
        except ValueError:
            raise InputError(f"{item!r}: expected 'all', BUS:n or n", key="--boards") from None
        found = {k for k in keys if k.endswith(f":{n}")}
        if not found:
            raise InputError(f"{item!r}: no board with seq ID {n}", key="--boards")
        out |= found
    return out


def _seen(s: ops.Seen | None) -> str:
    if s is None:
        return "-"
    program = f"{s.program} 0x{s.progid:08X}" if s.progid is not None else "no program"
    return f"{program}, {s.state}" + (", AutoStart" if s.autostart else "")


def print_plan(c: Console, p: ops.Plan) -> None:
    t = FitTable(f"{escape(p.manifest.topology.name)}: deploy plan")
    for col, drop in (("bus", 0), ("seq", 0), ("placement", 1), ("image", 0), ("before", 0),
                      ("action", 0), ("why", 0)):
        t.add_column(col, drop=drop)
    for r in p.rows:
        why = "; ".join([r.reason] * bool(r.reason) + [f"warning: {w}" for w in r.warnings])
        t.add_row(r.bus, str(r.seq_id or "-"), escape(r.placement), escape(r.image),
                  escape(_seen(r.before)), f"[{STYLE[r.action]}]{r.action}[/]", escape(why))
    c.print(t)
    c.print(summary(p), soft_wrap=True)


def summary(p: ops.Plan) -> str:
    n = len(p.rows)
    counts: dict[str, int] = {}
    for r in p.rows:
        counts[r.action] = counts.get(r.action, 0) + 1
    head = f"{counts.get(ops.UP_TO_DATE, 0)} of {n} up to date"
    rest = [f"{counts[a]} to {a}" for a in ops.WORK if counts.get(a)]
    rest += [f"{counts[a]} {a}" for a in (ops.REFUSED, ops.SKIPPED) if counts.get(a)]
    return head + (": " + ", ".join(rest) if rest else "")


def print_result(c: Console, result: ops.DeployResult) -> None:
    t = FitTable("deployed")
    for col, drop in (("bus", 0), ("seq", 0), ("placement", 1), ("outcome", 0), ("after", 0),
                      ("parameters", 0)):
        t.add_column(col, drop=drop)
    for b in result.boards:
        if b.row.action == ops.UP_TO_DATE:
            continue
        kept = {"kept": f"kept ({b.params.values})", "none": "-",
                "failed": "[red]failed[/]"}[b.params.outcome]
        outcome = f"[{STYLE.get(b.outcome, 'red')}]{b.outcome}[/]" + (
            f": {escape(b.detail)}" if b.detail and b.outcome != ops.REFUSED else "")
        t.add_row(b.row.bus, str(b.row.seq_id or "-"), escape(b.row.placement), outcome,
                  escape(_seen(b.after)), kept)
    if t.rows:
        c.print(t)


def board_json(b: ops.BoardDeploy) -> dict[str, Any]:
    def seen(s: ops.Seen | None) -> dict[str, Any] | None:
        if s is None:
            return None
        return {"state": s.state, "progid": None if s.progid is None else f"0x{s.progid:08X}",
                "program": s.program or None, "autostart": s.autostart}

    r = b.row
    return {"bus": r.bus, "seq_id": r.seq_id or None, "position": r.position + 1,
            "placement": r.placement,
            "serial": None if r.serial is None else f"0x{r.serial:08X}", "image": r.image,
            "progid": f"0x{r.progid:08X}", "autostart": r.autostart,
            "before": seen(r.before), "action": r.action, "reason": r.reason,
            "warnings": list(r.warnings), "outcome": b.outcome, "detail": b.detail,
            "after": seen(b.after),
            "parameters": {"kept": b.params.outcome == "kept" if b.params.outcome != "none"
                           else None, "outcome": b.params.outcome, "values": b.params.values,
                           "detail": b.params.detail}}


@click.command("deploy")
@click.argument("robot_name", metavar="ROBOT")
@click.option("--dry-run", is_flag=True,
              help="Print the plan and stop: exit code 0 when every board is up to date, 1 "
                   "when something would change.")
@click.option("--boards", "boards_text", metavar="LIST",
              help="Only these boards: BUS:n (seq ID n on BUS), or n (on every bus), comma "
                   "separated; the others are shown, never changed.")
@click.option("--journal", "journal_dir", type=click.Path(path_type=Path), metavar="DIR",
              help="Keep the journal of this deploy in DIR (default: "
                   "$XDG_STATE_HOME/ucom/deploy/ROBOT, else "
                   "~/.local/state/ucom/deploy/ROBOT).")
@connection_options
@json_option
@click.pass_context
def deploy_cmd(ctx: click.Context, robot_name: str, dry_run: bool, boards_text: str | None,
               journal_dir: Path | None, spec: ConnectSpec, bus_name: str | None,
               as_json: bool) -> None:
    """Bring ROBOT's boards to the images its manifest names, keeping their parameters.

    ROBOT is the robot's topology (a bundled name such as armar3, or a topology file):
    per board the image it should run (image = "FILE"), whether it starts by itself
    (autostart = true) and its attribute tree.  The images are checked first (they
    exist, parse, and fit each board's plug-on board and FPGA; exit code 3, nothing
    sent).  Then every bus is initialised and each board's Info compared with its image;
    the plan is printed: up to date, program (another ProgID, no program, interrupted),
    restore, start, or refused (the image does not fit, the board is missing).

    Then, on every bus at once: the parameters of the boards to program that run a
    program are saved in the journal, each image is sent once per bus to the boards that
    need it, verified, the parameters loaded back, AutoStart set as the manifest says and
    the programs started.  Boards that are up to date are not reset, stopped or
    reprogrammed.  A deploy that was killed is resumed by the next one from its journal
    (it says so); the journal is removed when the robot matches its manifest.  Ctrl-C,
    SIGTERM or SIGHUP at any step leaves no board ProgEnabled or in a transfer and says
    per board what it was left with (exit code 130, 143, 129; the journal stays).  Exit
    code 0 when the robot matches its manifest, 1 naming the boards that failed, are
    refused or missing."""
    topo = topology_mod.load(robot_name)
    manifest = ops.load_manifest(topo)  # exit 3 before anything is opened
    if bus_name is not None:
        if not any(w.bus == bus_name for w in manifest.boards):
            raise InputError(f"no board of {topo.name} with an image is on bus {bus_name!r}",
                             key="--bus")
        manifest = ops.Manifest(topo, tuple(w for w in manifest.boards if w.bus == bus_name),
                                manifest.trees)
    only = parse_boards(boards_text, manifest)
    journal = ops.Journal.open(journal_dir or ops.default_journal(topo.name), topo.name)
    request = ops.DeployRequest(manifest, journal,
                                only=frozenset(only) if only is not None else None)
    err = stderr()

    def event(text: str) -> None:
        err.print(f"deploy: {escape(text)}", soft_wrap=True, highlight=False)

    if journal.resumed:
        event(f"resuming the deploy that did not finish (journal {journal.directory})")
    with robot(_of_robot(spec, robot_name, bus_name)) as r:
        try:
            the_plan = run_cancellable(lambda _cancel: ops.plan(r, request), name="ucom-deploy")
        except KeyboardInterrupt as e:
            err.print(f"[yellow]deploy {stopped_how(e)} while planning (the init chains and "
                      "each board's Info): nothing that changes a board was sent[/]",
                      soft_wrap=True)
            ctx.exit(interrupt_exit_code(e))
            return
        if not as_json:
            print_plan(stdout(), the_plan)
        if dry_run:
            if as_json:
                emit_json(_doc(the_plan, None, spec, journal, dry_run=True))
            ctx.exit(0 if the_plan.matches else EXIT_FAILED)
        try:
            result = run_cancellable(lambda cancel: execute(
                r, request, the_plan, events=event, cancel=cancel), name="ucom-deploy",
                finished=lambda done, _stop: ops.DeployInterrupted(
                    replace(done, interrupted="finished")))
        except (KeyboardInterrupt, Cancelled) as e:
            _interrupted(ctx, spec, the_plan, journal, e, as_json)
            return
    if as_json:
        emit_json(_doc(the_plan, result, spec, journal, dry_run=False))
    else:
        print_result(stdout(), result)
        if result.ok:
            stdout().print(f"[green]{escape(topo.name)} matches its manifest[/]"
                           + (f" ({summary(the_plan)})" if the_plan.matches else ""),
                           soft_wrap=True)
    if not result.ok:
        names = ", ".join(f"{b.row.where} ({b.outcome}: {b.detail})" for b in result.failed)
        err.print(f"[red]failed: {escape(names)}[/]", soft_wrap=True)
        if result.journal is not None:
            err.print(f"[yellow]the journal is in {escape(str(result.journal))}; run the "
                      "deploy again to finish[/]", soft_wrap=True)
        ctx.exit(EXIT_FAILED)


def _interrupted(ctx: click.Context, spec: ConnectSpec, the_plan: ops.Plan,
                 journal: ops.Journal, e: BaseException, as_json: bool) -> None:
    """An interrupted deploy: per board what it was left with (the table, or ``--json``
    with ``interrupted``), a line on stderr, the signal's exit code."""
    how = stopped_how(e)
    err = stderr()
    if isinstance(e, ops.DeployInterrupted):
        result = e.result
        if as_json:
            stop = stop_signal(e)
            emit_json({**_doc(the_plan, result, spec, journal, dry_run=False),
                       "interrupted": {"how": how, "signal": stop.name if stop is not None
                                       else "SIGINT", "step": result.interrupted}})
        else:
            print_result(stdout(), result)
        counts: dict[str, int] = {}
        for b in result.boards:
            if b.row.action in ops.WORK:
                counts[b.outcome] = counts.get(b.outcome, 0) + 1
        told = "; ".join(f"{n} {LEFT_WORDS.get(o, o)}" for o, n in counts.items())
        when = ("after it had finished" if result.interrupted == "finished"
                 else f"while {result.interrupted}")
        if result.journal is not None:
            tail = (f"the journal in {result.journal} says how far it got: run the deploy "
                    "again to finish it")
        elif result.ok:
            tail = "the robot matches its manifest"
        else:
            tail = "nothing was recorded yet: run the deploy again"
        err.print(f"[yellow]deploy {how} {escape(when)}: "
                  f"{escape(told or 'no board was touched')}; {escape(tail)}[/]",
                  soft_wrap=True)
    elif isinstance(e, NotBegun):
        err.print(f"[yellow]deploy {how} before it began: nothing was sent to any board[/]",
                  soft_wrap=True)
    else:  # a third signal cut the undo short
        err.print(f"[red]deploy {how} again while putting the boards back: they are left "
                  "as they are (check them with 'ucom deploy --dry-run'); the journal in "
                  f"{escape(str(journal.directory))} says how far it got[/]", soft_wrap=True)
    ctx.exit(interrupt_exit_code(e) if isinstance(e, KeyboardInterrupt) else EXIT_INTERRUPTED)


def _doc(p: ops.Plan, result: ops.DeployResult | None, spec: ConnectSpec,
         journal: ops.Journal, *, dry_run: bool) -> dict[str, Any]:
    boards = result.boards if result is not None else tuple(
        ops.BoardDeploy(r, r.action, r.reason, None) for r in p.rows)
    return {"robot": p.manifest.topology.name, "topology": p.manifest.topology.source,
            "dry_run": dry_run, "resumed": p.resumed, "summary": summary(p),
            "up_to_date": len(p.up_to_date), "boards_total": len(p.rows),
            "ok": result.ok if result is not None else p.matches,
            "journal": str(result.journal) if result is not None and result.journal
            else (str(journal.directory) if result is None and journal.resumed else None),
            "boards": [board_json(b) for b in boards], "connection": connection_json(spec)}
