"""``ucom fleet show``, ``ucom fleet serve``, ``ucom fleet fault`` and ``ucom fleet
defects``: the bundled virtual UCoM fleets, injecting a fault into a served one, and the
mutant boards' defects."""

from __future__ import annotations

import logging
import re
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import click
from rich.markup import escape

from ucom_tools.cli.errortext import describe
from ucom_tools.cli.output import emit_json, leds, stderr, stdout
from ucom_tools.cli.tables import FitTable
from ucom_tools.config import mutants
from ucom_tools.config import topology as topo
from ucom_tools.config.scenario import MAX_SECONDS, ROBOT, FaultKind, Scenario, injected
from ucom_tools.config.topology import BUNDLED, BusSpec, Topology
from ucom_tools.errors import BusError, InputError
from ucom_tools.plugons import board_name
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.virtual.serve.multiserve import (
    LOG_FORMAT,
    MultiServer,
    auto_processes,
    sigterm_interrupts,
    usable_cores,
)
from ucom_tools.virtual.serve.socketcand import (
    DEFAULT_PORT,
    MAX_CLIENTS,
    FleetServer,
    serve_until_interrupted,
)

SWITCH_INTERVAL_S = 0.0005
"""Python's thread switch interval while serving (its default is 5 ms)."""
EXTRA_BUS_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_.-]{0,14}")
"""A name ``--extra-bus`` takes: a network interface's as socketcand serves them (at most
15 characters), a letter first, then letters, digits, ``_``, ``.`` or ``-``."""
EXTRA_BUS_BITRATE = 1_000_000
"""The bitrate of a bus ``--extra-bus`` adds (frames take their length at it)."""
TOPOLOGY_HELP = f"a bundled topology ({', '.join(BUNDLED)}) or a topology file (TOML)"
SHOW_HELP = f"""Show the buses and boards of TOPOLOGY at power-on (or MS later, --run).

    TOPOLOGY is {TOPOLOGY_HELP}.  Shows per board its chain position, plug-on
    board, seq ID, firmware state, stored program, the running program's exchange (state,
    cycle time, load) and the three LEDs (red, yellow, green; dissertation B.2.3): in the
    bootloader they show the init lines, once a program runs its status: green blinks at
    a rate that shows the cycle time, yellow flashes after an overrun, red after a CAN
    error and steadily while the watchdog holds the motors stopped.  --json shows also
    the injected faults in progress (none in a fleet of its own)."""


@click.group()
def fleet() -> None:
    """The virtual UCoM fleets: boards that behave like the hardware, on simulated buses."""


@fleet.command("show", help=SHOW_HELP)
@click.argument("topology", metavar="TOPOLOGY")
@click.option("--state", "state_dir", type=click.Path(path_type=Path),
              help="Directory with the boards' non-volatile memory (see 'fleet serve').")
@click.option("--run", "run_ms", type=click.IntRange(0, 600_000), default=0,
              metavar="MS", help="Let the fleet run MS milliseconds (virtual time) first: "
                                 "programs with AutoStart come up and show their run-mode "
                                 "LEDs.")
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of tables.")
def show(topology: str, state_dir: Path | None, run_ms: int, as_json: bool) -> None:
    f = Fleet.load(topology, state_dir=state_dir)
    if run_ms:
        f.run_for(run_ms / 1000)
    snap = f.snapshot()
    if as_json:
        emit_json(snap)
        return
    total = sum(len(b["boards"]) for b in snap["buses"])
    stdout().print(f"[bold]{escape(snap['topology'])}[/] - {escape(snap['description'])}")
    stdout().print(f"{total} boards on {len(snap['buses'])} buses\n")
    for bus in snap["buses"]:
        t = FitTable(f"{bus['name']} ({bus['bitrate'] // 1000} kbit/s)")
        for col, drop in (("pos", 0), ("placement", 0), ("board", 3), ("FPGA", 4),
                          ("seq ID", 0), ("fixed ID", 1), ("state", 0), ("program", 0),
                          ("exchange", 2), ("LEDs r y g", 0)):
            t.add_column(col, drop=drop, no_wrap=col == "LEDs r y g")
        for b in bus["boards"]:
            prog = b["program"]
            f = b["fpga"]
            fpga = f"{board_name(f['board_id'])} app {f['app_id']} v{f['version']}" + (
                " [red]NEUTRAL[/]" if f["neutral"] else "")
            t.add_row(
                str(b["position"]), escape(b["placement"]), b["board"], fpga,
                str(b["seq_id"] or "-"),
                str(b["fixed_id"] or "-"), b["state"],
                f"{escape(prog['name'])} {prog['progid']}" if prog else "[dim]none[/]",
                _exchange(b["runtime"]), leds(b["leds"]))
        stdout().print(t)
        if bus["broken_init_links"]:
            stdout().print(f"  [yellow]init line cut before position(s) "
                      f"{', '.join(map(str, bus['broken_init_links']))}[/]")
    if not run_ms:
        stdout().print("[dim]LEDs at power-on: first board yellow only, every later board "
                       "yellow+green (B.2.3); 'ucom init' numbers the boards.[/]")
    if any(b["fpga"]["neutral"] for bus in snap["buses"] for b in bus["boards"]):
        stdout().print("[red]NEUTRAL[/]: the FPGA is made for another plug-on board than the one "
                  "plugged on; it ignores its inputs and keeps its outputs high impedance.")


