"""``ucom``: the root command and its error boundary (exit codes, one red line).

Every error a user can cause ends here as one line on stderr and an exit code of
:mod:`ucom_tools.cli.exitcodes`; a traceback only with ``-vv``.  The subcommands live in
their own modules (``commands/``: a module per console option; flash, console, srec,
fleet, tree, ...), which never import this one; each is imported when its command is
looked up (:class:`LazyCommands`), and :data:`COMMANDS` lists them all.  ``ucom --help``
and ``--version`` import click and no more (rich neither: it is imported where a command
or an error prints), so that they start as fast as click does (``tests/test_cli_startup.py``).
"""

from __future__ import annotations

import contextlib
import errno
import importlib
import io
import os
import sys
from collections.abc import Iterator, MutableMapping
from typing import Any, NamedTuple

import click

from ucom_tools import __version__, compiled
from ucom_tools.cli.exitcodes import (
    EXIT_BAD_INPUT,
    EXIT_BUS,
    EXIT_FAILED,
    EXIT_OK,
    EXIT_WRITE,
)
from ucom_tools.errors import BusError, InputError, UcomError, WriteError
from ucom_tools.signals import Terminated, interrupt_exit_code, stop_signals


class Entry(NamedTuple):
    """One subcommand of ``ucom``: where it is and its line in ``ucom --help``."""

    module: str
    """Its module in :mod:`ucom_tools.cli` (``commands.init`` is ``cli/commands/init.py``)."""
    attr: str
    """The command's name in that module."""
    summary: str
    """The first sentence of its help (``tests/test_cli_startup.py`` holds the two equal),
    listed by ``ucom --help`` without importing the command's module."""


