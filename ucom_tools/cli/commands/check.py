"""``ucom check``: not an option of dsp_console2can but built from its steps (init chain,
GetInfo): the compatibility matrix of plug-on board, FPGA and stored DSP program of every
board, judged per board (:mod:`ucom_tools.ops.compat`)."""

from __future__ import annotations

import click

from ucom_tools.cli import render
from ucom_tools.cli.commands.common import finish
from ucom_tools.cli.options import connection_options, emit_with_connection, json_option, robot
from ucom_tools.cli.output import stdout
from ucom_tools.ops.robot import ConnectSpec


@click.command("check")
@connection_options
@json_option
@click.pass_context
def check_cmd(ctx: click.Context, spec: ConnectSpec, bus_name: str | None, as_json: bool) -> None:
    """Compatibility matrix: plug-on board, FPGA and stored DSP program of every board.

    Runs the init chain, reads every board's Info (FPGA version registers, measured
    Board-ID, the stored program's descriptor) and judges each board: ok, warning (FPGA
    minor version, program without descriptor), mismatch (plug-on board vs FPGA, Board-ID,
    App-ID, FPGA major version), no program, or missing (expected by the topology, no
    answer).  Exit code 1 when a board mismatches or is missing."""
    from ucom_tools.ops.compat import check

    with robot(spec) as r:
        rows = check(r, bus=bus_name)
    if as_json:
        emit_with_connection(spec, render.check_json(rows))
    else:
        render.print_check(stdout(), rows)
    finish(ctx, bool(rows) and not any(x.failed for x in rows))
