"""``ucom reset-one``: option 21 of dsp_console2can, Reset Specific: reset one board (by
seq ID, or fixed ID)."""

from __future__ import annotations

import click

from ucom_tools.cli.commands.common import rows_out
from ucom_tools.cli.menu import ONE_BOARD, help_text
from ucom_tools.cli.options import (
    connection_options,
    init_option,
    json_option,
    needing_init,
    robot,
)
from ucom_tools.ops import options as ops
from ucom_tools.ops.robot import ConnectSpec


@click.command("reset-one", help=help_text(21, ONE_BOARD))
@click.argument("board")
@connection_options
@init_option
@json_option
@click.pass_context
def reset_one_cmd(ctx: click.Context, board: str, spec: ConnectSpec, bus_name: str | None,
                  run_init: bool, as_json: bool) -> None:
    ref = ops.parse_ref(board, allow_all=False)
    with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r, needing_init(21):
        rows = ops.reset(r, ref, bus=bus_name)
    rows_out(ctx, spec, rows, as_json, f"Reset board {ref}")
