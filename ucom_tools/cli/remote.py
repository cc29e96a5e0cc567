"""``ucom remote``: the run-time part (dsp_remote_part) on the command line: ``check`` the
boards against their trees, ``run`` the cyclic exchange (a live view on a terminal, or
``--for N`` seconds and a summary), ``plot`` a recorded run."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click
from rich.markup import escape

from ucom_tools.cli import run_summary as say
from ucom_tools.cli.exitcodes import EXIT_FAILED
from ucom_tools.cli.options import Finite, connection_json, connection_options, json_option
from ucom_tools.cli.output import emit_json, stderr
from ucom_tools.cli.remote_run import one_bus, part_of, run_robot
from ucom_tools.errors import InputError
from ucom_tools.net.keys import DEFAULT_ENDPOINT
from ucom_tools.ops.remote.faults import POLICIES, STOP
from ucom_tools.ops.remote.report import MappingError
from ucom_tools.ops.robot import ConnectSpec
from ucom_tools.viewers.foxglove_msgs import DEFAULT_ADDRESS as FOXGLOVE_ADDRESS
from ucom_tools.wire import mca

ROBOT_HELP = ("ROBOT_OR_TREES is the robot: a bundled topology (armar3, lauron4, ...) or a "
              "topology file whose boards name their attribute trees (not needed with "
              "--virtual or --topology, which name it); and/or attribute tree files, which "
              "replace the robot's trees of the same Prefix.")


@click.group("remote")
def remote() -> None:
    """The run time: boards in the cyclic exchange, values by robot-wide name.

    See ucom-protocol(7), RUN TIME, for what goes over the bus."""


CHECK_HELP = (
    """Check the running boards against their attribute trees (the mapping check).

    """
    + ROBOT_HELP + """  Starts each board's program if it is not running, fetches
    its edge descriptions and compares them with its tree's mapping table: every edge the
    tree names must be the board's, in the same order and of the same kind.  Writes
    nothing.  Exit 1 when a board differs or does not answer.""")


@remote.command("check", help=CHECK_HELP)
@click.argument("robot_or_trees", nargs=-1)
@connection_options
@json_option
@click.pass_context
def check(ctx: click.Context, robot_or_trees: tuple[str, ...], spec: ConnectSpec,
          bus_name: str | None, as_json: bool) -> None:
    with part_of(robot_or_trees, one_bus(spec, bus_name)) as part:
        report = part.check()
        if as_json:
            emit_json({"connection": connection_json(spec), "ok": report.ok,
                       "boards": say.check_json(report)})
        else:
            say.print_check(report)
        if report.boards and all(b.no_program for b in report.boards):
            raise MappingError(report)  # one line that says what to do (part_of)
    if not report.ok:
        ctx.exit(EXIT_FAILED)


RUN_HELP = (
    """Run the robot's boards in the cyclic exchange.

    """
    + ROBOT_HELP + """  Starts each board's program if needed, checks its edges
    against its tree (a difference: every one is listed, nothing starts, exit 1, unless
    --force), writes the trees' PAR and CI defaults, sets up the SO maps at the programs'
    default rates (the bus load is estimated first: over 100 % is refused, over 70 %
    warned), starts the exchange on every bus and runs the PC's loop: CI maps and MCA
    Alive every cycle.  It first listens on every bus for the boards' watchdog time:
    where another host's exchange runs (MCA Alive or CI maps it did not send) nothing is
    sent and the exit code is 4, unless --force.  On a terminal a live view shows every
    value; 'set NAME VALUE' changes a CI or PAR while running.  The live view, --record
    and --zenoh run in a process of their own, apart from the loop, and read only the
    snapshots it hands over: none of them can keep it from its deadline.  With --for it runs N
    seconds and prints what the joints did (--json: every edge's last value and the
    loop's figures).  Ctrl-C or the end stops every board (motors off); a PC that dies
    leaves them to their watchdog.  A board that is lost (it went silent: power,
    reset, bus-off, a cable, the emergency stop; or its bus failed) stops every other
    board and ends the run with exit 1 naming it (--on-fault stop), or is reported while
    the others run on (--on-fault hold), and with --rejoin brought back when it returns,
    its joints held where they stand (ucom-protocol(7), RUN TIME, Faults); --json lists
    them under 'faults'.""")


_RUN_OPTIONS = [
    click.option("--set", "sets", multiple=True, metavar="NAME=VALUE",
                  help="Set a CI or PAR edge by its robot-wide name after the start "
                       "(repeatable), e.g. --set 'Right Eye Target=1000'."),
    click.option("--for", "seconds", type=Finite(0, min_open=True), metavar="SECONDS",
                  help="Run this long, then stop the boards and print what they did."),
    click.option("--rate", type=Finite(1, 10_000), default=1000.0, show_default=True,
                  metavar="HZ", help="Cycles per second of the PC's loop."),
    click.option("--watchdog", "alive_ms", type=click.IntRange(mca.ALIVE_MIN_MS,
                                                                mca.ALIVE_MAX_MS),
                  default=mca.ALIVE_DEFAULT_MS, show_default=True, metavar="MS",
                  help="The boards stop their motors when no MCA Alive came for this long."),
    click.option("--record", "record", type=click.Path(), metavar="FILE",
                  help="Record every frame (format by extension: .asc .blf .log .trc; .csv "
                       ".db for one bus) and every value change to FILE.values.csv; or, as "
                       "FILE.mcap, frames, values per board, joints, events and the robot's "
                       "structure in one MCAP file (Foxglove, Lichtblick; ucom(1), MCAP "
                       "RECORDINGS)."),
    click.option("--record-rate", "record_hz", type=Finite(0, min_open=True), metavar="HZ",
                  help="Values per second per board in an MCAP --record (default: the "
                       "loop's rate; at most that)."),
    click.option("--period", "periods", multiple=True, metavar="EDGE=CYCLES",
                  help="Exchange a program edge (its generic name, on every board that runs "
                       "the program) every CYCLES cycles instead of its default (0: not "
                       "cyclic), e.g. --period 'Voltage A=10'."),
    click.option("--force", is_flag=True,
                  help="Start the boards that match their trees even when others do not, and "
                       "start even where another host's exchange runs (its MCA Alive or CI "
                       "maps are on the bus: exit code 4 without --force)."),
    click.option("--realtime", is_flag=True,
                  help="Run the PC's loop under SCHED_FIFO (Linux; needs CAP_SYS_NICE or an "
                       "rtprio limit), so other busy processes cannot make it miss cycles; "
                       "where not permitted it runs as usual and says why.  Without it the "
                       "loop asks for a 0.1 ms time slice (Linux 6.12 and later)."),
    click.option("--zenoh", "zenoh_endpoint", is_flag=False, flag_value=DEFAULT_ENDPOINT,
                  default=None, metavar="[ENDPOINT]",
                  help="Share the running robot on Zenoh, listening on ENDPOINT (alone: "
                       f"{DEFAULT_ENDPOINT}, this host only): its structure, values and events "
                       "for 'ucom browse' on other hosts (ucom-network(7))."),
    click.option("--zenoh-config", "zenoh_config", type=click.Path(dir_okay=False),
                  metavar="FILE", help="Share it with this Zenoh JSON5 configuration (TLS, "
                       "authentication, access control, routers); --zenoh replaces its listen "
                       "endpoints."),
    click.option("--foxglove", "foxglove", is_flag=False, flag_value=FOXGLOVE_ADDRESS,
                  default=None, metavar="[HOST:PORT]",
                  help="Serve the running robot to the Foxglove app or Lichtblick (the "
                       "Foxglove WebSocket protocol) on HOST:PORT (alone: "
                       f"{FOXGLOVE_ADDRESS}, this host only): each board's values, the "
                       "joints, every bus's frames, the run's events; only what a client "
                       "subscribes to is encoded (ucom(1), FOXGLOVE)."),
    click.option("--allow-writes", is_flag=True,
                  help="Take writes (CI, PAR) and a stop from the network (--zenoh; "
                       "--foxglove: writes only), checked as a local --set; without it they "
                       "are refused.  Starting is never taken."),
    click.option("--publish-rate", "publish_hz", type=Finite(0, min_open=True), default=100.0,
                  show_default=True, metavar="HZ",
                  help="How often the shared values go out (at most the loop's rate)."),
    click.option("--on-fault", "on_fault", type=click.Choice(POLICIES), default=STOP,
                  show_default=True,
                  help="When a board is lost (none of its SO maps for 3 periods of its "
                       "fastest, at least 5 ms; or its bus failed): 'stop' stops every other "
                       "board at once (motors off) and ends the run, exit 1; 'hold' runs the "
                       "others on with their targets and reports the lost board (writes to "
                       "it are refused)."),
    click.option("--rejoin", is_flag=True,
                  help="With --on-fault hold: bring a lost board back when it returns, without "
                       "stopping the loop (its program started and configured again, its "
                       "targets set to where its joints stand: no joint jumps).  A run whose "
                       "every lost board rejoined exits 0 and lists its faults."),
]


def run_options(f: Any) -> Any:
    """The options of a run (``remote run``; ``gateway canopen`` adds its own)."""
    for option in reversed(_RUN_OPTIONS):
        f = option(f)
    return f


@remote.command("run", help=RUN_HELP)
@click.argument("robot_or_trees", nargs=-1)
@run_options
@connection_options
@json_option
@click.pass_context
def run(ctx: click.Context, robot_or_trees: tuple[str, ...], **options: Any) -> None:
    run_robot(ctx, robot_or_trees, **options)




LAYOUT_HELP = """Write a layout for the Foxglove app or Lichtblick that shows ROBOT.

ROBOT is a bundled topology (armar3, lauron4, ...) or a topology file whose boards name
their attribute trees.  A tab per board with joints: a plot of each joint's sensor
against its target and one of its velocity against its velocity target (the values
topics of 'remote run --foxglove' and of a '--record FILE.mcap', which are the same);
a tab with the run's events (/events); a last one with the latest frame of the first bus
(/CAN0/frames; the panel's topic field picks another bus: a browser sent every bus's
frames falls behind).  Import it in the app (Layouts, Import from file), then open
ws://127.0.0.1:8765 or the recording.  Lichtblick refuses the app's format: give it
--for lichtblick (the format of Foxglove Studio 1.x, which Lichtblick reads).  The file
is written whole or not at all; an existing one only with --force (else exit code 3)."""


@remote.command("layout", help=LAYOUT_HELP)
@click.argument("robot")
@click.option("-o", "--output", required=True, metavar="FILE",
              help="The layout file to write (JSON; '-': standard output).")
@click.option("--for", "form", type=click.Choice(("foxglove", "lichtblick")),
              default="foxglove", show_default=True,
              help="The app the layout is for.")
@click.option("--force", is_flag=True, help="Replace an existing FILE.")
def layout(robot: str, output: str, form: str, force: bool) -> None:
    from ucom_tools.fileio import STDOUT, write_text
    from ucom_tools.gateway import joints
    from ucom_tools.viewers.foxglove_layout import layout_json

    found = joints.load(robot)
    text = layout_json(found, form)
    if output != STDOUT and Path(output).is_file() and not force:
        raise InputError(f"{output} exists; --force replaces it", key="--output")
    write_text(output, text + "\n", key="--output", allow_stdout=True)
    if output != STDOUT:
        stderr().print(f"wrote {escape(output)}: a layout for {escape(form)}, "
                       f"{len(found.joints)} joints of {escape(found.topology.name)}",
                       highlight=False)


try:
    from ucom_tools.cli.plot import plot as _plot
    remote.add_command(_plot)
except ImportError:  # pragma: no cover - while plot.py is written
    pass
