"""``ucom browse``: a running robot's edges from another host, over Zenoh (the mcabrowser of
ucom-tools; ``man/ucom-network.7``): read, set, watch, or the whole structure."""

from __future__ import annotations

import json
import sys
from typing import TYPE_CHECKING, Any

import click
from rich.markup import escape

from ucom_tools.cli.browse_view import value_of as _value_of
from ucom_tools.cli.options import Finite, json_option, parse_sets
from ucom_tools.cli.output import emit_json, stderr, stdout
from ucom_tools.errors import InputError
from ucom_tools.net.keys import DEFAULT_ENDPOINT
from ucom_tools.viewers.foxglove_msgs import DEFAULT_ADDRESS as FOXGLOVE_ADDRESS
from ucom_tools.viewers.foxglove_msgs import parse_address

if TYPE_CHECKING:
    from ucom_tools.net.client import Reading, RobotClient


def _line(name: str, value: object, unit: str) -> str:
    return f"{name} = {value}{' ' + unit if unit else ''}"


def _stale(reading: Reading, where: str) -> str:
    """`` (stale: ...)`` after a value whose board is lost, else nothing."""
    if reading.valid:
        return ""
    return f" (stale: {where} is lost" + (f", {reading.seen}" if reading.seen else "") + ")"


def _value_json(reading: Reading) -> dict[str, Any]:
    out: dict[str, Any] = {"t": reading.t, "value": reading.value, "valid": reading.valid}
    if not reading.valid:
        out["lost_since"] = reading.lost_since
    return out


@click.command("browse")
@click.argument("robot", required=False)
@click.option("--zenoh", "endpoint", default=DEFAULT_ENDPOINT, show_default=True,
              metavar="ENDPOINT", help="Where the robot's loop listens (its 'remote run "
              "--zenoh'); this connects as a peer, multicast scouting off.")
@click.option("--zenoh-config", "config_file", type=click.Path(dir_okay=False),
              metavar="FILE", help="A Zenoh JSON5 configuration (TLS, authentication, "
              "routers); --zenoh, where given, replaces its connect endpoints.")
@click.option("--get", "gets", multiple=True, metavar="NAME",
              help="Print the edge's current value (repeatable) and exit.")
@click.option("--set", "sets", multiple=True, metavar="NAME=VALUE",
              help="Set a CI or PAR on the robot (repeatable; the robot must run with "
                   "--allow-writes) and exit with its answer.")
@click.option("--watch", "watches", multiple=True, metavar="NAME",
              help="Print 'time name value' lines as the edge's values come (repeatable), "
                   "until Ctrl-C or --for.")
@click.option("--for", "seconds", type=Finite(0, min_open=True), metavar="SECONDS",
              help="Watch this long.")
@click.option("--stop", "stop", is_flag=True,
              help="Stop the robot's boards (motors off) and its loop (needs "
                   "--allow-writes there); starting is never done from here.")
@click.option("--foxglove", "foxglove", is_flag=False, flag_value=FOXGLOVE_ADDRESS,
              default=None, metavar="[HOST:PORT]",
              help="Serve the robot to the Foxglove app or Lichtblick on HOST:PORT (alone: "
                   f"{FOXGLOVE_ADDRESS}, this host only) until Ctrl-C or --for: each board's "
                   "values, the joints, the events (not the frames: they stay on the "
                   "robot's host).")
@click.option("--allow-writes", is_flag=True,
              help="With --foxglove: pass the Foxglove clients' writes on to the robot "
                   "(which takes them only where its loop runs with --allow-writes).")
@click.option("--timeout", type=Finite(0, min_open=True), default=5.0, show_default=True,
              metavar="SECONDS", help="How long to wait for the robot to be found and to "
              "answer.")
