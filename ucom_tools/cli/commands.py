"""The console options of dsp_console2can as ``ucom`` subcommands, and ``ucom flash``.

Thin click glue: each command parses its arguments, runs an operation of
:mod:`ucom_tools.ops` and prints its result (a table, or JSON with ``--json``); the
exit code says how it went (:mod:`ucom_tools.cli.exitcodes`).  Help texts come from the
option table of :mod:`ucom_tools.cli.menu`, which the console shares.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import click

from ucom_tools.cli import render
from ucom_tools.cli.exitcodes import EXIT_FAILED
from ucom_tools.cli.menu import BOARD, ONE_BOARD, help_text, parse_level
from ucom_tools.cli.options import (
    connection_options,
    emit_with_connection,
    init_option,
    json_option,
    needing_init,
    robot,
)
from ucom_tools.cli.output import stdout
from ucom_tools.ops import options as ops
from ucom_tools.ops.enumerate import enumerate_bus
from ucom_tools.ops.robot import ConnectSpec
from ucom_tools.wire.codes import StatusOp, Target

if TYPE_CHECKING:  # imported where used, so that the other commands start without them
    pass



def _finish(ctx: click.Context, ok: bool) -> None:
    if not ok:
        ctx.exit(EXIT_FAILED)


def _rows(ctx: click.Context, spec: ConnectSpec, rows: list[ops.Row], as_json: bool,
          title: str) -> None:
    if as_json:
        emit_with_connection(spec, render.rows_json(rows))
    else:
        render.print_rows(stdout(), rows, title)
    _finish(ctx, bool(rows) and all(r.ok for r in rows))


# ----------------------------------------------------------------------------- 1, 9, 21
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
    _finish(ctx, all(x.ok for x in rows))


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
    _finish(ctx, all(x.ok for x in rows))


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
    _rows(ctx, spec, rows, as_json, f"Reset board {ref}")


# ----------------------------------------------------------------------------- 2
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
    _finish(ctx, all(e.ok for e in results))


# ----------------------------------------------------------------------------- 3, 13, 16/17
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
    _info_out(ctx, spec, rows, as_json, "GetInfo")


def _info_out(ctx: click.Context, spec: ConnectSpec, rows: list[ops.Row], as_json: bool,
              title: str) -> None:
    if as_json:
        emit_with_connection(spec, {"boards": [{"bus": x.bus, **render.addr_json(x.address),
                                 "placement": x.placement, "ok": x.ok, "detail": x.detail,
                                 **(render.info_json(x.info) if x.info else {})}
                                for x in rows]})
    elif rows:
        render.print_infos(stdout(), rows, title)
    else:
        stdout().print(f"[yellow]{title}: no board answered[/] (boards answer once they "
                       "have a number: run 'ucom init', or add --init)")
    _finish(ctx, bool(rows) and all(x.ok for x in rows))


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
    _info_out(ctx, spec, rows, as_json, "Count")


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
    _info_out(ctx, spec, rows, as_json, "DSP list")


# ----------------------------------------------------------------------------- 4, 8
def _status_command(name: str, option: int, op: StatusOp) -> click.Command:
    @click.command(name, help=help_text(option, BOARD))
    @click.argument("board")
    @connection_options
    @init_option
    @json_option
    @click.option("--off", is_flag=True, help="Clear the flag instead of setting it.")
    @click.pass_context
    def cmd(ctx: click.Context, board: str, spec: ConnectSpec, bus_name: str | None,
            run_init: bool, as_json: bool, off: bool) -> None:
        ref = ops.parse_ref(board)
        with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r, \
                needing_init(option):
            rows = ops.set_status(r, ref, op, 0 if off else 1, bus=bus_name)
        _rows(ctx, spec, rows, as_json, f"{name} {board}" + (" off" if off else ""))
    return cmd


prog_enable_cmd = _status_command("prog-enable", 4, StatusOp.PROG_ENABLE)
autostart_cmd = _status_command("autostart", 8, StatusOp.AUTOSTART)


# ----------------------------------------------------------------------------- 7
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
    _rows(ctx, spec, rows, as_json, f"Start {board}" + (" (ExtRAM)" if extram else ""))


# ----------------------------------------------------------------------------- 10, 11, 12
def _pin_command(name: str, option: int, op: StatusOp) -> click.Command:
    @click.command(name, help=help_text(option, "LEVEL is 'set' (drive the pin low) or "
                                                "'release'; the board's LEDs show it.\n\n"
                                        + ONE_BOARD))
    @click.argument("board")
    @click.argument("level")
    @connection_options
    @init_option
    @json_option
    @click.pass_context
    def cmd(ctx: click.Context, board: str, level: str, spec: ConnectSpec,
            bus_name: str | None, run_init: bool, as_json: bool) -> None:
        ref = ops.parse_ref(board, allow_all=False)
        value = parse_level(level)
        with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r, \
                needing_init(option):
            rows = ops.set_status(r, ref, op, value, bus=bus_name)
            status = (ops.board_status(r, ref, bus=bus_name)
                      if rows and all(x.ok for x in rows) else [])
        if as_json:
            data = render.rows_json(rows)
            data["status"] = [{"bus": b, "pins": s.pins, "leds": s.leds} for b, s in status]
            emit_with_connection(spec, data)
        else:
            render.print_rows(stdout(), rows, f"{name} {board} {level}")
            for b, s in status:
                stdout().print(f"{b} board {ref.address}: LEDs {render.status_leds(s)}")
        _finish(ctx, bool(rows) and all(x.ok for x in rows))
    return cmd


set_init_in_cmd = _pin_command("set-init-in", 10, StatusOp.INIT_IN)
set_init_out_cmd = _pin_command("set-init-out", 11, StatusOp.INIT_OUT)


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
    _rows(ctx, spec, rows, as_json, f"set-seqid {old} -> {new}")


# ----------------------------------------------------------------------------- 14, 15
def _probe_command(name: str, option: int, last: bool, detail: str) -> click.Command:
    @click.command(name, help=help_text(option, detail))
    @connection_options
    @json_option
    @click.pass_context
    def cmd(ctx: click.Context, spec: ConnectSpec, bus_name: str | None, as_json: bool) -> None:
        with robot(spec) as r:
            results = ops.probe(r, last=last, bus=bus_name)
        if as_json:
            emit_with_connection(spec, render.probe_json(results))
        else:
            render.print_probe(stdout(), results)
        _finish(ctx, all(len(p.answers) == 1 for p in results))
    return cmd


first_cmd = _probe_command("first", 14, False, "Two answers mean the init line is broken "
                           "(exit code 1).")
last_cmd = _probe_command("last", 15, True, "Found through its init output, the reverse "
                          "direction of the chain; two answers mean a broken line.")


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
    _finish(ctx, bool(rows) and not any(x.failed for x in rows))

