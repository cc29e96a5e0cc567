"""``ucom xreset``: option 9 of dsp_console2can, XReset: clear AutoStart and reset a
board or every board (boards without a number act too, but cannot answer)."""

from __future__ import annotations

import click

from ucom_tools.cli import render
from ucom_tools.cli.commands.common import finish
from ucom_tools.cli.menu import BOARD, help_text
from ucom_tools.cli.options import (
    connection_options,
    emit_with_connection,
    json_option,
    needing_init,
    robot,
)
from ucom_tools.cli.output import stdout
from ucom_tools.ops import options as ops
from ucom_tools.ops.robot import ConnectSpec


@click.command("xreset", help=help_text(9, "Default: every board (boards without a number "
                                           "act too, but cannot answer).\n\n" + BOARD))
@click.argument("board", default="all")
@connection_options
@json_option
@click.pass_context
def xreset_cmd(ctx: click.Context, board: str, spec: ConnectSpec, bus_name: str | None,
               as_json: bool) -> None:
    ref = ops.parse_ref(board)
    with robot(spec) as r, needing_init(9):
        rows = ops.reset(r, ref, bus=bus_name, clear_autostart=True)
    if as_json:
        emit_with_connection(spec, render.rows_json(rows))
    else:
        render.print_reset(stdout(), rows, "XReset")
    finish(ctx, all(x.ok for x in rows))
