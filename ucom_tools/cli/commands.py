"""The console options of dsp_console2can as ``ucom`` subcommands, and ``ucom flash``."""

from __future__ import annotations

import threading
from typing import Any

import click

from ucom_tools.cli import render
from ucom_tools.cli.connect import connection_options, init_option, json_option, robot
from ucom_tools.cli.main import EXIT_FAILED, EXIT_INTERRUPTED
from ucom_tools.cli.output import emit_json, stderr, stdout
from ucom_tools.errors import InputError
from ucom_tools.image import Image, load_image
from ucom_tools.ops import boards as ops
from ucom_tools.ops.enumerate import enumerate_bus
from ucom_tools.ops.flash import FlashResult, Selection, flash
from ucom_tools.ops.robot import ConnectSpec, Robot
from ucom_tools.protocol.programmer import Cancelled
from ucom_tools.wire.codes import StatusOp, Target
from ucom_tools.wire.ids import IdType

BOARD = "BOARD is a seq ID (1-31), F<n> for a fixed ID, or 'all'; BUS:<n> picks one bus."


def _finish(ctx: click.Context, ok: bool) -> None:
    if not ok:
        ctx.exit(EXIT_FAILED)


def _rows(ctx: click.Context, rows: list[ops.Row], as_json: bool, title: str) -> None:
    if as_json:
        emit_json(render.rows_json(rows))
    else:
        render.print_rows(stdout(), rows, title)
    _finish(ctx, bool(rows) and all(r.ok for r in rows))


def _level(text: str) -> int:
    t = text.strip().lower()
    if t in ("set", "1", "lo", "low", "on"):
        return 1
    if t in ("release", "0", "hi", "high", "off"):
        return 0
    raise InputError(f"{text!r}: LEVEL is 'set' (drive the pin low) or 'release'", key="LEVEL")


def _image(path: str) -> Image:
    return load_image(path)


# ----------------------------------------------------------------------------- 1, 9, 21
@click.command("reset")
@connection_options
@json_option
@click.pass_context
def reset_cmd(ctx: click.Context, spec: ConnectSpec, bus_name: str | None, as_json: bool) -> None:
    """Option 1, Reset All: reset every board and list who answered (who is alive).

    Boards answer once they have a number (seq ID from the init chain, or a fixed ID);
    a reset keeps the seq ID, a power cycle clears it."""
    with robot(spec) as r:
        rows = ops.reset(r, bus=bus_name)
    if as_json:
        emit_json(render.rows_json(rows))
    else:
        render.print_reset(stdout(), rows, "Reset All")


@click.command("xreset", help="Option 9, XReset: clear the AutoStart flag and reset "
               "(default: every board).\n\n" + BOARD)
@click.argument("board", default="all")
@connection_options
@json_option
@click.pass_context
def xreset_cmd(ctx: click.Context, board: str, spec: ConnectSpec, bus_name: str | None,
               as_json: bool) -> None:
    ref = ops.parse_ref(board)
    with robot(spec) as r:
        rows = ops.reset(r, ref, bus=bus_name, clear_autostart=True)
    if as_json:
        emit_json(render.rows_json(rows))
    else:
        render.print_reset(stdout(), rows, "XReset")


@click.command("reset-one")
@click.argument("board")
@connection_options
@init_option
@json_option
@click.pass_context
def reset_one_cmd(ctx: click.Context, board: str, spec: ConnectSpec, bus_name: str | None,
                  run_init: bool, as_json: bool) -> None:
    """Option 21, Reset Specific: reset one board (needs a completed init).

    BOARD is a seq ID (1-31) or F<n> for a fixed ID; BUS:<n> picks one bus."""
    ref = ops.parse_ref(board, allow_all=False)
    with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r:
        rows = ops.reset(r, ref, bus=bus_name)
    _rows(ctx, rows, as_json, f"Reset board {ref}")


# ----------------------------------------------------------------------------- 2
@click.command("init")
@connection_options
@click.option("--no-info", is_flag=True, help="Do not read every board's Info.")
@json_option
@click.pass_context
def init_cmd(ctx: click.Context, spec: ConnectSpec, bus_name: str | None, no_info: bool,
             as_json: bool) -> None:
    """Option 2, Init: number the boards along the init line and check the wiring.

    Per bus: the boards in chain order with seq ID and Info, compared with the boards the
    topology expects, and a diagnosis when they differ (broken init line, unpowered
    board, clashing fixed IDs) saying where to look and which LEDs tell.  Exit code 1
    when a bus shows a fault."""
    with robot(spec) as r:
        results = [enumerate_bus(h, with_info=not no_info) for h in r.select(bus_name)]
    if as_json:
        emit_json({"buses": [render.enumeration_json(e) for e in results]})
    else:
        for e in results:
            render.print_enumeration(stdout(), e)
    _finish(ctx, all(e.ok for e in results))


