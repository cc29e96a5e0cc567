"""``ucom info``: option 3 of dsp_console2can, GetInfo: a board's (or every board's)
Info: program name, date, ProgID, flags."""

from __future__ import annotations

import click

from ucom_tools.cli.commands.common import info_out
from ucom_tools.cli.menu import BOARD, help_text
from ucom_tools.cli.options import (
    connection_options,
    init_option,
    json_option,
    needing_init,
    robot,
)
from ucom_tools.ops import options as ops
from ucom_tools.ops.robot import ConnectSpec


@click.command("info", help=help_text(3, BOARD))
@click.argument("board")
@connection_options
@init_option
@json_option
@click.pass_context
def info_cmd(ctx: click.Context, board: str, spec: ConnectSpec, bus_name: str | None,
             run_init: bool, as_json: bool) -> None:
    ref = ops.parse_ref(board)
    with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r, needing_init(3):
        rows = ops.info(r, ref, bus=bus_name)
    info_out(ctx, spec, rows, as_json, "GetInfo")