class _Processes(click.ParamType):
    """``--processes``: ``auto`` (None) or a number of processes, 1 or more."""

    name = "auto|N"

    def convert(self, value: Any, param: click.Parameter | None,
                ctx: click.Context | None) -> int | None:
        if value is None or isinstance(value, int):
            return value
        text = str(value).strip().lower()
        if text == "auto":
            return None
        if text.isdigit() and int(text) >= 1:
            return int(text)
        self.fail(f"{value!r} is neither 'auto' nor a number of processes (1 or more)", param,
                  ctx)


def _extra_bus_names(ctx: click.Context, param: click.Parameter,
                     value: tuple[str, ...]) -> tuple[str, ...]:
    """``--extra-bus``: each a usable channel name, none twice."""
    for i, name in enumerate(value):
        if not EXTRA_BUS_NAME.fullmatch(name):
            raise click.BadParameter(
                f"{name!r} is not a channel name: 1-15 characters, a letter first, then "
                "letters, digits, '_', '.' or '-'", ctx, param)
        if name in value[:i]:
            raise click.BadParameter(f"{name!r} is given twice", ctx, param)
    return value


def with_extra_buses(robot: Topology, names: tuple[str, ...]) -> Topology:
    """``robot`` with a bus of no boards for each of ``names`` after its own (at
    :data:`EXTRA_BUS_BITRATE`); a usage error naming the bus when one is the robot's."""
    own = [bus.name for bus in robot.buses]
    for name in names:
        if name in own:
            raise click.BadParameter(
                f"{name!r} is a bus of {robot.name} ({', '.join(own)}); an extra bus needs "
                "a name of its own", param_hint="'--extra-bus'")
    return replace(robot, buses=robot.buses + tuple(
        BusSpec(name, EXTRA_BUS_BITRATE, ()) for name in names))


@fleet.command("serve")
@click.argument("topology", metavar="TOPOLOGY")
@click.option("--state", "state_dir", type=click.Path(path_type=Path),
              help="Keep each board's flash and AutoStart flag in DIR across restarts.")
@click.option("--host", default="127.0.0.1", show_default=True, help="Address to bind.")
@click.option("--port", default=DEFAULT_PORT, show_default=True, type=click.IntRange(0, 65535),
              help="TCP port (0 = any free port; the chosen one is printed).")
@click.option("--max-clients", default=MAX_CLIENTS, show_default=True,
              type=click.IntRange(1, None),
              help="Clients served at once (on all buses together); one more is told "
                   "'< error too many clients (N) >' and closed.")
@click.option("--processes", type=_Processes(), default="auto", show_default=True,
              help="auto: serve each bus from a process of its own when TOPOLOGY has more "
                   "than one bus (each bus steps on its own), but no more "
                   "processes than this machine has cores; 1: the whole fleet in this "
                   "process; N: the buses shared out among N processes (at most one per "
                   "bus).")
@click.option("--defect", metavar="NAME",
              help="Serve mutant boards: every board that names no defect in the topology "
                   "breaks the protocol in this documented way ('ucom fleet defects' lists "
                   "them), to show that a conformance suite catches it.")
@click.option("--fault", "old_fault", metavar="NAME", hidden=True,
              help="The old name of --defect.")
