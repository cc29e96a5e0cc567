"""``ucom``: the root command and its error boundary (exit codes, one red line).

Every error a user can cause ends here as one line on stderr and an exit code of
:mod:`ucom_tools.cli.exitcodes`; a traceback only with ``-vv``.  The subcommands live in
their own modules (commands, console, srec, fleet, tree), which never import this one.
"""

from __future__ import annotations

import sys
import traceback
from typing import Any

import click
from rich.markup import escape

from ucom_tools import __version__
from ucom_tools.cli import (
    commands,
    conformance,
    console,
    dbc,
    decode,
    fleet,
    output,
    params,
    remote,
    srec,
    tree,
)
from ucom_tools.cli.exitcodes import (
    EXIT_BAD_INPUT,
    EXIT_BUS,
    EXIT_FAILED,
    EXIT_INTERRUPTED,
)
from ucom_tools.cli.output import stderr
from ucom_tools.errors import BusError, InputError, UcomError


class UcomGroup(click.Group):
    """Root group: maps ucom-tools errors to exit codes, one line on stderr."""

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except InputError as e:
            self._fail(ctx, e, EXIT_BAD_INPUT, "bad input")
        except BusError as e:
            self._fail(ctx, e, EXIT_BUS, "bus error")
        except UcomError as e:
            self._fail(ctx, e, EXIT_FAILED, "error")
        except KeyboardInterrupt:
            stderr().print("[yellow]interrupted[/]")
            ctx.exit(EXIT_INTERRUPTED)

    @staticmethod
    def _fail(ctx: click.Context, e: Exception, code: int, label: str) -> None:
        if (ctx.obj or {}).get("verbose", 0) >= 2:
            traceback.print_exc(file=sys.stderr)
        stderr().print(f"[bold red]ucom: {label}:[/] {escape(str(e))}", highlight=False,
                       soft_wrap=True)
        ctx.exit(code)


@click.group(cls=UcomGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="ucom")
@click.option("-v", "--verbose", count=True, help="More detail; -vv shows tracebacks.")
@click.pass_context
def cli(ctx: click.Context, verbose: int) -> None:
    """Toolchain and bus console for UCoM controller boards (ARMAR-III and others).

    Exit codes: 0 success, 1 some boards failed (or are missing, or a wiring fault),
    2 usage error, 3 bad input (file, topology, argument, environment; nothing was sent),
    4 bus or connection failure, 130 interrupted.  The connection options may come from
    UCOM_INTERFACE, UCOM_CHANNEL, UCOM_BITRATE, UCOM_HOST, UCOM_PORT, UCOM_VIRTUAL,
    UCOM_TOPOLOGY, UCOM_STATE, UCOM_PACE; a bus named on the command line wins over the
    environment.  See ucom(1) and ucom-protocol(7).
    """
    output.reset()
    ctx.ensure_object(dict)
    ctx.obj["verbose"] = verbose


for _command in commands.COMMANDS:
    cli.add_command(_command)
cli.add_command(console.console)
cli.add_command(srec.srec)
cli.add_command(fleet.fleet)
cli.add_command(tree.tree)
cli.add_command(remote.remote)
cli.add_command(params.params)
cli.add_command(conformance.conformance)
cli.add_command(decode.decode)
cli.add_command(dbc.dbc)


def main() -> None:
    cli(prog_name="ucom")


__all__ = ["EXIT_FAILED", "cli", "main"]
