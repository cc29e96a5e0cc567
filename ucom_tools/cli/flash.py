"""``ucom flash`` (an image into the boards of every bus, verified; ``--keep-params``),
and what the console's options 5 and 6 share with it: what they ask of
:mod:`ucom_tools.ops.flash`, what they say (:func:`flash_out`), how an interrupted one
ends (:func:`cancelled`), and the factory of their commands (:func:`program_command`),
called once each in :mod:`ucom_tools.cli.commands.program` (``ucom program``) and
:mod:`ucom_tools.cli.commands.extram_load` (``ucom extram-load``)."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING

import click
from rich.markup import escape

from ucom_tools.cli import render
from ucom_tools.cli.exitcodes import EXIT_FAILED, EXIT_INTERRUPTED
from ucom_tools.cli.menu import help_text
from ucom_tools.cli.options import (
    connection_options,
    emit_with_connection,
    init_option,
    json_option,
    needing_init,
    robot,
    verbosity,
)
from ucom_tools.cli.output import stderr, stdout
from ucom_tools.errors import InputError, UcomError
from ucom_tools.ops import options as ops
from ucom_tools.ops.robot import ConnectSpec, Robot
from ucom_tools.signals import interrupt_exit_code, stop_signal, stopped_how
from ucom_tools.wire.codes import Target
from ucom_tools.wire.ids import IdType

if TYPE_CHECKING:  # imported where used, so that the other commands start without them
    from ucom_tools.ops import params_keep
    from ucom_tools.ops.flash_types import FlashRequest, FlashResult


def flash_out(ctx: click.Context, spec: ConnectSpec, result: FlashResult,
              as_json: bool, kept: params_keep.KeepResult | None = None) -> None:
    """A finished flash (``flash``, ``program``, ``extram-load``): the table or JSON, the
    boards that failed on stderr, exit code 1 unless every selected board verified (and,
    with ``--keep-params``, got its values back)."""
    from ucom_tools.cli import params as params_cli

    if as_json:
        extra = {"keep_params": params_cli.kept_json(kept)} if kept is not None else {}
        emit_with_connection(spec, {**render.flash_json(result), **extra})
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


def cancelled(ctx: click.Context, spec: ConnectSpec, e: BaseException, as_json: bool) -> None:
    """An interrupted flash: per board what it was left with (the table, or ``--json``
    with ``interrupted``), one line on stderr, the signal's exit code."""
    from ucom_tools.cli.flashrun import NotBegun
    from ucom_tools.ops.flash_types import FlashInterrupted

    how = stopped_how(e)
    if isinstance(e, FlashInterrupted):
        result = e.result
        if as_json:
            stop = stop_signal(e)
            emit_with_connection(spec, {**render.flash_json(result), "interrupted": {
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
    from ucom_tools.cli.flashrun import FORCE, as_finished, run_cancellable, with_force_hint
    from ucom_tools.image.formats import load_image
    from ucom_tools.ops.flash import interrupted_before
    from ucom_tools.ops.flash_types import KEEP, FlashInterrupted, FlashRequest, Selection
    from ucom_tools.protocol.programmer import Cancelled
    request = FlashRequest(load_image(image), selection=Selection.parse(boards), bus=bus_name,
                           autostart=autostart, start=start_after or keep_params,
                           verify=not no_verify, force=force)
    with robot(spec) as r:
        r.select(bus_name)  # an unknown --bus is exit code 3 before anything is sent
        out = _Flashed()
        try:
            done = run_cancellable(
                lambda cancel: _flash_job(r, request, out, keep_params, verbosity(ctx), cancel),
                name="ucom-flash", finished=lambda out, stop: (
                    as_finished(out.result, stop) if out.result is not None
                    else FlashInterrupted(interrupted_before(r, request, KEEP))))
        except (KeyboardInterrupt, Cancelled) as e:
            if isinstance(e, FlashInterrupted):
                e.result = with_force_hint(e.result, FORCE)
            if out.kept is not None and out.kept.directory is not None:
                stderr().print(f"[yellow]the values read before programming are in "
                               f"{escape(str(out.kept.directory))}[/]", soft_wrap=True)
            cancelled(ctx, spec, e, as_json)
            return
        if done.result is None:
            assert done.kept is not None
            _keep_refused(ctx, spec, done.kept, as_json)
            return
    flash_out(ctx, spec, done.result, as_json, done.restored)


def _flash_job(r: Robot, request: FlashRequest, out: _Flashed, keep_params: bool,
               verbose: int, cancel: threading.Event) -> _Flashed:
    """All of ``ucom flash`` in the worker (run_cancellable): a signal only sets
    ``cancel``, looked at between the steps and throughout the flash."""
    from ucom_tools.cli.flashrun import FORCE, flash_progress, with_force_hint
    from ucom_tools.ops import params_keep
    from ucom_tools.ops.flash import flash, listen_first
    from ucom_tools.ops.flash_types import KEEP, LISTENING, RESET

    bus_name = request.bus
    _stage(r, request, LISTENING, cancel)
    listen_first(r, bus_name)  # another host programming: exit 4, nothing sent
    _stage(r, request, LISTENING, cancel)
    out.kept = params_keep.keep_before(r, bus=bus_name) if keep_params else None
    _stage(r, request, KEEP, cancel)
    if out.kept is not None and not out.kept.readout.ok and not request.force:
        return out
    with flash_progress(r, request.image, verbose=verbose, bus=bus_name) as report:
        for h in r.select(bus_name):
            h.client.reset()
        _stage(r, request, RESET, cancel)
        out.result = with_force_hint(flash(r, request, progress=report, cancel=cancel), FORCE)
    if out.kept is not None:
        out.restored = _keep_after(r, out.kept, out.result)
    return out


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
        emit_with_connection(spec, {"programmed": False,
                                    "keep_params": params_cli.kept_json(report)})
    else:
        params_cli.print_kept(stdout(), report)
    names = ", ".join(b.where for b in report.failed)
    stderr().print(f"[red]nothing programmed: the values of {escape(names)} could not be "
                   "read (--force programs anyway)[/]", soft_wrap=True)
    ctx.exit(EXIT_FAILED)


def program_command(name: str, option: int, target: Target, detail: str) -> click.Command:
    """Option ``option`` (5, Program, or 6, ExtRAMLoad): an image into ``target`` of one
    board, or of every ProgEnabled board, verified like ``flash``."""
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
        with robot(spec, run_init=run_init, bus=ref.bus or bus_name) as r, \
                needing_init(option):
            try:
                request = FlashRequest(img, selection=selection, bus=ref.bus or bus_name,
                                       target=target, init=False, force=force)
                result = run_flash(r, request, verbose=verbosity(ctx))
            except (KeyboardInterrupt, Cancelled) as e:
                cancelled(ctx, spec, e, as_json)
                return
        flash_out(ctx, spec, result, as_json)
    return cmd