@click.option("--loss", type=click.FloatRange(0, 1, max_open=True), default=0.0,
              metavar="SHARE", help="Lose this share of the frames between each client and "
                                    "its bus, each way (e.g. 0.01), as a lossy link to the "
                                    "PC would: to try tools the way they will meet a real "
                                    "bus.")
@click.option("--seed", type=int, default=0, show_default=True,
              help="Seed of --loss (each client's losses are drawn from SEED, its bus and its "
                   "number).")
@click.option("--scenario", "scenario_file", metavar="FILE", type=click.Path(path_type=Path),
              help="Injected faults, timed from each bus's first MCA Alive: boards that lose "
                   "power, reset or go bus-off, a cut cable, the emergency stop (TOML, 'man "
                   "ucom', SCENARIOS); 'ucom fleet fault' injects one by hand.")
@click.option("--extra-bus", "extra_buses", metavar="NAME", multiple=True,
              callback=_extra_bus_names,
              help="Also serve a bus NAME with no boards on it (repeatable): a channel where "
                   "clients in other processes meet (a gateway and a CANopen master), each "
                   "one's frames reaching every other as on the robot's buses (1 Mbit/s; "
                   "--loss applies as there).")
@click.pass_context
def serve(ctx: click.Context, topology: str, state_dir: Path | None, host: str, port: int,
          max_clients: int, processes: int | None, defect: str | None,
          old_fault: str | None, loss: float, seed: int, scenario_file: Path | None,
          extra_buses: tuple[str, ...]) -> None:
    """Serve TOPOLOGY's buses with the socketcand protocol, in real time.

    Other processes reach the boards through a socketcand client: 'ucom ... -i socketcand
    --host 127.0.0.1 --port 29536 -c CAN0', or python-can's
    can.Bus(interface="socketcand", host="127.0.0.1", port=29536, channel="CAN0").
    No client can stop the bus for the others: a malformed element gets
    '< error ... >', a client that stops reading is dropped, connections are limited.
    Clients dropped or refused are logged on stderr (-v: every connection).  Runs until
    interrupted: Ctrl-C (exit code 130) or SIGTERM (143).

    With --processes auto (the default) a topology with several buses is served from one
    process per bus behind the one port: the buses share nothing but the wall clock, to
    which each is paced.  A bus process that dies stops the whole serve (exit code 4,
    naming the bus).

    --defect NAME serves mutant boards, e.g. 'ucom fleet serve armar3 --defect
    seq-from-zero' (see 'ucom fleet defects').

    --scenario FILE injects faults as it serves (each at its time after the first MCA
    Alive on its bus; a whole-robot fault on each bus from that bus's own); 'ucom fleet
    fault' injects one by hand, on this port.

    --extra-bus CO0 serves a channel CO0 beside the robot's buses with no boards on it,
    e.g. for 'ucom gateway canopen' and a CANopen master in other processes."""
    defect = _defect(defect, old_fault)
    robot = topo.load(topology)
    scenario = None
    if scenario_file is not None:
        scenario = Scenario.load(scenario_file)
        scenario.check(robot)  # before anything runs
    robot = with_extra_buses(robot, extra_buses)
    count = _process_count(robot, processes)
    verbose = int((ctx.find_root().obj or {}).get("verbose", 0))
    log_level = logging.INFO if verbose else logging.WARNING
    logging.basicConfig(level=log_level, format=LOG_FORMAT, stream=sys.stderr)
    # the fleet's driver thread is busy most of the time: switch threads often, so
    # that clients' readers and writers get their turn within a cycle
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    logging.getLogger("ucom.fleet").setLevel(logging.INFO)  # a scenario's faults as they come
    if count > 1:
        _serve_per_bus(robot, state_dir, host, port, max_clients, log_level, count,
                       {**({"defect": defect} if defect else {}),
                        **({"client_loss": loss, "seed": seed} if loss else {}),
                        **({"scenario": scenario} if scenario else {})},
                       extra=extra_buses, auto=processes is None)
        return
    f = Fleet(robot, state_dir=state_dir, realtime=True, defect=defect, client_loss=loss,
              seed=seed, scenario=scenario)
    try:
        server = FleetServer(f, host, port, max_clients=max_clients)
    except OSError as e:
        f.close()
        raise BusError(f"cannot listen on {host}:{port}: {e.strerror}") from None
    h, p = server.address
    print(f"listening on {h}:{p}", flush=True)
    one_core = ("one process (auto: 1 core); "
                if processes is None and len(robot.buses) > 1 else "")
    stderr().print(f"serving {f.name} ({', '.join(f.buses)}) with socketcand on {h}:{p}; "
                   f"{one_core}{_extra(extra_buses)}{_mutants(defect)}{_losing(loss)}"
                   f"{_scenario(scenario)}"
                   f"state: {state_dir or 'not kept'}; Ctrl-C stops")
    try:
        with sigterm_interrupts():
            serve_until_interrupted(server)
    finally:
        f.close()
        sys.stdout.flush()


