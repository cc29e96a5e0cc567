"""Connection options shared by every command that talks to boards, and their precedence.

A bus is named either by ``--virtual`` or by ``-i/-c/--host/--port`` (with ``--topology``
for a real robot); each option can also come from a ``UCOM_*`` environment variable.  The
command line always wins: when it names a bus of one kind, environment variables naming
the other kind are ignored, and a note on stderr (and the ``connection`` object of
``--json``) says which bus was used and what was ignored.
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import click
from click.core import ParameterSource
from rich.markup import escape

from ucom_tools.cli.output import stderr
from ucom_tools.config.topology import BUNDLED
from ucom_tools.errors import InputError, UcomError
from ucom_tools.ops.robot import ConnectSpec, Robot, open_robot
from ucom_tools.trace.logs import check_log

ENVIRONMENT = {
    "interface": "UCOM_INTERFACE", "channels": "UCOM_CHANNEL", "bitrate": "UCOM_BITRATE",
    "host": "UCOM_HOST", "port": "UCOM_PORT", "virtual": "UCOM_VIRTUAL",
    "topology": "UCOM_TOPOLOGY", "state_dir": "UCOM_STATE", "pace": "UCOM_PACE",
}
"""The only environment variables ucom reads (besides COLUMNS and NO_COLOR)."""
REAL = ("interface", "channels", "host", "port", "topology")
VIRTUAL = ("virtual",)
FLAGS = {"interface": "-i", "channels": "-c", "host": "--host", "port": "--port",
         "topology": "--topology", "virtual": "--virtual"}


class Finite(click.FloatRange):
    """A number within a range that is finite: ``nan`` and ``inf`` are refused by name
    (click's own FloatRange lets ``nan`` through every bound)."""

    name = "finite number"

    def convert(self, value: Any, param: click.Parameter | None,
                ctx: click.Context | None) -> Any:
        number = click.FLOAT.convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return super().convert(number, param, ctx)


def parse_sets(sets: tuple[str, ...]) -> list[tuple[str, str]]:
    """``--set NAME=VALUE`` options as (name, value text); InputError naming the option
    for one without ``=``, a name or a value."""
    out = []
    for s in sets:
        name, sep, value = s.partition("=")
        if not sep or not name.strip() or not value.strip():
            raise InputError(f"{s!r}: expected NAME=VALUE (e.g. 'Right Eye Target=1000')",
                             key="--set")
        out.append((name.strip(), value.strip()))
    return out


def connection_options(f: Callable[..., Any]) -> Callable[..., Any]:
    """Add -i/-c/-b/--host/--port/--virtual/--topology/--state/--pace/--scenario/--bus/--log
    to a command."""
    env = ENVIRONMENT
    options = [
        click.option("-i", "--interface", envvar=env["interface"], metavar="NAME",
                     help="python-can interface (socketcan, pcan, kvaser, socketcand, ...)."),
        click.option("-c", "--channel", "channels", multiple=True, envvar=env["channels"],
                     metavar="CH", help="CAN channel; repeat for several buses."),
        click.option("-b", "--bitrate", type=int, envvar=env["bitrate"],
                     help="Bus bitrate (passed to interfaces that set it; deadlines assume "
                          "it; default: the topology's, else 1000000)."),
        click.option("--host", envvar=env["host"], help="Host of a socketcand server."),
        click.option("--port", type=int, envvar=env["port"], help="Port of a socketcand server."),
        click.option("--virtual", metavar="TOPOLOGY", envvar=env["virtual"],
                     help=f"Use the in-process virtual fleet ({', '.join(BUNDLED)} or a "
                          "topology file) instead of CAN hardware."),
        click.option("--topology", metavar="FILE", envvar=env["topology"],
                     help="Topology of the real robot: the boards expected on each bus."),
        click.option("--state", "state_dir", envvar=env["state_dir"],
                     type=click.Path(path_type=Path),
                     help="With --virtual: keep the boards' flash in DIR across runs."),
        click.option("--pace", is_flag=True, envvar=env["pace"],
                     help="With --virtual: run the buses at their real bitrate."),
        click.option("--scenario", metavar="FILE", type=click.Path(path_type=Path),
                     help="With --virtual: injected faults for the fleet (a board that "
                          "loses power, resets, goes bus-off; a cut cable; the emergency "
                          "stop), timed from each bus's first MCA Alive (TOML, 'man ucom', "
                          "SCENARIOS)."),
        click.option("--bus", "bus_name", metavar="NAME", help="Only this bus."),
        click.option("--log", "log_file", metavar="FILE", type=click.Path(path_type=Path),
                     help="Record every frame of every bus opened, received and sent, into "
                          "FILE, a python-can log whose format follows the extension (.asc, "
                          ".blf, .log, .trc; .csv and .db for one bus; .gz for the text "
                          "ones); 'ucom decode FILE' reads it back."),
    ]
    for opt in reversed(options):
        f = opt(f)

    @functools.wraps(f)
    def wrapper(*args: Any, interface: str | None, channels: tuple[str, ...],
                bitrate: int | None, host: str | None, port: int | None, virtual: str | None,
                topology: str | None, state_dir: Path | None, pace: bool,
                scenario: Path | None, log_file: Path | None, **kwargs: Any) -> Any:
        if log_file is not None:
            check_log(log_file)  # before anything is read, opened or sent
        values: dict[str, Any] = {"interface": interface, "channels": channels, "host": host,
                                  "port": port, "virtual": virtual, "topology": topology}
        origin, ignored = _resolve(click.get_current_context(), values)
        if scenario is not None and not values["virtual"]:
            raise click.UsageError(
                "--scenario injects faults into the in-process virtual fleet: give it with "
                "--virtual (a served fleet takes 'ucom fleet serve --scenario FILE', or "
                "'ucom fleet fault' by hand)")
        spec = ConnectSpec(values["interface"], tuple(values["channels"]), bitrate,
                           values["host"], values["port"], values["virtual"],
                           values["topology"], state_dir, pace, origin=origin,
                           ignored=tuple(ignored), log=log_file, scenario=scenario)
        if ignored:
            stderr().print(f"[yellow]ucom: using {escape(describe(spec))} from the "
                           f"{origin}; ignored from the environment: "
                           f"{escape(', '.join(ignored))}[/]", soft_wrap=True)
        return f(*args, spec=spec, **kwargs)

    return wrapper


def describe(spec: ConnectSpec) -> str:
    """The bus of ``spec`` as the options that name it (``--virtual armar3``)."""
    if spec.virtual:
        return f"--virtual {spec.virtual}" + (
            f" --scenario {spec.scenario}" if spec.scenario else "")
    parts = [f"-i {spec.interface}"] if spec.interface else []
    if spec.host and spec.port:
        parts.append(f"{spec.host}:{spec.port}")
    elif spec.host or spec.port:
        parts.append(f"--host {spec.host}" if spec.host else f"--port {spec.port}")
    parts += [f"-c {c}" for c in spec.channels]
    if spec.topology:
        parts.append(f"--topology {spec.topology}")
    return " ".join(parts) or "no bus"


def _given(values: dict[str, Any], name: str) -> bool:
    v = values[name]
    return bool(v) if not isinstance(v, int) or isinstance(v, bool) else True


def _resolve(ctx: click.Context, values: dict[str, Any]) -> tuple[str, list[str]]:
    """Apply the precedence; returns where the bus came from and what was ignored."""
    def source(name: str) -> ParameterSource | None:
        return ctx.get_parameter_source(name)

    def named(names: tuple[str, ...], where: ParameterSource) -> list[str]:
        return [n for n in names if _given(values, n) and source(n) is where]

    cli_real, cli_virtual = named(REAL, ParameterSource.COMMANDLINE), \
        named(VIRTUAL, ParameterSource.COMMANDLINE)
    env_real, env_virtual = named(REAL, ParameterSource.ENVIRONMENT), \
        named(VIRTUAL, ParameterSource.ENVIRONMENT)
    if cli_real and cli_virtual:
        raise click.UsageError(
            "--virtual and " + "/".join(FLAGS[n] for n in cli_real)
            + " name two different buses; give one of them")
    drop: list[str] = []
    if cli_real and env_virtual:
        drop = env_virtual
    elif cli_virtual and env_real:
        drop = env_real
    elif env_real and env_virtual:
        raise InputError(
            "the environment names two different buses: "
            + ", ".join(f"{ENVIRONMENT[n]}" for n in env_virtual + env_real)
            + "; unset one, or name the bus on the command line")
    ignored = []
    for n in drop:
        v = values[n]
        shown = " ".join(v) if isinstance(v, tuple) else str(v)
        ignored.append(f"{ENVIRONMENT[n]}={shown}")
        values[n] = () if isinstance(v, tuple) else None
    used = [n for n in REAL + VIRTUAL if _given(values, n)]
    from_cli = any(source(n) is ParameterSource.COMMANDLINE for n in used)
    return ("command line" if from_cli or not used else "environment"), ignored


def init_option(f: Callable[..., Any]) -> Callable[..., Any]:
    return click.option("--init", "run_init", is_flag=True,
                        help="Run the init chain (option 2) first.")(f)


def json_option(f: Callable[..., Any]) -> Callable[..., Any]:
    return click.option("--json", "as_json", is_flag=True,
                        help="Print JSON instead of tables.")(f)


def connection_json(spec: ConnectSpec) -> dict[str, Any]:
    """Which bus a command used (and which environment variables it ignored), for --json."""
    return {"bus": describe(spec), "from": spec.origin, "ignored": list(spec.ignored)}


@contextmanager
def robot(spec: ConnectSpec, *, run_init: bool = False, bus: str | None = None
          ) -> Iterator[Robot]:
    r = open_robot(spec)
    try:
        if run_init:
            r.each(lambda h: h.client.init_chain(), bus)
        yield r
    except InputError:
        r.close(keep_log=False)  # bad input: nothing is written, --log neither
        raise
    finally:
        r.close()


@contextmanager
def needing_init(option: int) -> Iterator[None]:
    """Words a :class:`~ucom_tools.ops.options.NotInitialised` raised inside for the
    command line: what menu option ``option`` needs and how to get it."""
    from ucom_tools.cli.menu import init_advice
    from ucom_tools.ops.options import NotInitialised

    try:
        yield
    except NotInitialised as e:
        raise UcomError(init_advice(e.bus, option)) from None


def environment_note() -> str:
    """The UCOM_* variables set in this environment (for -v diagnostics)."""
    return ", ".join(f"{v}={os.environ[v]}" for v in ENVIRONMENT.values() if v in os.environ)


def emit_with_connection(spec: ConnectSpec, data: dict[str, Any]) -> None:
    """JSON on stdout, with the bus that was used."""
    from ucom_tools.cli.output import emit_json

    emit_json({**data, "connection": connection_json(spec)})


def verbosity(ctx: click.Context) -> int:
    """How many -v the root command was given."""
    return int((ctx.find_root().obj or {}).get("verbose", 0))
