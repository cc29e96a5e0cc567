"""The console options of dsp_console2can as ``ucom`` subcommands, and ``ucom flash``.

Thin click glue: each command parses its arguments, runs an operation of
:mod:`ucom_tools.ops` and prints its result (a table, or JSON with ``--json``); the
exit code says how it went (:mod:`ucom_tools.cli.exitcodes`).  Help texts come from the
option table of :mod:`ucom_tools.cli.menu`, which the console shares.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import click
from rich.markup import escape

from ucom_tools.cli import render
from ucom_tools.cli.exitcodes import EXIT_FAILED, EXIT_INTERRUPTED
from ucom_tools.cli.menu import help_text, label, parse_level
from ucom_tools.cli.options import (
    connection_json,
    connection_options,
    init_option,
    json_option,
    robot,
)
from ucom_tools.cli.output import emit_json, stderr, stdout
from ucom_tools.errors import InputError, UcomError
from ucom_tools.ops import options as ops
from ucom_tools.ops.enumerate import enumerate_bus
from ucom_tools.ops.robot import ConnectSpec, Robot
from ucom_tools.signals import interrupt_exit_code, stop_signal, stopped_how
from ucom_tools.wire.codes import StatusOp, Target
from ucom_tools.wire.ids import IdType

if TYPE_CHECKING:  # imported where used, so that the other commands start without them
    from ucom_tools.ops import params_keep
    from ucom_tools.ops.flash_types import FlashRequest, FlashResult

BOARD = "BOARD is a seq ID (1-31), F<n> for a fixed ID, or 'all'; BUS:<n> picks one bus."
ONE_BOARD = "BOARD is a seq ID (1-31) or F<n> for a fixed ID; BUS:<n> picks one bus."


def _finish(ctx: click.Context, ok: bool) -> None:
    if not ok:
        ctx.exit(EXIT_FAILED)


def _json(spec: ConnectSpec, data: dict[str, Any]) -> None:
    """JSON on stdout, with the bus that was used."""
    emit_json({**data, "connection": connection_json(spec)})


def _verbose(ctx: click.Context) -> int:
    return int((ctx.find_root().obj or {}).get("verbose", 0))


def _rows(ctx: click.Context, spec: ConnectSpec, rows: list[ops.Row], as_json: bool,
          title: str) -> None:
    if as_json:
        _json(spec, render.rows_json(rows))
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
        rows = ops.reset(r, bus=bus_name, what=label(1))
    if as_json:
        _json(spec, render.rows_json(rows))
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
    with robot(spec) as r:
        rows = ops.reset(r, ref, bus=bus_name, clear_autostart=True, what=label(9))
    if as_json:
        _json(spec, render.rows_json(rows))
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
    with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r:
        rows = ops.reset(r, ref, bus=bus_name, what=label(21))
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
        _json(spec, {"buses": [render.enumeration_json(e) for e in results]})
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
    with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r:
        rows = ops.info(r, ref, bus=bus_name, what=label(3))
    _info_out(ctx, spec, rows, as_json, "GetInfo")


def _info_out(ctx: click.Context, spec: ConnectSpec, rows: list[ops.Row], as_json: bool,
              title: str) -> None:
    if as_json:
        _json(spec, {"boards": [{"bus": x.bus, **render.addr_json(x.address),
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
        rows = ops.info(r, ops.BoardRef(None, ops.ALL), bus=bus_name, what=label(13))
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
        with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r:
            rows = ops.set_status(r, ref, op, 0 if off else 1, what=label(option),
                                  bus=bus_name)
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
    with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r:
        rows = ops.start(r, ref, Target.EXTRAM if extram else Target.FLASH, bus=bus_name,
                         what=label(7))
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
        with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r:
            rows = ops.set_status(r, ref, op, value, what=label(option), bus=bus_name)
            status = (ops.board_status(r, ref, bus=bus_name)
                      if rows and all(x.ok for x in rows) else [])
        if as_json:
            data = render.rows_json(rows)
            data["status"] = [{"bus": b, "pins": s.pins, "leds": s.leds} for b, s in status]
            _json(spec, data)
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
    ref = ops.parse_ref(old, allow_all=False, what="OLD")
    with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r:
        rows = ops.set_seqid(r, ref, new, bus=bus_name, what=label(12))
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
            _json(spec, render.probe_json(results))
        else:
            render.print_probe(stdout(), results)
        _finish(ctx, all(len(p.answers) == 1 for p in results))
    return cmd


first_cmd = _probe_command("first", 14, False, "Two answers mean the init line is broken "
                           "(exit code 1).")
last_cmd = _probe_command("last", 15, True, "Found through its init output, the reverse "
                          "direction of the chain; two answers mean a broken line.")


# ----------------------------------------------------------------------------- 5, 6, flash
def _flash_out(ctx: click.Context, spec: ConnectSpec, result: FlashResult,
               as_json: bool, kept: params_keep.KeepResult | None = None) -> None:
    from ucom_tools.cli import params as params_cli

    if as_json:
        extra = {"keep_params": params_cli.kept_json(kept)} if kept is not None else {}
        _json(spec, {**render.flash_json(result), **extra})
    else:
        render.print_flash(stdout(), result)
        if kept is not None:
            params_cli.print_kept(stdout(), kept)
    if kept is not None and not kept.ok:
        names = ", ".join(b.where for b in kept.failed)
        stderr().print(f"[red]params not kept: {escape(names)}[/]", soft_wrap=True)
    if not result.all_verified or result.failed:
        names = ", ".join(
            (f"{b.bus}:{b.seq_id}" if b.seq_id else f"{b.bus}:{b.placement}")
            + ("" if b.verified else f" ({b.outcome})" if b.outcome != "failed"
               else " (not verified)")
            + (" (did not start)" if b.verified and b.started is False else "")
            for b in result.failed) or "no board found"
        stderr().print(f"[red]failed: {names}[/]", soft_wrap=True)
        ctx.exit(EXIT_FAILED)
    if kept is not None and not kept.ok:
        ctx.exit(EXIT_FAILED)


def _cancelled(ctx: click.Context, spec: ConnectSpec, e: BaseException, as_json: bool) -> None:
    """An interrupted flash: per board what it was left with (the table, or ``--json``
    with ``interrupted``), one line on stderr, the signal's exit code."""
    from ucom_tools.cli.flashrun import NotBegun
    from ucom_tools.ops.flash_types import FlashInterrupted

    how = stopped_how(e)
    if isinstance(e, FlashInterrupted):
        result = e.result
        if as_json:
            stop = stop_signal(e)
            _json(spec, {**render.flash_json(result), "interrupted": {
                "how": how, "signal": stop.name if stop is not None else "SIGINT",
                "buses": {b.bus: b.interrupted for b in result.buses}}})
        else:
            render.print_flash(stdout(), result)
        stderr().print(f"[yellow]{escape(render.interrupted_line(result, how))}[/]",
                       soft_wrap=True)
    elif isinstance(e, NotBegun):
        stderr().print(f"[yellow]flash {how} before it began: nothing was sent to any "
                       "board[/]", soft_wrap=True)
    else:  # a third signal cut the undo short
        stderr().print(f"[red]flash {how} again while putting the boards back: they are "
                       "left as they are (check them with 'ucom info all --init')[/]",
                       soft_wrap=True)
    ctx.exit(interrupt_exit_code(e) if isinstance(e, KeyboardInterrupt) else EXIT_INTERRUPTED)