# ----------------------------------------------------------------------------- 3, 13, 16/17
@click.command("info", help="Option 3, GetInfo: program name, date, ProgID, size, flags of "
               "a board (needs init).\n\n" + BOARD)
@click.argument("board")
@connection_options
@init_option
@json_option
@click.pass_context
def info_cmd(ctx: click.Context, board: str, spec: ConnectSpec, bus_name: str | None,
             run_init: bool, as_json: bool) -> None:
    ref = ops.parse_ref(board)
    with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r:
        rows = ops.info(r, ref, bus=bus_name)
    _info_out(ctx, rows, as_json, "GetInfo")


def _info_out(ctx: click.Context, rows: list[ops.Row], as_json: bool, title: str) -> None:
    if as_json:
        emit_json({"boards": [{"bus": x.bus, **render.addr_json(x.address), "ok": x.ok,
                               "detail": x.detail,
                               **(render.info_json(x.info) if x.info else {})} for x in rows]})
    elif rows:
        render.print_infos(stdout(), rows, title)
    else:
        stdout().print(f"[yellow]{title}: no board answered[/]")
    _finish(ctx, bool(rows) and all(x.ok for x in rows))


@click.command("count")
@connection_options
@init_option
@json_option
@click.pass_context
def count_cmd(ctx: click.Context, spec: ConnectSpec, bus_name: str | None, run_init: bool,
              as_json: bool) -> None:
    """Option 13, Count: GetInfo of every board that has a number."""
    with robot(spec, run_init=run_init, bus=bus_name) as r:
        rows = ops.info(r, ops.BoardRef(None, ops.ALL), bus=bus_name)
    _info_out(ctx, rows, as_json, "Count")


@click.command("list")
@connection_options
@init_option
@json_option
@click.pass_context
def list_cmd(ctx: click.Context, spec: ConnectSpec, bus_name: str | None, run_init: bool,
             as_json: bool) -> None:
    """Options 16 and 17: build and print the list of active boards (DSP list)."""
    with robot(spec, run_init=run_init, bus=bus_name) as r:
        rows = ops.dsp_list(r, bus=bus_name)
    _info_out(ctx, rows, as_json, "DSP list")


# ----------------------------------------------------------------------------- 4, 7, 8
def _status_command(name: str, option: int, op: StatusOp, doc: str) -> click.Command:
    @click.command(name, help=doc + "\n\n" + BOARD)
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
            rows = ops.set_status(r, ref, op, 0 if off else 1, option=option, bus=bus_name)
        _rows(ctx, rows, as_json, f"{name} {board}" + (" off" if off else ""))
    return cmd


prog_enable_cmd = _status_command(
    "prog-enable", 4, StatusOp.PROG_ENABLE,
    "Option 4, SetProgEnable: enable programming of one board or all (needs init).")
autostart_cmd = _status_command(
    "autostart", 8, StatusOp.AUTOSTART,
    "Option 8, SetAutoStart: start the flash program right after every reset.")


@click.command("start", help="Option 7, Start: start the program in flash (or ExtRAM) and "
               "show its messages.\n\n" + BOARD)
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
        rows = ops.start(r, ref, Target.EXTRAM if extram else Target.FLASH, bus=bus_name)
    _rows(ctx, rows, as_json, f"Start {board}")


# ----------------------------------------------------------------------------- 10, 11, 12
def _pin_command(name: str, option: int, op: StatusOp, doc: str) -> click.Command:
    @click.command(name, help=doc + " LEVEL is 'set' (drive the pin low) or 'release'; the "
                   "board's LEDs show it.\n\nBOARD is a seq ID or F<n>; BUS:<n> picks a bus.")
    @click.argument("board")
    @click.argument("level")
    @connection_options
    @init_option
    @json_option
    @click.pass_context
    def cmd(ctx: click.Context, board: str, level: str, spec: ConnectSpec,
            bus_name: str | None, run_init: bool, as_json: bool) -> None:
        ref = ops.parse_ref(board, allow_all=False)
        value = _level(level)
        with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r:
            rows = ops.set_status(r, ref, op, value, option=option, bus=bus_name)
            status = (ops.board_status(r, ref, bus=bus_name)
                      if rows and all(x.ok for x in rows) else [])
        if as_json:
            data = render.rows_json(rows)
            data["status"] = [{"bus": b, "pins": s.pins, "leds": s.leds} for b, s in status]
            emit_json(data)
        else:
            render.print_rows(stdout(), rows, f"{name} {board} {level}")
            for b, s in status:
                stdout().print(f"{b} board {ref.address}: LEDs {render.status_leds(s)}")
        _finish(ctx, bool(rows) and all(x.ok for x in rows))
    return cmd


