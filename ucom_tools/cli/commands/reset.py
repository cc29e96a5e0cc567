"""``ucom reset``: option 1 of dsp_console2can, Reset All: reset every board and list
the boards that answered (those with a number: a seq ID or a fixed ID)."""

from __future__ import annotations

import click

from ucom_tools.cli import render
from ucom_tools.cli.commands.common import finish
from ucom_tools.cli.menu import help_text
from ucom_tools.cli.options import connection_options, emit_with_connection, json_option, robot
from ucom_tools.cli.output import stdout
from ucom_tools.ops import options as ops
from ucom_tools.ops.robot import ConnectSpec


@click.command("reset", help=help_text(1, "Boards answer once they have a number (seq ID "
                                          "from the init chain, or a fixed ID); a reset keeps "
                                          "the seq ID, a power cycle clears it.  With a "
                                          "topology, an expected board that does not answer "
                                          "makes the exit code 1."))
@connection_options
@json_option
@click.pass_context
def reset_cmd(ctx: click.Context, spec: ConnectSpec, bus_name: str | None, as_json: bool) -> None:
    with robot(spec) as r:
        rows = ops.reset(r, bus=bus_name)
    if as_json:
        emit_with_connection(spec, render.rows_json(rows))
    else:
        render.print_reset(stdout(), rows, "Reset All")
    finish(ctx, all(x.ok for x in rows))
