"""``ucom``: the root command and its error boundary (exit codes, one red line).

Every error a user can cause ends here as one line on stderr and an exit code of
:mod:`ucom_tools.cli.exitcodes`; a traceback only with ``-vv``.  The subcommands live in
their own modules (commands, console, srec, fleet, tree, ...), which never import this
one; each is imported when its command is looked up (:class:`LazyCommands`).
"""

from __future__ import annotations

import contextlib
import errno
import importlib
import io
import os
import sys
import traceback
from collections.abc import Iterator, MutableMapping
from typing import Any

import click
from rich.markup import escape

from ucom_tools import __version__, compiled
from ucom_tools.cli import output
from ucom_tools.cli.exitcodes import (
    EXIT_BAD_INPUT,
    EXIT_BUS,
    EXIT_FAILED,
    EXIT_OK,
    EXIT_WRITE,
)
from ucom_tools.cli.output import stderr
from ucom_tools.errors import BusError, InputError, UcomError, WriteError
from ucom_tools.signals import Terminated, interrupt_exit_code, stop_signals

BOOTLOADER_COMMANDS = ("check", "reset", "init", "info", "prog-enable", "program",
                       "extram-load", "start", "autostart", "xreset", "set-init-in",
                       "set-init-out", "set-seqid", "count", "first", "last", "list",
                       "reset-one", "flash")
"""The commands of :mod:`ucom_tools.cli.commands` (its ``COMMANDS``)."""

SUBCOMMANDS: dict[str, tuple[str, str]] = {
    **{name: ("commands", "") for name in BOOTLOADER_COMMANDS},
    "console": ("console", "console"), "image": ("image", "image"),
    "srec": ("srec", "srec"), "fleet": ("fleet", "fleet"), "tree": ("tree", "tree"),
    "remote": ("remote", "remote"), "browse": ("browse", "browse"),
    "params": ("params", "params"), "conformance": ("conformance", "conformance"),
    "decode": ("decode", "decode"), "dbc": ("dbc", "dbc"), "deploy": ("deploy", "deploy_cmd"),
    "gateway": ("gateway", "gateway"),
}
"""Each subcommand: its module in :mod:`ucom_tools.cli` and the command's name there."""


class LazyCommands(MutableMapping[str, click.Command]):
    """The root's subcommands, each imported when it is first looked up: ``ucom init``
    does not import the fleet server, the decoder or Zenoh (half of the start-up time of
    a command; ``ucom --help`` imports them all to list them)."""

    def __init__(self, specs: dict[str, tuple[str, str]]) -> None:
        self._specs = dict(specs)
        self._loaded: dict[str, click.Command] = {}

    def __getitem__(self, name: str) -> click.Command:
        command = self._loaded.get(name)
        if command is None:
            module_name, attr = self._specs[name]  # KeyError: no such command
            module = importlib.import_module(f"ucom_tools.cli.{module_name}")
            command = getattr(module, attr) if attr else \
                next(c for c in module.COMMANDS if c.name == name)
            self._loaded[name] = command
        return command

    def __setitem__(self, name: str, command: click.Command) -> None:
        self._specs[name] = ("", "")
        self._loaded[name] = command

    def __delitem__(self, name: str) -> None:
        del self._specs[name]
        self._loaded.pop(name, None)

    def __iter__(self) -> Iterator[str]:
        return iter(self._specs)

    def __len__(self) -> int:
        return len(self._specs)


class UcomGroup(click.Group):
    """Root group: maps ucom-tools errors to exit codes, one line on stderr."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        ctx.meta["ucom.argv"] = list(args)  # for the error boundary: was --json asked?
        return super().parse_args(ctx, args)

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
            with contextlib.suppress(OSError):
                if isinstance(e, Terminated):
                    stderr().print(f"[yellow]terminated ({e.name})[/]")
                else:
                    stderr().print("[yellow]interrupted[/]")
            ctx.exit(interrupt_exit_code(e))

    @staticmethod
    def _fail(ctx: click.Context, e: Exception, code: int, label: str) -> None:
        if (ctx.obj or {}).get("verbose", 0) >= 2:
            traceback.print_exc(file=sys.stderr)
        stderr().print(f"[bold red]ucom: {label}:[/] {escape(str(e))}", highlight=False,
                       soft_wrap=True)
        if "--json" in ctx.meta.get("ucom.argv", ()) and not output.json_emitted():
            # a program reading --json gets a document on standard output in any case
            output.emit_json({"error": {"kind": label, "message": str(e),
                                        "exit_code": code}})
        ctx.exit(code)


@click.group(cls=UcomGroup, commands=LazyCommands(SUBCOMMANDS),
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