set_init_in_cmd = _pin_command("set-init-in", 10, StatusOp.INIT_IN,
                               "Option 10, SetInitIn: drive one board's init input (debugging).")
set_init_out_cmd = _pin_command("set-init-out", 11, StatusOp.INIT_OUT,
                                "Option 11, SetInitOut: drive one board's init output.")


@click.command("set-seqid")
@click.argument("old")
@click.argument("new", type=click.IntRange(1, 31))
@connection_options
@init_option
@json_option
@click.pass_context
def set_seqid_cmd(ctx: click.Context, old: str, new: int, spec: ConnectSpec,
                  bus_name: str | None, run_init: bool, as_json: bool) -> None:
    """Option 12, SetSeqID: give the board with seq ID OLD the seq ID NEW (needs init)."""
    ref = ops.parse_ref(old, allow_all=False, what="OLD")
    with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r:
        rows = ops.set_status(r, ref, StatusOp.SEQ_ID, new, option=12, bus=bus_name)
    _rows(ctx, rows, as_json, f"set-seqid {old} -> {new}")


# ----------------------------------------------------------------------------- 14, 15
def _probe_command(name: str, last: bool, doc: str) -> click.Command:
    @click.command(name, help=doc)
    @connection_options
    @json_option
    @click.pass_context
    def cmd(ctx: click.Context, spec: ConnectSpec, bus_name: str | None, as_json: bool) -> None:
        with robot(spec) as r:
            results = ops.probe(r, last=last, bus=bus_name)
        if as_json:
            emit_json(render.probe_json(results))
        else:
            render.print_probe(stdout(), results)
        _finish(ctx, all(len(p.answers) == 1 for p in results))
    return cmd


first_cmd = _probe_command("first", False, "Option 14, Get First: which board is first on the "
                           "init line; two answers mean the init line is broken.")
last_cmd = _probe_command("last", True, "Option 15, Get Last: which board is last on the init "
                          "line (found through its init output).")


# ----------------------------------------------------------------------------- 5, 6, flash
def run_flash(r: Robot, image: Image, **kwargs: Any) -> FlashResult:
    """Run a flash operation with progress on a TTY; Ctrl-C cancels it cleanly."""
    from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn, TransferSpeedColumn

    cancel = threading.Event()
    box: dict[str, Any] = {}
    progress = None
    if stderr().is_terminal:
        progress = Progress(TextColumn("{task.description}"), BarColumn(), DownloadColumn(),
                            TransferSpeedColumn(), TextColumn("{task.fields[boards]} board(s)"),
                            console=stderr(), transient=True)
        tasks: dict[str, Any] = {}
        lock = threading.Lock()

        def report(bus: str, sent: int, total: int, boards: int) -> None:
            with lock:
                if bus not in tasks:
                    tasks[bus] = progress.add_task(bus, total=total, boards=boards)
            progress.update(tasks[bus], completed=sent, boards=boards)

        kwargs["progress"] = report

    def work() -> None:
        try:
            box["result"] = flash(r, image, cancel=cancel, **kwargs)
        except BaseException as e:  # handed to the main thread below
            box["error"] = e

    worker = threading.Thread(target=work, name="ucom-flash")
    if progress is not None:
        progress.start()
    worker.start()
    try:
        while worker.is_alive():
            worker.join(0.1)
    except KeyboardInterrupt:
        cancel.set()
        worker.join()
        raise
    finally:
        if progress is not None:
            progress.stop()
    if "error" in box:
        raise box["error"]
    return box["result"]


def _flash_out(ctx: click.Context, result: FlashResult, as_json: bool) -> None:
    if as_json:
        emit_json(render.flash_json(result))
    else:
        render.print_flash(stdout(), result)
    if not result.all_verified or result.failed:
        names = ", ".join((f"{b.bus}:{b.seq_id}" if b.seq_id else f"{b.bus}:{b.placement}")
                          + ("" if b.verified else f" ({b.outcome})" if b.outcome != "failed"
                             else " (not verified)")
                          + (" (did not start)" if b.verified and b.started is False else "")
                          for b in result.failed) or "no board found"
        stderr().print(f"[red]failed: {names}[/]")
        ctx.exit(EXIT_FAILED)


@click.command("flash")
@click.argument("image", type=click.Path(dir_okay=False))
@click.option("--boards", default="all", show_default=True,
              help="'all' or seq IDs like 1,3 (on each selected bus).")
@click.option("--autostart", is_flag=True, help="Set AutoStart on every verified board.")
@click.option("--start", "start_after", is_flag=True, help="Start the verified boards.")
@click.option("--no-verify", is_flag=True,
              help="Skip reading back each board's Info after its verified transfer.")
