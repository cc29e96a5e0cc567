"""``ucom count``: option 13 of dsp_console2can, Count: the Info of every board that
has a number (a seq ID or a fixed ID)."""

from __future__ import annotations

import click

from ucom_tools.cli.commands.common import info_out
from ucom_tools.cli.menu import help_text
from ucom_tools.cli.options import connection_options, init_option, json_option, robot
from ucom_tools.ops import options as ops
from ucom_tools.ops.robot import ConnectSpec


@click.command("count", help=help_text(13, "Boards answer once they have a number: add "
                                           "--init before the first init chain.  With a "
                                           "topology, an expected board that does not answer "
                                           "makes the exit code 1."))
@connection_options
@init_option
@json_option
@click.pass_context
def count_cmd(ctx: click.Context, spec: ConnectSpec, bus_name: str | None, run_init: bool,
              as_json: bool) -> None:
    with robot(spec, run_init=run_init, bus=bus_name) as r:
        rows = ops.info(r, ops.BoardRef(None, ops.ALL), bus=bus_name)
    info_out(ctx, spec, rows, as_json, "Count")
