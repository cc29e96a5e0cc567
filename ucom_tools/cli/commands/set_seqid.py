"""``ucom set-seqid``: option 12 of dsp_console2can, SetSeqID: give a board another seq
ID (refused, nothing sent, when another board of the bus holds it)."""

from __future__ import annotations

import click

from ucom_tools.cli.commands.common import rows_out
from ucom_tools.cli.menu import help_text
from ucom_tools.cli.options import (
    connection_options,
    init_option,
    json_option,
    needing_init,
    robot,
)
from ucom_tools.ops import options as ops
from ucom_tools.ops.robot import ConnectSpec


@click.command("set-seqid", help=help_text(12, "OLD is the board's seq ID (BUS:<n> picks a "
                                               "bus), NEW the seq ID it takes.  A NEW that "
                                               "another board of the bus holds is refused "
                                               "(exit code 3, nothing sent)."))
@click.argument("old")
@click.argument("new", type=click.IntRange(1, 31))
@connection_options
@init_option
@json_option
@click.pass_context
def set_seqid_cmd(ctx: click.Context, old: str, new: int, spec: ConnectSpec,
                  bus_name: str | None, run_init: bool, as_json: bool) -> None:
    ref = ops.parse_ref(old, allow_all=False, key="OLD")
    with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r, needing_init(12):
        rows = ops.set_seqid(r, ref, new, bus=bus_name)
    rows_out(ctx, spec, rows, as_json, f"set-seqid {old} -> {new}")
