"""Connection options shared by every command that talks to boards."""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import click

from ucom_tools.config.topology import BUNDLED
from ucom_tools.ops.robot import ConnectSpec, Robot, open_robot


def connection_options(f: Callable[..., Any]) -> Callable[..., Any]:
    """Add -i/-c/-b/--host/--port/--virtual/--topology/--state/--pace/--bus to a command."""
    options = [
        click.option("-i", "--interface", envvar="UCOM_INTERFACE", metavar="NAME",
                     help="python-can interface (socketcan, pcan, kvaser, socketcand, ...)."),
        click.option("-c", "--channel", "channels", multiple=True, envvar="UCOM_CHANNEL",
                     metavar="CH", help="CAN channel; repeat for several buses."),
        click.option("-b", "--bitrate", type=int, envvar="UCOM_BITRATE",
                     help="Bitrate for interfaces that set it (e.g. 1000000)."),
        click.option("--host", envvar="UCOM_HOST", help="Host of a socketcand server."),
        click.option("--port", type=int, envvar="UCOM_PORT", help="Port of a socketcand server."),
        click.option("--virtual", metavar="TOPOLOGY", envvar="UCOM_VIRTUAL",
                     help=f"Use the in-process virtual fleet ({', '.join(BUNDLED)} or a "
                          "topology file) instead of CAN hardware."),
        click.option("--topology", metavar="FILE", envvar="UCOM_TOPOLOGY",
                     help="Topology of the real robot: the boards expected on each bus."),
        click.option("--state", "state_dir", envvar="UCOM_STATE",
                     type=click.Path(file_okay=False, path_type=Path),
                     help="With --virtual: keep the boards' flash in DIR across runs."),
        click.option("--pace", is_flag=True, envvar="UCOM_PACE",
                     help="With --virtual: run the buses at their real bitrate."),
        click.option("--bus", "bus_name", metavar="NAME", help="Only this bus."),
    ]
    for opt in reversed(options):
        f = opt(f)

    @functools.wraps(f)
    def wrapper(*args: Any, interface: str | None, channels: tuple[str, ...],
                bitrate: int | None, host: str | None, port: int | None, virtual: str | None,
                topology: str | None, state_dir: Path | None, pace: bool, **kwargs: Any) -> Any:
        spec = ConnectSpec(interface, tuple(channels), bitrate, host, port, virtual, topology,
                           state_dir, pace)
        return f(*args, spec=spec, **kwargs)

    return wrapper


def init_option(f: Callable[..., Any]) -> Callable[..., Any]:
    return click.option("--init", "run_init", is_flag=True,
                        help="Run the init chain (option 2) first.")(f)


def json_option(f: Callable[..., Any]) -> Callable[..., Any]:
    return click.option("--json", "as_json", is_flag=True,
                        help="Print JSON instead of tables.")(f)


@contextmanager
def robot(spec: ConnectSpec, *, run_init: bool = False, bus: str | None = None
          ) -> Iterator[Robot]:
    r = open_robot(spec)
    try:
        if run_init:
            for h in r.select(bus):
                h.client.init_chain()
        yield r
    finally:
        r.close()