COMMANDS: dict[str, Entry] = {
    # the options of dsp_console2can, in its menu's order, a module each in cli/commands/
    "reset": Entry("commands.reset", "reset_cmd",
                   "Option 1, Reset All: reset every board and list who answered."),
    "init": Entry("commands.init", "init_cmd", "Option 2, Init: number the boards along "
                  "the init line, check the wiring."),
    "info": Entry("commands.info", "info_cmd", "Option 3, GetInfo: program name, date, "
                  "ProgID, flags of a board (needs init: option 2, or --init)."),
    "prog-enable": Entry("commands.prog_enable", "prog_enable_cmd", "Option 4, "
                         "SetProgEnable: enable programming of a board or all (needs init: "
                         "option 2, or --init)."),
    "program": Entry("commands.program", "program_cmd", "Option 5, Program: program a "
                     "board, or all ProgEnabled boards (needs init: option 2, or --init)."),
    "extram-load": Entry("commands.extram_load", "extram_load_cmd", "Option 6, ExtRAMLoad: "
                         "load the image into external RAM (needs init: option 2, or "
                         "--init)."),
    "start": Entry("commands.start", "start_cmd", "Option 7, Start: start the program in "
                   "flash or ExtRAM (needs init: option 2, or --init)."),
    "autostart": Entry("commands.autostart", "autostart_cmd", "Option 8, SetAutoStart: "
                       "start the flash program after every reset (needs init: option 2, "
                       "or --init)."),
    "xreset": Entry("commands.xreset", "xreset_cmd",
                    "Option 9, XReset: clear AutoStart and reset."),
    "set-init-in": Entry("commands.set_init_in", "set_init_in_cmd", "Option 10, SetInitIn: "
                         "drive a board's init input (needs init: option 2, or --init)."),
    "set-init-out": Entry("commands.set_init_out", "set_init_out_cmd", "Option 11, "
                          "SetInitOut: drive a board's init output (needs init: option 2, "
                          "or --init)."),
    "set-seqid": Entry("commands.set_seqid", "set_seqid_cmd", "Option 12, SetSeqID: give a "
                       "board another seq ID (needs init: option 2, or --init)."),
    "count": Entry("commands.count", "count_cmd", "Option 13, Count: GetInfo of every board "
                   "that has a number."),
    "first": Entry("commands.first", "first_cmd", "Option 14, Get First: which board is "
                   "first on the init line."),
    "last": Entry("commands.last", "last_cmd", "Option 15, Get Last: which board is last on "
                  "the init line."),
    "list": Entry("commands.dsp_list", "list_cmd", "Option 16, DSPListUpdate: build the "
                  "list of active boards."),
    "reset-one": Entry("commands.reset_one", "reset_one_cmd", "Option 21, Reset Specific: "
                       "reset one board (needs init: option 2, or --init)."),
    # flash (cli/flash.py, which also holds what program and extram-load share with it),
    # and check, built of the options' steps
    "flash": Entry("flash", "flash_cmd", "Program IMAGE (S-record or Intel HEX) into the "
                   "boards of every bus, verified."),
    "check": Entry("commands.check", "check_cmd", "Compatibility matrix: plug-on board, "
                   "FPGA and stored DSP program of every board."),
    # the rest, a module each
    "console": Entry("console", "console", "The interactive console of dsp_console2can: "
                     "options 1-21 and q."),
    "image": Entry("image", "image", "Firmware images: S-record (CodeWarrior 56800 "
                   "convention) and Intel HEX."),
    "srec": Entry("srec", "srec", "Firmware images (S-record or Intel HEX): the same as "
                  "'ucom image info/progid'."),
    "fleet": Entry("fleet", "fleet", "The virtual UCoM fleets: boards that behave like the "
                   "hardware, on simulated buses."),
    "tree": Entry("tree", "tree", "Attribute trees: the per-board configuration of a UCoM "
                  "program (ucom-tree(5))."),
    "remote": Entry("remote", "remote", "The run time: boards in the cyclic exchange, values "
                    "by robot-wide name."),
    "browse": Entry("browse", "browse",
                    "A running robot's edges from this host, over Zenoh."),
    "params": Entry("params", "params", "Live parameters: the PAR and CI values a robot's "
                    "boards hold, read back into attribute trees and written from them "
                    "(ucom-tree(5))."),
    "conformance": Entry("conformance", "conformance", "Check that the boards speak the "
                         "protocol (ucom-protocol(7)), content and timing."),
    "decode": Entry("decode", "decode", "Decode a CAN TRACE into the UCoM conversation it "
                    "carries, per bus and board."),
    "dbc": Entry("dbc", "dbc", "Export the UCoM frames as a DBC file for SavvyCAN, cantools "
                 "monitor, CANalyzer and other DBC tools."),
    "deploy": Entry("deploy", "deploy_cmd", "Bring ROBOT's boards to the images its manifest "
                    "names, keeping their parameters."),
    "gateway": Entry("gateway", "gateway", "A UCoM robot's joints as CANopen CiA 402 drives "
                     "(ucom-gateway(7))."),
}
"""Every subcommand of ``ucom``, the one list of them: :class:`LazyCommands` imports a
command from it when it is looked up, and ``ucom --help`` lists them from it."""


class LazyCommands(MutableMapping[str, click.Command]):
    """The root's subcommands, each imported when it is first looked up: ``ucom init``
    imports the bootloader commands and what they use, not the fleet server, the decoder
    or Zenoh, and ``ucom --help`` imports none of them (:meth:`listing`)."""

    def __init__(self, table: dict[str, Entry]) -> None:
        self._table = dict(table)
        self._loaded: dict[str, click.Command] = {}

    def __getitem__(self, name: str) -> click.Command:
        command = self._loaded.get(name)
        if command is None:
            entry = self._table[name]  # KeyError: no such command
            module = importlib.import_module(f"ucom_tools.cli.{entry.module}")
            command = getattr(module, entry.attr)
            assert isinstance(command, click.Command) and command.name == name, entry
            self._loaded[name] = command
        return command

    def listing(self, name: str) -> click.Command:
        """The command as ``ucom --help`` lists it: itself once imported, else a stand-in
        with its summary (the same line, cut to the same width)."""
        command = self._loaded.get(name)
        return command if command is not None else \
            click.Command(name, help=self._table[name].summary)

    def __setitem__(self, name: str, command: click.Command) -> None:
        self._table[name] = Entry("", "", "")
        self._loaded[name] = command

    def __delitem__(self, name: str) -> None:
        del self._table[name]
        self._loaded.pop(name, None)

    def __iter__(self) -> Iterator[str]:
        return iter(self._table)

    def __len__(self) -> int:
        return len(self._table)