def _stage(r: Robot, request: FlashRequest, phase: str, cancel: threading.Event) -> None:
    """Before the job: stop (nothing sent that changes a board) if cancelled."""
    from ucom_tools.ops.flash import interrupted_before
    from ucom_tools.ops.flash_types import FlashInterrupted

    if cancel.is_set():
        raise FlashInterrupted(interrupted_before(r, request, phase))


@dataclass
class _Flashed:
    """What ``ucom flash``'s worker did: refused before programming (the values to keep
    could not be read), or the result and the values kept."""

    kept: params_keep.Kept | None = None
    result: FlashResult | None = None
    restored: params_keep.KeepResult | None = None


@click.command("flash")
@click.argument("image", type=click.Path())
@click.option("--boards", default="all", show_default=True,
              help="'all' or seq IDs like 1,3 (on each selected bus).")
@click.option("--autostart", is_flag=True, help="Set AutoStart on every verified board.")
@click.option("--start", "start_after", is_flag=True, help="Start the verified boards.")
@click.option("--no-verify", is_flag=True,
              help="Skip reading back each board's Info after its verified transfer.")
@click.option("--force", is_flag=True,
              help="Program boards whose Board-ID, App-ID or FPGA major version do not fit "
                   "the image (with a warning); with --keep-params, also program when some "
                   "board's values could not be read.")