def _process_count(robot: Topology, asked: int | None) -> int:
    """How many processes serve ``robot``: ``--processes N`` as asked (a usage error when
    N exceeds the buses: a bus is never split), ``auto`` (None) one per bus up to the
    cores there are (:func:`~ucom_tools.virtual.serve.multiserve.auto_processes`)."""
    buses = len(robot.buses)
    if asked is None:
        return auto_processes(robot)
    if asked > buses:
        raise click.BadParameter(
            f"{asked} processes for {robot.name}, which has {buses} "
            f"bus{'' if buses == 1 else 'es'}: at most one process per bus "
            f"(give {buses}, or auto)", param_hint="'--processes'")
    return asked


def _serve_per_bus(robot: Topology, state_dir: Path | None, host: str, port: int,
                   max_clients: int, log_level: int, processes: int,
                   fleet_options: dict[str, Any], *, extra: tuple[str, ...] = (),
                   auto: bool = False) -> None:
    """``fleet serve --processes auto``: one process per bus (or N processes for the
    buses) behind one port."""
    try:
        server = MultiServer(robot, host, port, state_dir=state_dir, max_clients=max_clients,
                             log_level=log_level, switch_interval=SWITCH_INTERVAL_S,
                             processes=processes, fleet_options=fleet_options)
    except OSError as e:
        raise BusError(f"cannot listen on {host}:{port}: {e.strerror}") from None
    with server:
        with sigterm_interrupts():
            server.start()
        h, p = server.address
        print(f"listening on {h}:{p}", flush=True)
        shares = ("one process per bus" if len(server.processes) == len(server.buses) else
                  f"{len(server.processes)} processes"
                  + (f" (auto: {usable_cores()} cores)" if auto else "") + ": "
                  + "; ".join(worker.label for worker in server.processes))
        stderr().print(f"serving {robot.name} ({', '.join(server.buses)}) with socketcand on "
                       f"{h}:{p}, {shares}; {_extra(extra)}"
                       f"{_mutants(fleet_options.get('defect'))}"
                       f"{_losing(fleet_options.get('client_loss', 0.0))}"
                       f"{_scenario(fleet_options.get('scenario'))}"
                       f"state: {state_dir or 'not kept'}; "
                       "Ctrl-C stops")
        try:
            server.serve_until_interrupted()
        finally:
            sys.stdout.flush()


def _extra(names: tuple[str, ...]) -> str:
    if not names:
        return ""
    return f"{', '.join(names)} without boards (--extra-bus); "


def _losing(loss: float) -> str:
    return "" if not loss else f"[bold yellow]losing {loss:.1%} of the frames each way[/]; "


def _scenario(scenario: Scenario | None) -> str:
    if scenario is None:
        return ""
    count = len(scenario.faults)
    return (f"[bold yellow]scenario {escape(scenario.source)} ({count} fault"
            f"{'' if count == 1 else 's'})[/]; ")


def _defect(defect: str | None, old_fault: str | None) -> str | None:
    """The --defect NAME asked for (checked), or --fault NAME, its old name (said on stderr)."""
    if old_fault is not None:
        if defect is not None:
            raise click.UsageError("--fault is the old name of --defect: give one of them")
        stderr().print("[yellow]--fault is the old name of --defect; it still works[/]")
        return mutants.check(old_fault, key="--fault")
    return mutants.check(defect, key="--defect")


def _mutants(defect: str | None) -> str:
    return "" if defect is None else f"[bold yellow]mutant boards ({escape(defect)})[/]; "


