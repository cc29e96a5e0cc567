"""``ucom start``: option 7 of dsp_console2can, Start: start the program of a board (or
all) in flash, or with ``--extram`` the one loaded into external RAM, showing the
messages it sends as it starts."""

from __future__ import annotations

import click

from ucom_tools.cli.commands.common import rows_out
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
from ucom_tools.wire.codes import Target


@click.command("start", help=help_text(7, "Shows the messages the program sends as it "
                                          "starts (its compatibility check).\n\n" + BOARD))
@click.argument("board")
@click.option("--extram", is_flag=True, help="Start the program loaded into external RAM.")
@connection_options
@init_option
@json_option
@click.pass_context
def start_cmd(ctx: click.Context, board: str, extram: bool, spec: ConnectSpec,
              bus_name: str | None, run_init: bool, as_json: bool) -> None:
    ref = ops.parse_ref(board)
    with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r, needing_init(7):
        rows = ops.start(r, ref, Target.EXTRAM if extram else Target.FLASH, bus=bus_name)
    rows_out(ctx, spec, rows, as_json, f"Start {board}" + (" (ExtRAM)" if extram else ""))