@click.option("--keep-params", is_flag=True,
              help="Keep the live PAR and CI values: before programming, read them from "
                   "every board that runs a program (checked against its attribute tree in "
                   "the topology); afterwards start the programs (implies --start) and load "
                   "the values back, read back to verify.  A board whose values cannot be "
                   "read (its program's edges differ from its tree, no answer) stops the job "
                   "before anything is programmed (exit code 1) unless --force.")
@connection_options
@json_option
@click.pass_context
def flash_cmd(ctx: click.Context, image: str, boards: str, autostart: bool,
              start_after: bool, no_verify: bool, force: bool, keep_params: bool,
              spec: ConnectSpec, bus_name: str | None, as_json: bool) -> None:
    """Program IMAGE (S-record or Intel HEX) into the boards of every bus, verified.

    Resets, runs the init chain with wiring checks, brings boards that run a program back
    to their bootloader, enables programming, sends the image once per bus (all buses in
    parallel), checks every board's ProgID, resends only the frames a board missed (on a
    bus that loses frames too), then sets AutoStart and starts the boards when asked.
    Option 20 (ProgAll) is 'flash --boards all'.  Boards the image does not fit (plug-on
    board, FPGA Board-ID, App-ID, FPGA major version) are refused unless --force.  Exit
    code 0 only when every selected board verified; with a topology, an expected board
    that never answered fails the job too.  Ctrl-C, SIGTERM or SIGHUP at any moment
    leaves every board with its old program intact, or in its bootloader with ProgEnable
    cleared and no transfer open (ABORT, then each board's Info read), and says which
    per board (exit code 130, 143, 129).

    With --keep-params the PAR and CI values of the boards that run a program are read
    first (into a temporary directory, as 'ucom params dump' writes them) and loaded back
    afterwards into the programs, started again (also on boards that were not
    programmed: the reset stopped them); the directory is left, and named, when a board
    did not get its values back.  Boards in their bootloader have nothing to keep."""
    from ucom_tools.cli.flashrun import (
        FORCE,
        as_finished,
        flash_progress,
        run_cancellable,
        with_force_hint,
    )
    from ucom_tools.image.formats import load_image
    from ucom_tools.ops import params_keep
    from ucom_tools.ops.flash import flash, interrupted_before, listen_first
    from ucom_tools.ops.flash_types import (
        KEEP,
        LISTENING,
        RESET,
        FlashInterrupted,
        FlashRequest,
        Selection,
    )
    from ucom_tools.protocol.programmer import Cancelled
    request = FlashRequest(load_image(image), selection=Selection.parse(boards), bus=bus_name,
                           autostart=autostart, start=start_after or keep_params,
                           verify=not no_verify, force=force)
    with robot(spec) as r:
        r.select(bus_name)  # an unknown --bus is exit code 3 before anything is sent

        out = _Flashed()

        def job(cancel: threading.Event) -> _Flashed:
            """All of it in the worker (run_cancellable): a signal only sets ``cancel``,
            looked at between the steps and throughout the flash."""
            _stage(r, request, LISTENING, cancel)
            listen_first(r, bus_name)  # another host programming: exit 4, nothing sent
            _stage(r, request, LISTENING, cancel)
            out.kept = params_keep.keep_before(r, bus=bus_name) if keep_params else None
            _stage(r, request, KEEP, cancel)
            if out.kept is not None and not out.kept.readout.ok and not force:
                return out
            with flash_progress(r, request.image, verbose=_verbose(ctx),
                                bus=bus_name) as report:
                for h in r.select(bus_name):
                    h.client.reset()
                _stage(r, request, RESET, cancel)
                out.result = with_force_hint(flash(r, request, progress=report,
                                                   cancel=cancel), FORCE)
            if out.kept is not None:
                out.restored = _keep_after(r, out.kept, out.result)
            return out

        try:
            done = run_cancellable(job, name="ucom-flash", finished=lambda out, stop: (
                as_finished(out.result, stop) if out.result is not None else FlashInterrupted(
                    interrupted_before(r, request, KEEP))))
        except (KeyboardInterrupt, Cancelled) as e:
            if isinstance(e, FlashInterrupted):
                e.result = with_force_hint(e.result, FORCE)
            if out.kept is not None and out.kept.directory is not None:
                stderr().print(f"[yellow]the values read before programming are in "
                               f"{escape(str(out.kept.directory))}[/]", soft_wrap=True)
            _cancelled(ctx, spec, e, as_json)
            return
        if done.result is None:
            assert done.kept is not None
            _keep_refused(ctx, spec, done.kept, as_json)
            return
    _flash_out(ctx, spec, done.result, as_json, done.restored)


