"""What the console-option commands share: how they end (the exit code), how they print
rows and Info, and the factories of the commands that are one option applied to a
different flag or pin (``prog-enable``/``autostart``, ``set-init-in``/``set-init-out``,
``first``/``last``), each of which is one call in its own module."""

from __future__ import annotations

import click

from ucom_tools.cli import render
from ucom_tools.cli.exitcodes import EXIT_FAILED
from ucom_tools.cli.menu import BOARD, ONE_BOARD, help_text, parse_level
from ucom_tools.cli.options import (
    connection_options,
    emit_with_connection,
    init_option,
    json_option,
    needing_init,
    robot,
)
from ucom_tools.cli.output import stdout
from ucom_tools.ops import options as ops
from ucom_tools.ops.robot import ConnectSpec
from ucom_tools.wire.codes import StatusOp


def finish(ctx: click.Context, ok: bool) -> None:
    """Exit code 1 (:data:`EXIT_FAILED`) unless ``ok``."""
    if not ok:
        ctx.exit(EXIT_FAILED)


def rows_out(ctx: click.Context, spec: ConnectSpec, rows: list[ops.Row], as_json: bool,
             title: str) -> None:
    """Per board what it answered (a table titled ``title``, or JSON); exit code 1 when
    no board answered or one failed."""
    if as_json:
        emit_with_connection(spec, render.rows_json(rows))
    else:
        render.print_rows(stdout(), rows, title)
    finish(ctx, bool(rows) and all(r.ok for r in rows))


def info_out(ctx: click.Context, spec: ConnectSpec, rows: list[ops.Row], as_json: bool,
             title: str) -> None:
    """The boards' Info (``info``, ``count``, ``list``); exit code 1 when no board
    answered or one failed."""
    if as_json:
        emit_with_connection(spec, {"boards": [{"bus": x.bus, **render.addr_json(x.address),
                                 "placement": x.placement, "ok": x.ok, "detail": x.detail,
                                 **(render.info_json(x.info) if x.info else {})}
                                for x in rows]})
    elif rows:
        render.print_infos(stdout(), rows, title)
    else:
        stdout().print(f"[yellow]{title}: no board answered[/] (boards answer once they "
                       "have a number: run 'ucom init', or add --init)")
    finish(ctx, bool(rows) and all(x.ok for x in rows))


# ----------------------------------------------------------------------------- 4, 8
def status_command(name: str, option: int, op: StatusOp) -> click.Command:
    """Option ``option``: set (or with ``--off`` clear) the status flag ``op`` of a board
    or all."""
    @click.command(name, help=help_text(option, BOARD))
    @click.argument("board")
    @connection_options
    @init_option
    @json_option
    @click.option("--off", is_flag=True, help="Clear the flag instead of setting it.")
    @click.pass_context
    def cmd(ctx: click.Context, board: str, spec: ConnectSpec, bus_name: str | None,
            run_init: bool, as_json: bool, off: bool) -> None:
        ref = ops.parse_ref(board)
        with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r, \
                needing_init(option):
            rows = ops.set_status(r, ref, op, 0 if off else 1, bus=bus_name)
        rows_out(ctx, spec, rows, as_json, f"{name} {board}" + (" off" if off else ""))
    return cmd


# ----------------------------------------------------------------------------- 10, 11
def pin_command(name: str, option: int, op: StatusOp) -> click.Command:
    """Option ``option``: drive (or release) the init pin ``op`` of one board, then show
    its LEDs."""
    @click.command(name, help=help_text(option, "LEVEL is 'set' (drive the pin low) or "
                                                "'release'; the board's LEDs show it.\n\n"
                                        + ONE_BOARD))
    @click.argument("board")
    @click.argument("level")
    @connection_options
    @init_option
    @json_option
    @click.pass_context
    def cmd(ctx: click.Context, board: str, level: str, spec: ConnectSpec,
            bus_name: str | None, run_init: bool, as_json: bool) -> None:
        ref = ops.parse_ref(board, allow_all=False)
        value = parse_level(level)
        with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r, \
                needing_init(option):
            rows = ops.set_status(r, ref, op, value, bus=bus_name)
            status = (ops.board_status(r, ref, bus=bus_name)
                      if rows and all(x.ok for x in rows) else [])
        if as_json:
            data = render.rows_json(rows)
            data["status"] = [{"bus": b, "pins": s.pins, "leds": s.leds} for b, s in status]
            emit_with_connection(spec, data)
        else:
            render.print_rows(stdout(), rows, f"{name} {board} {level}")
            for b, s in status:
                stdout().print(f"{b} board {ref.address}: LEDs {render.status_leds(s)}")
        finish(ctx, bool(rows) and all(x.ok for x in rows))
    return cmd


# ----------------------------------------------------------------------------- 14, 15
def probe_command(name: str, option: int, last: bool, detail: str) -> click.Command:
    """Option ``option``: which board is first (or ``last``) on each bus's init line;
    exit code 1 unless exactly one answered on every bus."""
    @click.command(name, help=help_text(option, detail))
    @connection_options
    @json_option
    @click.pass_context
    def cmd(ctx: click.Context, spec: ConnectSpec, bus_name: str | None, as_json: bool) -> None:
        with robot(spec) as r:
            results = ops.probe(r, last=last, bus=bus_name)
        if as_json:
            emit_with_connection(spec, render.probe_json(results))
        else:
            render.print_probe(stdout(), results)
        finish(ctx, all(len(p.answers) == 1 for p in results))
    return cmd