class UcomGroup(click.Group):
    """Root group: maps ucom-tools errors to exit codes, one line on stderr."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        ctx.meta["ucom.argv"] = list(args)  # for the error boundary: was --json asked?
        return super().parse_args(ctx, args)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """As click lists the commands, but from :data:`COMMANDS` (nothing imported)."""
        if not isinstance(self.commands, LazyCommands):
            super().format_commands(ctx, formatter)
            return
        listed = [(name, self.commands.listing(name)) for name in self.list_commands(ctx)]
        listed = [(name, command) for name, command in listed if not command.hidden]
        if listed:
            limit = formatter.width - 6 - max(len(name) for name, _ in listed)
            with formatter.section("Commands"):
                formatter.write_dl([(name, command.get_short_help_str(limit))
                                    for name, command in listed])

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except InputError as e:
            self._fail(ctx, e, EXIT_BAD_INPUT, "bad input")
        except WriteError as e:
            self._fail(ctx, e, EXIT_WRITE, "cannot write")
        except BusError as e:
            self._fail(ctx, e, EXIT_BUS, "bus error")
        except UcomError as e:
            self._fail(ctx, e, EXIT_FAILED, "error")
        except KeyboardInterrupt as e:  # Ctrl-C, SIGTERM, SIGHUP (ucom_tools.signals)
            from ucom_tools.cli.output import stderr

            with contextlib.suppress(OSError):
                if isinstance(e, Terminated):
                    stderr().print(f"[yellow]terminated ({e.name})[/]")
                else:
                    stderr().print("[yellow]interrupted[/]")
            ctx.exit(interrupt_exit_code(e))

    @staticmethod
    def _fail(ctx: click.Context, e: Exception, code: int, label: str) -> None:
        import traceback

        from rich.markup import escape

        from ucom_tools.cli import output
        from ucom_tools.cli.errortext import describe

        if (ctx.obj or {}).get("verbose", 0) >= 2:
            traceback.print_exc(file=sys.stderr)
        text = describe(e, ctx.invoked_subcommand)
        output.stderr().print(f"[bold red]ucom: {label}:[/] {escape(text)}", highlight=False,
                       soft_wrap=True)
        if "--json" in ctx.meta.get("ucom.argv", ()) and not output.json_emitted():
            # a program reading --json gets a document on standard output in any case
            output.emit_json({"error": {"kind": label, "message": text,
                                        "exit_code": code}})
        ctx.exit(code)


@click.group(cls=UcomGroup, commands=LazyCommands(COMMANDS),
             context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="ucom",
                      message=f"%(prog)s, version %(version)s, run time "
                              f"{compiled.status().reason}")
@click.option("-v", "--verbose", count=True, help="More detail; -vv shows tracebacks.")
@click.pass_context
def cli(ctx: click.Context, verbose: int) -> None:
    """Toolchain and bus console for UCoM controller boards (ARMAR-III and others).

    Exit codes: 0 success, 1 some boards failed (or are missing, or a wiring fault),
    2 usage error, 3 bad input (file, topology, argument, environment; nothing was sent),
    4 bus or connection failure, 5 an output could not be written (full disk), 130
    interrupted (129, 143: ended by SIGHUP, SIGTERM; the same safe stop).  The
    connection options may come from UCOM_INTERFACE, UCOM_CHANNEL, UCOM_BITRATE,
    UCOM_HOST, UCOM_PORT, UCOM_VIRTUAL, UCOM_TOPOLOGY, UCOM_STATE, UCOM_PACE; a bus named
    on the command line wins over the environment.  See ucom(1) and ucom-protocol(7).
    """
    from ucom_tools.cli import output

    output.reset()
    ctx.ensure_object(dict)
    ctx.obj["verbose"] = verbose


class GuardedStdout(io.TextIOBase):
    """Standard output that a job cannot die of: the first write error (a closed pipe, a
    full disk) is kept and later output is dropped, so the job goes on to its end and
    :func:`main` decides the exit code (``man/ucom.1``, EXIT STATUS)."""

    def __init__(self, stream: Any) -> None:
        super().__init__()
        self._stream = stream
        self.failure: OSError | None = None

    def write(self, text: str) -> int:
        if self.failure is None:
            try:
                self._stream.write(text)
            except OSError as err:
                self.failure = err
        return len(text)

    def flush(self) -> None:
        if self.failure is None:
            try:
                self._stream.flush()
            except OSError as err:
                self.failure = err

    def writable(self) -> bool:
        return True

    def isatty(self) -> bool:
        return bool(self._stream.isatty())

    def fileno(self) -> int:
        return int(self._stream.fileno())

    @property
    def encoding(self) -> str:  # type: ignore[override]
        return str(self._stream.encoding)

    @property
    def errors(self) -> str | None:  # type: ignore[override]
        return self._stream.errors

    @property
    def buffer(self) -> Any:
        return _GuardedBinary(self._stream.buffer, self)


class _GuardedBinary:
    """The binary side of :class:`GuardedStdout`: its errors are kept there too."""

    def __init__(self, raw: Any, guard: GuardedStdout) -> None:
        self._raw = raw
        self._guard = guard

    def write(self, data: bytes) -> int:
        if self._guard.failure is None:
            try:
                self._guard._stream.flush()
                self._raw.write(data)
            except OSError as err:
                self._guard.failure = err
        return len(data)

    def flush(self) -> None:
        if self._guard.failure is None:
            try:
                self._raw.flush()
            except OSError as err:
                self._guard.failure = err

    def __getattr__(self, name: str) -> Any:
        return getattr(self._raw, name)


def main() -> None:
    """The ``ucom`` command: SIGTERM and SIGHUP stop a job as Ctrl-C does; a closed
    standard output (``| head``) ends the output quietly with the job's exit code, a full
    one is named with exit code 5 (when the job itself succeeded)."""
    guard = GuardedStdout(sys.stdout)
    sys.stdout = guard
    code: int | str | None = EXIT_OK
    try:
        with stop_signals():
            cli.main(prog_name="ucom", standalone_mode=True)
    except SystemExit as e:
        code = e.code
    finally:
        guard.flush()
        sys.stdout = guard._stream
    if guard.failure is not None:
        _quiet_stdout()
        if guard.failure.errno != errno.EPIPE:
            from rich.markup import escape

            from ucom_tools.cli.output import stderr

            with contextlib.suppress(OSError):
                stderr().print(f"[bold red]ucom: cannot write:[/] standard output: "
                               f"{escape(guard.failure.strerror or str(guard.failure))}",
                               highlight=False, soft_wrap=True)
            if code in (None, EXIT_OK):
                code = EXIT_WRITE
    sys.exit(code)


def _quiet_stdout() -> None:
    """Point standard output at /dev/null, so that the interpreter's last flush does not
    fail again on a closed pipe or a full disk."""
    with contextlib.suppress(OSError, ValueError, AttributeError):
        fd = os.open(os.devnull, os.O_WRONLY)
        os.dup2(fd, sys.stdout.fileno())
        os.close(fd)


__all__ = ["EXIT_FAILED", "cli", "main"]