@json_option
def browse(robot: str | None, endpoint: str, config_file: str | None, gets: tuple[str, ...],
           sets: tuple[str, ...], watches: tuple[str, ...], seconds: float | None,
           stop: bool, foxglove: str | None, allow_writes: bool, timeout: float,
           as_json: bool) -> None:
    """A running robot's edges from this host, over Zenoh.

    ROBOT is the robot's name in the keys (its topology's file name: armar3); not needed
    where one robot runs there.  --set writes (exit 3 where the robot refuses the value,
    naming its range or the closest names; 1 where it takes no writes), --get prints
    values, --watch streams them.  Without these, on a terminal, it opens the live view:
    the robot as a tree (bus, board with prefix, state and LEDs, its edges by kind) with
    values and their age, refreshed at the robot's publishing rate (at most 20 times a second);
    it says "connection lost" when the robot goes and connects again when it is back.
    Keys: / filter by name (Enter keeps it, Esc clears it), s set a CI or PAR (Tab
    completes the name; NAME=VALUE or the name, Enter, then the value; the robot's answer
    is shown), x stop the boards (y confirms), arrows, PgUp, PgDn, Home, End scroll, q
    quits (exit 0).  Off a terminal (standard input or output a pipe or a file) it prints
    the structure and every value once (--json: as one document).  --foxglove serves
    the robot over the Foxglove WebSocket protocol instead, as 'remote run --foxglove'
    does on the robot's host (exit 4 where the address is in use).  Exit 4 where no
    robot answers on the endpoint within --timeout.  See ucom-network(7)."""
    from ucom_tools.cli import browse_tty
    from ucom_tools.cli.browse_tty import interactive
    from ucom_tools.net.client import RobotClient

    wanted = parse_sets(sets)
    fox = _checked(wanted, gets, watches, seconds, stop, foxglove, allow_writes)
    where = endpoint if config_file is None or endpoint != DEFAULT_ENDPOINT else None
    with RobotClient.connect(where, robot=robot, config_file=config_file,
                             timeout=timeout) as client:
        if fox is not None:
            _serve_foxglove(client, fox, allow_writes, seconds, as_json)
            return
        if not (wanted or gets or stop or watches or as_json) and interactive(sys.stdin,
                                                                             sys.stdout):
            name = client.robot
            browse_tty.run(client, lambda: RobotClient.connect(
                where, robot=name, config_file=config_file, timeout=min(timeout, 2.0)),
                timeout)
            return
        out = _asked(client, wanted, gets, stop, timeout, as_json)
        if watches:
            if as_json and (wanted or gets or stop):
                emit_json(out)  # the document first, then the watch's lines
            _watch(client, watches, seconds, as_json)
            return
        if not (wanted or gets or stop):
            values = client.read(timeout=timeout)
            if as_json:
                out["structure"] = client.structure
                out["values"] = {n: _value_json(r) for n, r in values.items()}
            else:
                _print_tree(client.structure, values, client)
        if as_json:
            emit_json(out)


def _checked(wanted: list[tuple[str, str]], gets: tuple[str, ...], watches: tuple[str, ...],
             seconds: float | None, stop: bool, foxglove: str | None,
             allow_writes: bool) -> tuple[str, int] | None:
    """The options that go together, or InputError; --foxglove's address."""
    fox = parse_address(foxglove) if foxglove is not None else None
    if fox is not None and (wanted or gets or watches or stop):
        raise InputError("--foxglove serves the robot: give --get, --set, --watch and "
                         "--stop without it", key="--foxglove")
    if allow_writes and fox is None:
        raise InputError("--allow-writes is for the writes of --foxglove's clients",
                         key="--allow-writes")
    if seconds is not None and not watches and fox is None:
        raise InputError("--for is the length of a --watch (or of --foxglove)", key="--for")
    return fox