@click.option("--force", is_flag=True,
              help="Program boards whose Board-ID, App-ID or FPGA major version do not fit "
                   "the image (with a warning).")
@connection_options
@json_option
@click.pass_context
def flash_cmd(ctx: click.Context, image: str, boards: str, autostart: bool,
              start_after: bool, no_verify: bool, force: bool, spec: ConnectSpec,
              bus_name: str | None, as_json: bool) -> None:
    """Program IMAGE (S-record) into the boards of every bus, verified.

    Resets, runs the init chain with wiring checks, brings boards that run a program back
    to their bootloader, enables programming, sends the image once per bus (all buses in
    parallel), checks every board's ProgID, resends only what a board missed, then sets
    AutoStart and starts the boards when asked.  Option 20 (ProgAll) is
    'flash --boards all'.  Boards the image does not fit (plug-on board, FPGA Board-ID,
    App-ID, FPGA major version) are refused unless --force.  Exit code 0 only when every
    selected board verified."""
    img = _image(image)
    selection = Selection.parse(boards)
    with robot(spec) as r:
        for h in r.select(bus_name):
            h.client.reset()
        try:
            result = run_flash(r, img, selection=selection, bus=bus_name, autostart=autostart,
                               start=start_after, verify=not no_verify, force=force)
        except (KeyboardInterrupt, Cancelled):
            stderr().print("[yellow]flash cancelled: the boards dropped the transfer and keep no "
                      "startable program[/]")
            ctx.exit(EXIT_INTERRUPTED)
    _flash_out(ctx, result, as_json)


def _program_command(name: str, target: Target, doc: str) -> click.Command:
    @click.command(name, help=doc)
    @click.argument("board")
    @click.argument("image", type=click.Path(dir_okay=False))
    @click.option("--force", is_flag=True,
                  help="Program even when the image does not fit the board (with a warning).")
    @connection_options
    @init_option
    @json_option
    @click.pass_context
    def cmd(ctx: click.Context, board: str, image: str, force: bool, spec: ConnectSpec,
            bus_name: str | None, run_init: bool, as_json: bool) -> None:
        ref = ops.parse_ref(board)
        img = _image(image)
        if ref.is_all:
            selection = Selection("enabled")
        elif ref.address.id_type is IdType.FIXED:
            raise InputError("program by seq ID (run init first); fixed IDs are not used for "
                             "programming", key="BOARD")
        else:
            selection = Selection("list", (ref.address.number,))
        with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r:
            try:
                result = run_flash(r, img, selection=selection, bus=ref.bus or bus_name,
                                   target=target, init=False, force=force)
            except (KeyboardInterrupt, Cancelled):
                stderr().print("[yellow]cancelled[/]")
                ctx.exit(EXIT_INTERRUPTED)
        _flash_out(ctx, result, as_json)
    return cmd


program_cmd = _program_command(
    "program", Target.FLASH,
    "Option 5, Program: program IMAGE into board BOARD, or into every ProgEnabled board "
    "with 'all' (needs init; see prog-enable).  Verified like 'flash'.")
extram_cmd = _program_command(
    "extram-load", Target.EXTRAM,
    "Option 6, ExtRAMLoad: load IMAGE into external RAM of BOARD instead of flash (gone "
    "after reset; start it with 'start --extram').")


@click.command("check")
@connection_options
@json_option
@click.pass_context
def check_cmd(ctx: click.Context, spec: ConnectSpec, bus_name: str | None, as_json: bool) -> None:
    """Compatibility matrix: plug-on board, FPGA and stored DSP program of every board.

    Runs the init chain, reads every board's Info (FPGA version registers, measured
    Board-ID, the stored program's descriptor) and judges each board: ok, warning (FPGA
    minor version, program without descriptor), mismatch (plug-on board vs FPGA, Board-ID,
    App-ID, FPGA major version) or no program.  Exit code 1 when a board mismatches."""
    from ucom_tools.ops.compat import check

    with robot(spec) as r:
        rows = check(r, bus=bus_name)
    if as_json:
        emit_json(render.check_json(rows))
    else:
        render.print_check(stdout(), rows)
    _finish(ctx, bool(rows) and not any(x.failed for x in rows))


COMMANDS = [check_cmd, reset_cmd, init_cmd, info_cmd, prog_enable_cmd, program_cmd, extram_cmd,
            start_cmd, autostart_cmd, xreset_cmd, set_init_in_cmd, set_init_out_cmd,
            set_seqid_cmd, count_cmd, first_cmd, last_cmd, list_cmd, reset_one_cmd, flash_cmd]

