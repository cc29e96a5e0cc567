"""``ucom init``: option 2 of dsp_console2can, Init: run the init chain on every bus,
numbering the boards along the init line, and check the wiring against the topology
(a diagnosis when they differ)."""

from __future__ import annotations

import click

from ucom_tools.cli import render
from ucom_tools.cli.commands.common import finish
from ucom_tools.cli.menu import help_text
from ucom_tools.cli.options import connection_options, emit_with_connection, json_option, robot
from ucom_tools.cli.output import stdout
from ucom_tools.ops.enumerate import enumerate_bus
from ucom_tools.ops.robot import ConnectSpec


@click.command("init", help=help_text(2, "Per bus: the boards in chain order with seq ID and "
                                         "Info, compared with the boards the topology expects, "
                                         "and a diagnosis when they differ (broken init line, "
                                         "unpowered board, clashing fixed IDs) saying where to "
                                         "look and which LEDs tell.  Exit code 1 when a bus "
                                         "shows a fault."))
@connection_options
@click.option("--no-info", is_flag=True, help="Do not read every board's Info.")
@json_option
@click.pass_context
def init_cmd(ctx: click.Context, spec: ConnectSpec, bus_name: str | None, no_info: bool,
             as_json: bool) -> None:
    with robot(spec) as r:
        results = r.each(lambda h: enumerate_bus(h, with_info=not no_info), bus_name)
    if as_json:
        emit_with_connection(spec, {"buses": [render.enumeration_json(e) for e in results]})
    else:
        for e in results:
            render.print_enumeration(stdout(), e)
    finish(ctx, all(e.ok for e in results))