def _keep_after(r: Robot, kept: params_keep.Kept, result: FlashResult) -> params_keep.KeepResult:
    """Load the kept values back; when that fails altogether, say where they are."""
    from ucom_tools.ops import params_keep

    try:
        return params_keep.keep_after(r, kept, {(b.bus, b.seq_id): b.outcome
                                               for b in result.boards})
    except (UcomError, KeyboardInterrupt):
        if kept.directory is not None:
            stderr().print(f"[yellow]the values read before programming are in "
                           f"{escape(str(kept.directory))}[/]", soft_wrap=True)
        raise


def _keep_refused(ctx: click.Context, spec: ConnectSpec, kept: params_keep.Kept,
                  as_json: bool) -> None:
    """flash --keep-params without --force when some board's values could not be read:
    nothing programmed, exit code 1."""
    from ucom_tools.cli import params as params_cli
    from ucom_tools.ops import params_keep

    report = params_keep.keep_refused(kept)
    if as_json:
        _json(spec, {"programmed": False, "keep_params": params_cli.kept_json(report)})
    else:
        params_cli.print_kept(stdout(), report)
    names = ", ".join(b.where for b in report.failed)
    stderr().print(f"[red]nothing programmed: the values of {escape(names)} could not be "
                   "read (--force programs anyway)[/]", soft_wrap=True)
    ctx.exit(EXIT_FAILED)


def _program_command(name: str, option: int, target: Target, detail: str) -> click.Command:
    @click.command(name, help=help_text(option, detail))
    @click.argument("board")
    @click.argument("image", type=click.Path())
    @click.option("--force", is_flag=True,
                  help="Program even when the image does not fit the board (with a warning).")
    @connection_options
    @init_option
    @json_option
    @click.pass_context
    def cmd(ctx: click.Context, board: str, image: str, force: bool, spec: ConnectSpec,
            bus_name: str | None, run_init: bool, as_json: bool) -> None:
        from ucom_tools.cli.flashrun import run_flash
        from ucom_tools.image.formats import load_image
        from ucom_tools.ops.flash_types import FlashRequest, Selection
        from ucom_tools.protocol.programmer import Cancelled

        ref = ops.parse_ref(board)
        img = load_image(image)
        if ref.is_all:
            selection = Selection("enabled")
        elif ref.address.id_type is IdType.FIXED:
            raise InputError("program by seq ID (run init first); fixed IDs are not used for "
                             "programming", key="BOARD")
        else:
            selection = Selection("list", (ref.address.number,))
        with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r:
            try:
                request = FlashRequest(img, selection=selection, bus=ref.bus or bus_name,
                                       target=target, init=False, force=force)
                result = run_flash(r, request, what=label(option), verbose=_verbose(ctx))
            except (KeyboardInterrupt, Cancelled) as e:
                _cancelled(ctx, spec, e, as_json)
                return
        _flash_out(ctx, spec, result, as_json)
    return cmd


program_cmd = _program_command(
    "program", 5, Target.FLASH,
    "Programs IMAGE into board BOARD, or with 'all' into every ProgEnabled board (see "
    "prog-enable); verified like 'flash'.\n\n" + BOARD)
extram_cmd = _program_command(
    "extram-load", 6, Target.EXTRAM,
    "Loads IMAGE into external RAM of BOARD instead of flash (gone after reset; start it "
    "with 'start --extram').\n\n" + BOARD)


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
        _json(spec, render.check_json(rows))
    else:
        render.print_check(stdout(), rows)
    _finish(ctx, bool(rows) and not any(x.failed for x in rows))

