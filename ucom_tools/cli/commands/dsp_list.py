"""``ucom list``: options 16 and 17 of dsp_console2can in one, DSPListUpdate and Print
DspList: build the list of active boards and print it.  (The module is not ``list.py``,
which would read as the builtin.)"""

from __future__ import annotations

import click

from ucom_tools.cli.commands.common import info_out
from ucom_tools.cli.menu import help_text
from ucom_tools.cli.options import connection_options, init_option, json_option, robot
from ucom_tools.ops import options as ops
from ucom_tools.ops.robot import ConnectSpec


@click.command("list", help=help_text(16, "Options 16 and 17 in one: build and print the "
                                          "list of active boards."))
@connection_options
@init_option
@json_option
@click.pass_context
def list_cmd(ctx: click.Context, spec: ConnectSpec, bus_name: str | None, run_init: bool,
             as_json: bool) -> None:
    with robot(spec, run_init=run_init, bus=bus_name) as r:
        rows = ops.dsp_list(r, bus=bus_name)
    info_out(ctx, spec, rows, as_json, "DSP list")