@fleet.command("fault")
@click.argument("words", nargs=-1, required=True, metavar="[TARGET] KIND")
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Host of the 'ucom fleet serve'.")
@click.option("--port", default=DEFAULT_PORT, show_default=True,
              type=click.IntRange(1, 65535), help="Its socketcand port.")
@click.option("--for", "for_s", type=click.FloatRange(0, MAX_SECONDS), metavar="SECONDS",
              help="How long until it ends (reset: 0 unless given; the other kinds need "
                   "it).")
@click.option("--json", "as_json", is_flag=True, help="Print what was done as JSON.")
def fault_cmd(words: tuple[str, ...], host: str, port: int, for_s: float | None,
              as_json: bool) -> None:
    """Inject a fault into a running 'ucom fleet serve', at once, and print what it did.

    TARGET is a board (CAN0/3 or CAN0:3: bus and seq ID), a bus (CAN0) or robot;
    KIND is one of:

    \b
      power-off  the board loses power for --for seconds (its RAM, seq ID, FPGA
                 counters gone; it comes back in its bootloader or, with AutoStart,
                 its program, STOPPED, with no seq ID)
      reset      its DSP resets: silent for the reset time (+ --for), the same loss
      bus-off    its CAN controller neither sends nor acknowledges; its program runs
                 on (the watchdog fires after the watchdog time)
      cable      the bus's frames are lost between the PC and its boards
      estop      every board of the robot powered off (TARGET robot, or none)

    e.g. 'ucom fleet fault CAN0/3 power-off --for 1', 'ucom fleet fault estop --for 2'.
    Exit 2 for a TARGET or KIND that do not fit, 3 when the fleet has no such bus or
    board (nothing was done), 4 when no fleet that takes faults answers on HOST:PORT."""
    from ucom_tools.transport.fault_request import request_fault

    if len(words) == 1 and words[0] == FaultKind.ESTOP.value:
        target, kind = ROBOT, words[0]
    elif len(words) == 2:
        target, kind = words
    else:
        raise click.UsageError("give TARGET KIND (e.g. CAN0/3 power-off), or estop alone")
    try:
        asked = injected(kind, target, for_s)  # refuses what cannot fit, before connecting
    except InputError as err:
        raise click.UsageError(describe(err)) from None
    done = request_fault(host, port, asked.target, asked.kind.value, asked.for_s)
    if as_json:
        emit_json({"server": f"{host}:{port}", **asked.as_dict(), "done": done})
        return
    stdout().print(escape(done))


@fleet.command("defects")
@click.option("--json", "as_json", is_flag=True, help="Print the defects as JSON.")
def defects(as_json: bool) -> None:
    """List the defects a mutant board can have ('fleet serve --defect NAME', a topology's
    'defect = "NAME"'): each breaks ucom-protocol(7) in one documented way, names the
    section it violates and what a client sees."""
    if as_json:
        emit_json({"defects": [d.as_dict() for d in mutants.defects()]})
        return
    table = FitTable(box=None, show_header=True, header_style="bold")
    for col in ("defect", "what the board does wrong", "violates"):
        table.add_column(col)
    for d in mutants.defects():
        table.add_row(d.name, escape(d.title), escape(d.section))
    stdout().print(table)


@fleet.command("faults", hidden=True)
@click.option("--json", "as_json", is_flag=True, help="Print the defects as JSON.")
@click.pass_context
def old_faults(ctx: click.Context, as_json: bool) -> None:
    """The old name of 'ucom fleet defects' (its JSON under the old key, "faults")."""
    stderr().print("[yellow]'fleet faults' is the old name of 'fleet defects'; it still "
                   "works[/]")
    if as_json:
        emit_json({"faults": [d.as_dict() for d in mutants.defects()]})
        return
    ctx.invoke(defects, as_json=False)


def _exchange(rt: dict[str, Any] | None) -> str:
    """A running program's exchange in a few words: 'RUNNING 1 ms 70%'."""
    if rt is None:
        return "[dim]-[/]"
    style = {"RUNNING": "green", "LATCHED": "red"}.get(rt["state"], "yellow")
    cycle = rt["cycle_us"]
    cycle_text = f"{cycle / 1000:g} ms" if cycle >= 1000 else f"{cycle:g} us"
    late = f" [yellow]{rt['overruns']} overruns[/]" if rt["overruns"] else ""
    return f"[{style}]{rt['state']}[/] {cycle_text} {rt['load']:.0%}{late}"