def _asked(client: RobotClient, wanted: list[tuple[str, str]], gets: tuple[str, ...],
           stop: bool, timeout: float, as_json: bool) -> dict[str, Any]:
    """--set, --get and --stop, in that order: printed, and as --json's document."""
    out: dict[str, Any] = {"robot": client.robot, "endpoint": client.where}
    for name, text in wanted:
        answer = client.write(name, _value_of(text), timeout=timeout)
        out.setdefault("set", []).append(answer)
        if not as_json:
            stdout().print(escape(_line(answer["name"], answer["value"],
                                        answer.get("unit", ""))) + ": set", soft_wrap=True)
    if gets:
        values = client.read(list(gets), timeout=timeout)
        out["values"] = {n: _value_json(r) for n, r in values.items()}
        if not as_json:
            for n, r in values.items():
                ref = client.resolve(n)
                stdout().print(escape(_line(n, r.value, ref.spec.unit)
                                      + _stale(r, ref.where)), soft_wrap=True)
    if stop:
        out["stop"] = client.stop(timeout=timeout)
        if not as_json:
            stdout().print(f"robot {escape(client.robot)}: stopping every board")
    return out


def _watch(client: RobotClient, watches: tuple[str, ...], seconds: float | None,
           as_json: bool) -> None:
    """--watch: a line per value as it comes (--json: a JSON document a line)."""
    for t, n, v, valid in client.watch(list(watches), seconds, validity=True):
        if as_json:
            sys.stdout.write(json.dumps({"t": t, "name": n, "value": v,
                                         "valid": valid}) + "\n")
        else:
            sys.stdout.write(f"{t:.6f} {n} {v}{'' if valid else ' stale'}\n")
        sys.stdout.flush()


def _print_tree(structure: dict[str, Any], values: dict[str, Reading],
                client: Any) -> None:
    s = structure
    stdout().print(f"[bold]{escape(s.get('name', s['robot']))}[/] ({escape(s['robot'])}) on "
                   f"{escape(str(s.get('host')))}, pid {s.get('pid')}: {s.get('rate_hz'):g} Hz, "
                   f"published at {s.get('publish_hz'):g} Hz, writes "
                   + ("allowed" if s.get("allow_writes") else "not allowed"))
    for bus in s["buses"]:
        stdout().print(f"{escape(bus['name'])}")
        for b in bus["boards"]:
            stale = next((v for e in b["edges"] if (v := values.get(e["robot_name"]))
                          is not None and not v.valid), None)
            stdout().print(f"  {escape(b['where'])} [{escape(b['prefix'])}] "
                           f"{escape(b.get('program') or '')}"
                           + ("" if stale is None else
                              f"  [bold red]LOST[/] ({escape(stale.seen or 'silent')})"))
            for e in b["edges"]:
                v = values.get(e["robot_name"])
                shown = "-" if v is None else v.value
                stdout().print(f"    {e['kind']:<3} {escape(e['robot_name'])} = {shown}"
                               + (f" {escape(e['unit'])}" if e["unit"] else "")
                               + ("" if v is None or v.valid else " (stale: board lost)"),
                               soft_wrap=True)
    if not values:
        stderr().print("[dim]no values yet (the robot is starting)[/]")


def _serve_foxglove(client: Any, address: tuple[str, int], allow_writes: bool,
                    seconds: float | None, as_json: bool) -> None:
    """``--foxglove``: serve until Ctrl-C or ``seconds`` (exit 4 where it cannot)."""
    import threading

    from ucom_tools.viewers.foxglove_feed import BrowseFoxglove, serve_until

    served = BrowseFoxglove(client, *address, allow_writes=allow_writes)
    try:
        if not as_json:
            stderr().print(f"[dim]foxglove: robot {escape(client.robot)} on "
                           f"{escape(served.server.url)}, writes "
                           + ("passed on" if allow_writes else "refused")
                           + (f", for {seconds:g} s" if seconds else ", until Ctrl-C") + "[/]",
                           soft_wrap=True)
        serve_until(threading.Event(), seconds)
    finally:
        served.close()
    if as_json:
        emit_json({"robot": client.robot, "endpoint": client.where,
                   "foxglove": served.stats()})
