"""``ucom remote``: the run-time part (dsp_remote_part) on the command line: ``check`` the
boards against their trees, ``run`` the cyclic exchange (a live view on a terminal, or
``--for N`` seconds and a summary), ``plot`` a recorded run."""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import replace
from decimal import Decimal
from pathlib import Path
from typing import Any

import click
from rich.markup import escape

from ucom_tools.cli.consumers import END_S, ConsumerProcess, ExtraConsumer, error_of
from ucom_tools.cli.exitcodes import EXIT_BUS, EXIT_FAILED
from ucom_tools.cli.options import (
    Finite,
    connection_json,
    connection_options,
    json_option,
    parse_sets,
)
from ucom_tools.cli.output import emit_json, json_number, stderr, stdout
from ucom_tools.cli.tables import FitTable, shown_path
from ucom_tools.config import topology as topo
from ucom_tools.errors import InputError, UcomError
from ucom_tools.net.keys import DEFAULT_ENDPOINT, check_rate, robot_id
from ucom_tools.ops.realtime import frozen_heap
from ucom_tools.ops.remote import (
    HOLD,
    POLICIES,
    STOP,
    BoardEvent,
    BoardFault,
    BoardLost,
    CheckReport,
    MappingError,
    RemotePart,
    RemoteStop,
    Summary,
    WriteEvent,
    robot_trees,
)
from ucom_tools.ops.remote_feed import ConsumersGone, LoopFeed, Quit
from ucom_tools.ops.remote_publish import LoopHandover, LoopSnapshot
from ucom_tools.ops.robot import ConnectSpec, open_robot
from ucom_tools.signals import Terminated, interrupt_exit_code
from ucom_tools.trace.logs import check_buses, log_extension
from ucom_tools.viewers.foxglove_msgs import DEFAULT_ADDRESS as FOXGLOVE_ADDRESS
from ucom_tools.viewers.foxglove_msgs import parse_address
from ucom_tools.wire import mca
from ucom_tools.wire.codes import ErrorCode

ROBOT_HELP = ("ROBOT_OR_TREES is the robot: a bundled topology (armar3, lauron4, ...) or a "
              "topology file whose boards name their attribute trees (not needed with "
              "--virtual or --topology, which name it); and/or attribute tree files, which "
              "replace the robot's trees of the same Prefix.")
WARN_LOAD = 0.70


@click.group("remote")
def remote() -> None:
    """The run time: boards in the cyclic exchange, values by robot-wide name.

    See ucom-protocol(7), RUN TIME, for what goes over the bus."""


# ---------------------------------------------------------------------- the robot
def _is_tree(arg: str) -> bool:
    return arg.endswith(".tree")


def robot_spec(args: tuple[str, ...], spec: ConnectSpec) -> tuple[ConnectSpec, list[str]]:
    """The connection (with the robot's topology) and the tree files given."""
    trees = [a for a in args if _is_tree(a)]
    robots = [a for a in args if not _is_tree(a)]
    if len(robots) > 1:
        raise InputError(f"one robot, not {len(robots)}: {', '.join(robots)}",
                         key="ROBOT_OR_TREES")
    robot = robots[0] if robots else None
    if spec.virtual:
        if robot is not None and topo.load(robot).name != topo.load(spec.virtual).name:
            raise InputError(f"the robot is {robot!r} but --virtual runs {spec.virtual!r}",
                             key="ROBOT_OR_TREES")
        return spec, trees
    if robot is not None:
        if spec.topology and topo.load(spec.topology).name != topo.load(robot).name:
            raise InputError(f"the robot is {robot!r} but --topology is {spec.topology!r}",
                             key="ROBOT_OR_TREES")
        return replace(spec, topology=spec.topology or robot), trees
    if not spec.topology:
        raise InputError("which robot? give it (e.g. 'armar3'), --topology FILE or --virtual "
                         "ROBOT (tree files alone do not say which board runs which)",
                         key="ROBOT_OR_TREES")
    return spec, trees


@contextmanager
def _part(args: tuple[str, ...], spec: ConnectSpec, **kwargs: Any) -> Iterator[RemotePart]:
    spec, files = robot_spec(args, spec)
    r = open_robot(spec)
    try:
        part = RemotePart(r, robot_trees(r, files), **kwargs)
        try:
            yield part
        except MappingError as err:
            if err.no_program:  # the usual first try: the in-process fleet, no --state
                err.args = (f"{err}: {_flash_first(spec, r.topology)}",)
            raise
        finally:
            part.close()
    finally:
        r.close()


def _flash_first(spec: ConnectSpec, robot: topo.Topology | None) -> str:
    """What to do about boards that hold no program."""
    images = {b.image for bus in robot.buses for b in bus.boards} if robot else set()
    one = images.pop() if len(images) == 1 else None
    image = shown_path(one) if one is not None else "IMAGE"
    if not spec.virtual:
        return f"flash them first ('ucom flash {image}', or 'ucom deploy ROBOT')"
    flash = f"'ucom flash {image} --virtual {spec.virtual} --state DIR'"
    if spec.state_dir is None:
        return (f"the in-process fleet powers up with empty boards unless --state DIR keeps "
                f"what was flashed: flash first ({flash}) and give the same --state DIR")
    return f"flash them first ({flash} with this --state)"


# ---------------------------------------------------------------------- check
def _check_json(report: CheckReport) -> list[dict[str, Any]]:
    return [{"bus": b.bus, "board": b.board, "where": b.where, "prefix": b.prefix,
             "tree": b.tree_file, "program": b.program, "ok": b.ok, "error": b.error or None,
             "differences": [{"line": d.line, "message": d.message}
                             for d in b.differences]} for b in report.boards]


def _print_check(report: CheckReport) -> None:
    if report.boards and all(b.no_program for b in report.boards):
        return  # the error says it in one line
    t = FitTable("boards against their trees")
    for col, drop in (("board", 0), ("prefix", 0), ("tree", 2), ("edges CI/SO/PAR", 1),
                      ("result", 0)):
        t.add_column(col, drop=drop)
    for b in report.boards:
        summary = b.summary().removeprefix(f"{b.where}: ")
        result = ("[green]matches[/]" if b.ok else "[red]no program[/]" if b.no_program
                  else f"[red]{escape(summary)}[/]")
        t.add_row(escape(b.where), escape(b.prefix), escape(shown_path(b.tree_file)),
                  b.program or "-", result)
    stdout().print(t)
    for b in report.boards:
        if b.differences:
            tree = shown_path(b.tree_file)
            stdout().print(f"[bold]{escape(b.where)}[/] ({escape(tree)}):")
            for d in b.differences:
                where = f"{tree}:{d.line}: " if d.line else ""
                stdout().print(f"  {escape(where)}{escape(d.message)}", soft_wrap=True)


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
    with _part(robot_or_trees, _one_bus(spec, bus_name)) as part:
        report = part.check()
        if as_json:
            emit_json({"connection": connection_json(spec), "ok": report.ok,
                       "boards": _check_json(report)})
        else:
            _print_check(report)
        if report.boards and all(b.no_program for b in report.boards):
            raise MappingError(report)  # one line that says what to do (_part)
    if not report.ok:
        ctx.exit(EXIT_FAILED)


def _one_bus(spec: ConnectSpec, bus_name: str | None) -> ConnectSpec:
    if bus_name is None:
        return spec
    if spec.virtual:
        raise InputError("--bus with --virtual: the run time takes the whole robot",
                         key="--bus")
    return replace(spec, only=bus_name)


# ---------------------------------------------------------------------- run
def _parse_periods(periods: tuple[str, ...]) -> dict[str, int]:
    out = {}
    for p in periods:
        name, sep, value = p.partition("=")
        try:
            n = int(value)
        except ValueError:
            n = -1
        if not sep or not name.strip() or not 0 <= n <= 0xFFFF:
            raise InputError(f"{p!r}: expected EDGE=CYCLES with CYCLES 0..65535 (e.g. "
                             "'Voltage A=10')", key="--period")
        out[name.strip()] = n
    return out


def _plan_notes(part: RemotePart) -> None:
    for name, x in part.exchanges.items():
        p = x.plan
        line = (f"{name}: the exchange needs {p.nominal:.1%} of the bus "
                f"({p.worst:.1%} with the most stuff bits), {len(p.so_maps)} SO and "
                f"{len(p.ci_maps)} CI maps")
        if p.nominal > WARN_LOAD:
            stderr().print(f"[yellow]ucom: {escape(line)}: over {WARN_LOAD:.0%}, frames may "
                           "be late[/]", soft_wrap=True)
        else:
            stderr().print(f"[dim]{escape(line)}[/]", soft_wrap=True)


def _value_text(v: object) -> str:
    if isinstance(v, Decimal):
        return format(v, "f")
    return str(v)


def _stats_json(part: RemotePart, loads: dict[str, float]) -> dict[str, Any]:
    s = part.stats
    return {"cycles": s.cycles, "rate_hz": round(s.rate(part._clock()), 1),
            "missed": s.missed, "longest_gap_ms": round(s.longest_gap_s * 1e3, 3),
            "jitter_ms": {
                "p50": round(s.percentile(50) * 1e3, 3),
                "p99": round(s.percentile(99) * 1e3, 3),
                "max": round(max(s.late, default=0.0) * 1e3, 3)},
            "bus_load": {n: round(v, 4) for n, v in loads.items()},
            "planned_load": {n: {"nominal": round(x.plan.nominal, 4),
                                 "worst": round(x.plan.worst, 4)}
                             for n, x in part.exchanges.items()},
            "virtual_time": part.virtual,
            "realtime": part.scheduled_as}


def _boards_json(part: RemotePart) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    current: dict[str, Any] | None = None
    for ref in part.names:
        if current is None or (current["bus"], current["board"]) != (ref.bus, ref.board):
            current = {"bus": ref.bus, "board": ref.board, "where": ref.where,
                       "prefix": ref.prefix, "edges": []}
            out.append(current)
        raw = part.raw(ref)
        value = None if raw is None else ref.value(raw)
        current["edges"].append({"name": ref.unique, "kind": ref.kind.name,
                                 "value": json_number(value),
                                 "text": None if value is None else _value_text(value)})
    return out


def _print_summary(part: RemotePart, summary: Summary, loads: dict[str, float]) -> None:
    changed = [(r, summary.traces[r]) for r in part.names
               if r.kind is mca.Kind.SO and r in summary.traces and summary.traces[r].changes]
    # flags and one-count jitter (Settled 0 -> 1, an encoder's last count) say little here
    moved = [(r, t) for r, t in changed if r.raw(t.high) - r.raw(t.low) > 1]
    t = FitTable("what the joints did (sensor values that moved)")
    for col, drop in (("board", 1), ("name", 0), ("first", 0), ("last", 0), ("range", 0),
                      ("unit", 0)):
        t.add_column(col, drop=drop)
    clipped = False
    for ref, tr in moved:
        low, high = _value_text(tr.low), _value_text(tr.high)
        # a value at the end of what its encoding can carry: the board clipped it (the
        # quantity went further, e.g. a velocity over 32767 counts/s)
        least, most = ref.spec.raw_limits()
        if ref.raw(tr.low) <= least:
            low, clipped = f"{low}*", True
        if ref.raw(tr.high) >= most:
            high, clipped = f"{high}*", True
        t.add_row(escape(ref.where), escape(ref.unique), _value_text(tr.first),
                  _value_text(tr.last), f"{low} .. {high}", escape(ref.spec.unit))
    if moved:
        stdout().print(t)
        if clipped:
            stdout().print("[dim]* the most the edge's encoding can carry: the value went "
                           "further and was clipped[/]")
    jitter = len(changed) - len(moved)
    if not moved:
        stdout().print("no sensor value moved" + (
            f" by more than one count: {jitter} changed by one count or a flag only "
            "(--json lists every value)" if jitter else ""), soft_wrap=True)
    elif jitter:
        stdout().print(f"[dim]{jitter} more changed by one count or a flag only (--json "
                       "lists every value)[/]")
    s = part.stats
    clock = "virtual time" if part.virtual else "wall clock"
    gap = (f" (the longest gap between two cycles {s.longest_gap_s * 1e3:.1f} ms)"
           if s.missed else "")
    stdout().print(
        f"{s.cycles} cycles at {s.rate(part._clock()):.0f} Hz ({clock}), {s.missed} missed"
        f"{gap}, "
        f"lateness p50 {s.percentile(50) * 1e3:.3f} ms, p99 {s.percentile(99) * 1e3:.3f} "
        f"ms; bus load " + ", ".join(f"{n} {v:.1%}" for n, v in loads.items())
        + ("" if part.scheduling is None else f"; {part.scheduled_as}"))


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


def run_robot(ctx: click.Context, robot_or_trees: tuple[str, ...], sets: tuple[str, ...],
              seconds: float | None, rate: float, alive_ms: int, record: str | None,
              record_hz: float | None, periods: tuple[str, ...], force: bool, realtime: bool,
              zenoh_endpoint: str | None, zenoh_config: str | None, allow_writes: bool,
              publish_hz: float, on_fault: str, rejoin: bool, spec: ConnectSpec,
              bus_name: str | None, as_json: bool, extra: ExtraConsumer | None = None,
              foxglove: str | None = None) -> None:
    """``remote run``'s work; ``extra`` adds a consumer to the consumers' process (the
    CANopen gateway of ``gateway canopen``)."""
    if rejoin and on_fault != HOLD:
        raise click.UsageError("--rejoin needs --on-fault hold: under --on-fault stop a "
                               "lost board ends the run", ctx=ctx)
    wanted = parse_sets(sets)
    cycles = _parse_periods(periods)
    sharing = zenoh_endpoint is not None or zenoh_config is not None
    fox = parse_address(foxglove) if foxglove is not None else None  # exit 3 at once
    if allow_writes and not sharing and fox is None:
        raise InputError("writes from the network need the network: give --zenoh or "
                         "--foxglove", key="--allow-writes")
    view = seconds is None and sys.stdout.isatty() and not as_json
    summary = Summary()
    interrupted = 0  # the exit code of an interrupt
    how = ""
    consumer_error: UcomError | None = None  # what ended the consumers' process
    consumers: ConsumerProcess | None = None
    recorded: dict[str, int] = {}  # --record: the frames each bus saw while recording
    with ExitStack() as stack:
        spec = _one_bus(spec, bus_name)
        if record is not None:  # checked up front; the file is written by the consumers
            log_extension(record, key="--record")
        _check_record_rate(record, record_hz, rate)
        with _part(robot_or_trees, spec, rate_hz=rate, alive_ms=alive_ms,
                   periods=cycles or None, realtime=realtime, on_fault=on_fault,
                   rejoin=rejoin) as part:
            if sharing or fox is not None:
                check_rate(publish_hz, 1.0 / part.period_s)
            if record is not None:  # exit 3 before the exchange starts
                check_buses(log_extension(record, key="--record"), part.robot.buses,
                            Path(record), "--record")
            if not as_json:
                _plan_notes(part)
            feed: LoopFeed | None = None
            if record is not None or sharing or view or extra is not None or fox:
                # the view, the recording, the share and the gateway in a process of their
                # own: none of them holds the lock this process's loop needs
                # (ops/remote_feed.py)
                config = _consumers_config(part, record, view, zenoh_endpoint, zenoh_config,
                                           allow_writes, publish_hz, force)
                config["record_hz"] = record_hz
                if extra is not None:
                    config[extra.name] = extra.config
                if fox is not None:
                    config["foxglove"] = {"host": fox[0], "port": fox[1],
                                          "allow_writes": allow_writes,
                                          "publish_hz": publish_hz}
                consumers = ConsumerProcess(config)
                stack.callback(consumers.close)
                feed = consumers.feed(
                    part, frames=record is not None or fox is not None, rate_hz=max(
                        (publish_hz if sharing or fox else 0.0), (10.0 if view else 0.0),
                        1.0,
                        MCAP_EVENTS_HZ if record and record.lower().endswith(".mcap") else 0.0,
                        extra.rate_hz if extra is not None else 0.0))
                feed.attach_frames()  # from the check on, as a recording always did
                recorded = _frames_seen(part)
                ready = consumers.wait_ready(feed)  # exit 3 or 4 before the buses
                if extra is not None and extra.announce is not None and not as_json:
                    extra.announce(ready.get(extra.name))
                served = ready.get("foxglove")
                if served and not as_json:
                    stderr().print(f"[dim]foxglove: {escape(served['url'])}, values at "
                                   f"{publish_hz:g} Hz, writes "
                                   + ("allowed" if allow_writes else "refused") + "[/]",
                                   soft_wrap=True)
                net = ready.get("zenoh")
                if net and not as_json:
                    stderr().print(f"[dim]zenoh: robot {escape(net['robot'])} "
                                   + (f"joined through {escape(net['joined'])}"
                                      if net["joined"] else f"on {escape(net['where'])}")
                                   + f", values at {net['publish_hz']:g} Hz, writes "
                                   + ("allowed" if allow_writes else "refused") + "[/]",
                                   soft_wrap=True)
            part.claim(force=force)  # another host's exchange: exit 4, nothing sent
            report = part.check()
            if not report.ok:
                if as_json and not force:
                    emit_json({"connection": connection_json(spec), "started": False,
                               "boards": _check_json(report)})
                elif not as_json:
                    _print_check(report)
                if not force:
                    raise MappingError(report)
                stderr().print("[yellow]ucom: --force: starting only the boards that match "
                               "their trees[/]")
            refs = [(part.names.resolve(n, key="--set", kinds=(mca.Kind.CI, mca.Kind.PAR)),
                     v) for n, v in wanted]
            raws = [(ref, ref.raw(v, what="--set")) for ref, v in refs]
            part.on_values = summary  # on the loop's thread: a few dict look-ups a change
            if feed is not None:
                feed.attach()
            before: dict[str, tuple[float, int]] | None = None
            try:  # from the first board's start on: Ctrl-C stops the boards started
                with frozen_heap():
                    part.start(force=force)
                    if feed is not None:
                        feed.send_image()
                    for ref, raw in raws:
                        part.set(ref, ref.value(raw))
                    before = part.traffic()
                    if seconds is not None:
                        part.run(seconds)
                    elif view:
                        while True:  # until the view is quit, Ctrl-C, a stop
                            part.cycle()
                    else:
                        _run_plain(part)
            except KeyboardInterrupt as e:  # Ctrl-C, SIGTERM, SIGHUP: stop every board
                interrupted = interrupt_exit_code(e)
                how = f"terminated ({e.name})" if isinstance(e, Terminated) else "interrupted"
            except RemoteStop as e:  # from the network, with --allow-writes
                how = str(e)
            except BoardLost:  # --on-fault stop: every other board was stopped at once
                pass
            except Quit:  # the live view's q
                pass
            except ConsumersGone as e:  # the view, the recording or the share failed
                how = str(e)
                consumer_error = e
            finally:
                part.on_values = None
            loads = {} if before is None else part.load_between(before, part.traffic())
            problems = part.stop()
            network = None
            if feed is not None and consumers is not None:
                feed.end()
                recorded = {n: c - recorded.get(n, 0) for n, c in _frames_seen(part).items()}
                got = feed.wait_for("ended", END_S)  # the recording committed, the
                if got is not None:  # terminal given back
                    network = feed.stats.get("network")
                    if got[1] and consumer_error is None:
                        consumer_error = error_of(got[1], got[2], got[3])
                elif consumer_error is None:
                    consumer_error = UcomError(
                        "the consumers' process (live view, --record, --zenoh) "
                        + ("ended without saying how" if feed.gone
                           else f"did not end within {END_S:g} s"))
                if isinstance(consumer_error, ConsumersGone) and feed.ended is not None:
                    consumer_error = error_of(*feed.ended)
            if how:
                stderr().print(f"[yellow]{escape(how)}: "
                               + (f"{len(problems)} board(s) could not be stopped"
                                  if problems else "every board stopped") + "[/]")
            still_lost = sorted(part.lost.values(), key=lambda b: (b.bus, b.board))
            failed = part.failed_buses
            if part.scheduling is not None and part.scheduling.refused:
                stderr().print(f"[yellow]ucom: --realtime: {escape(part.scheduling.refused)}; "
                               "the loop ran at normal priority[/]", soft_wrap=True)
            stopped = _watchdog_stops(part.events, part.faults)
            if as_json:
                emit_json({"connection": connection_json(spec), "started": True,
                           "interrupted": bool(interrupted), "boards": _boards_json(part),
                           "run": _stats_json(part, loads), "not_stopped": problems,
                           "events": [_event_json(e) for e in part.events],
                           "faults": [_fault_json(f) for f in part.faults],
                           "lost": [{"bus": b.bus, "board": b.board, "where": b.where,
                                     "since": b.since, "seen": b.seen, "status": b.status}
                                    for b in still_lost],
                           "network": network,
                           **({"foxglove": feed.stats.get("foxglove") if feed else None}
                              if fox is not None else {}),
                           **({"record": {"file": record, "frames": recorded}}
                              if record is not None else {}),
                           **({extra.name: _extra_json(feed, extra.name)}
                              if extra is not None else {}),
                           "writes": [_write_json(w) for w in part.writes]})
            else:
                _print_summary(part, summary, loads)
                for p in problems:
                    stderr().print(f"[red]ucom: could not stop {escape(p)}: its watchdog "
                                   "stops it[/]", soft_wrap=True)
                _print_events(part.events)
                _print_faults(part, still_lost)
                if stopped:
                    _print_loop_away(part)
                _print_writes(part.writes)
    if consumer_error is not None:
        raise consumer_error
    if interrupted:
        ctx.exit(interrupted)
    if failed:
        ctx.exit(EXIT_BUS)
    if stopped or still_lost:
        ctx.exit(EXIT_FAILED)


MCAP_EVENTS_HZ = 10.0
"""Snapshots a second an MCAP --record asks for: its events and lost boards are placed
among the values this often (the values themselves come with every change)."""


def _frames_seen(part: RemotePart) -> dict[str, int]:
    """Frames each bus received and sent so far (what a --record holds of it)."""
    return {n: h.link.dispatcher.received + h.link.dispatcher.sent
            for n, h in part.robot.buses.items()}


def _check_record_rate(record: str | None, record_hz: float | None, rate: float) -> None:
    """InputError for a --record-rate that does not apply or does not fit."""
    if record_hz is None:
        return
    if record is None or not record.lower().endswith(".mcap"):
        raise InputError("records values at a rate in an MCAP recording only (--record "
                         "FILE.mcap); FILE.values.csv has every change", key="--record-rate")
    if not 0 < record_hz <= rate * 1.0001:
        raise InputError(f"must be more than 0 and at most the loop's rate ({rate:g} Hz), "
                         f"not {record_hz:g}", key="--record-rate")


def _extra_json(feed: LoopFeed | None, name: str) -> dict[str, Any] | None:
    """An extra consumer's figures, with the loop's count of its writes."""
    if feed is None:
        return None
    got = feed.stats.get(name)
    return {**(got or {}), "writes_applied": feed.drive.applied,
            "writes_refused": feed.drive.refused, "last_refused": feed.drive.reason or None}


def _consumers_config(part: RemotePart, record: str | None, view: bool,
                      endpoint: str | None, config_file: str | None, allow_writes: bool,
                      publish_hz: float, force: bool) -> dict[str, Any]:
    """What the consumers' process is to do (:mod:`ucom_tools.cli.consumers`)."""
    topology = part.robot.topology
    assert topology is not None
    sharing = endpoint is not None or config_file is not None
    return {"record": record, "view": view, "pid": os.getpid(),
            "robot": robot_id(topology.source, topology.name), "loop_hz": 1.0 / part.period_s,
            "zenoh": {"endpoint": endpoint, "config": config_file,
                      "allow_writes": allow_writes, "publish_hz": publish_hz,
                      "force": force} if sharing else None}


def _print_loop_away(part: RemotePart) -> None:
    """After watchdog stops: whether the PC's own loop was away that long (no MCA Alive
    sent), which points at this machine's load rather than the bus or the boards."""
    watchdog_ms = min((x.plan.alive_ms for x in part.exchanges.values()), default=0)
    gap_ms = part.stats.longest_gap_s * 1e3
    if part.virtual or not watchdog_ms or gap_ms < watchdog_ms:
        return
    hint = ("" if part.scheduling is not None and part.scheduling.used
            else "; --realtime runs it under SCHED_FIFO")
    stderr().print(f"[yellow]ucom: the PC's loop itself did not run for {gap_ms:.0f} ms at "
                   f"a time (the boards' watchdog: {watchdog_ms} ms): this machine kept it "
                   f"from its deadlines{hint}[/]", soft_wrap=True)


def _watchdog_stops(events: list[BoardEvent], faults: list[BoardFault],
                    ) -> list[tuple[str, int]]:
    """The boards whose watchdog stopped them and that did not rejoin after it."""
    out = set()
    for e in events:
        if e.stopped_motors and not any(
                f.event == "rejoined" and (f.bus, f.board) == (e.bus, e.board)
                and f.time >= e.time for f in faults):
            out.add((e.bus, e.board))
    return sorted(out)


def _fault_json(f: BoardFault) -> dict[str, Any]:
    return {"time": f.time, "bus": f.bus, "board": f.board, "where": f.where,
            "event": f.event, "seen": f.seen, "answered": f.answered}


def _print_faults(part: RemotePart, still_lost: list[Any]) -> None:
    """Every board lost and rejoined, in order; under --on-fault stop what was done;
    the boards still lost at the end; each bus that failed (exit 4), as a bus error is
    shown elsewhere."""
    for why in part.failed_buses.values():
        stderr().print(f"[bold red]ucom: bus error:[/] {escape(why)}", soft_wrap=True)
    for f in part.faults:
        if f.event == "lost":
            stderr().print(f"[red]ucom: {escape(f.where)} lost at {f.time:.3f} s: "
                           f"{escape(f.seen)}[/]", soft_wrap=True)
        else:
            after = "" if f.answered is None else \
                f", {f.time - f.answered:.3f} s after it answered"
            stderr().print(f"[green]ucom: {escape(f.where)} rejoined at {f.time:.3f} s"
                           f"{after}: {escape(f.seen)}[/]", soft_wrap=True)
    if part.on_fault == STOP and part.faults:
        stderr().print(f"[red]ucom: --on-fault stop: every other board was stopped at "
                       f"{part.faults[0].time:.3f} s (MCA Start STOP on every bus); the run "
                       "ended[/]", soft_wrap=True)
    elif still_lost:
        for b in still_lost:
            stderr().print(f"[red]ucom: {escape(b.where)} still lost at the end (since "
                           f"{b.since:.3f} s): {escape(b.status)}[/]", soft_wrap=True)


def _write_json(w: WriteEvent) -> dict[str, Any]:
    return {"time": w.time, "name": w.name or None, "value": w.value, "origin": w.origin,
            "result": w.result}


def _print_writes(writes: list[WriteEvent]) -> None:
    """What the network set (a line per refused write, a count of the rest)."""
    done = sum(w.done for w in writes)
    if done:
        stderr().print(f"[dim]{done} value(s) set or stops asked from the network[/]")
    for w in writes:
        if not w.done:
            stderr().print(f"[yellow]ucom: refused from the network ({escape(w.origin)}) at "
                           f"{w.time:.3f} s: {escape(w.name)}={escape(w.value)}: "
                           f"{escape(w.result)}[/]", soft_wrap=True)


def _event_json(e: BoardEvent) -> dict[str, Any]:
    return {"time": e.time, "bus": e.bus, "board": e.board, "where": e.where,
            "error": e.code.name, "text": e.text, "stopped_motors": e.stopped_motors}


def _print_events(events: list[BoardEvent]) -> None:
    """What the boards reported while running, a line per board and kind (with a
    count), the watchdogs that stopped motors in red."""
    seen: dict[tuple[str, int, ErrorCode], tuple[BoardEvent, int]] = {}
    for e in events:
        first, n = seen.get((e.bus, e.board, e.code), (e, 0))
        seen[(e.bus, e.board, e.code)] = (first, n + 1)
    for first, n in seen.values():
        style = "red" if first.stopped_motors else "yellow"
        times = f" ({n} times)" if n > 1 else ""
        stderr().print(f"[{style}]ucom: {escape(first.where)} at {first.time:.3f} s: "
                       f"{escape(first.text)}{times}[/]", soft_wrap=True)


def _run_plain(part: RemotePart) -> None:
    """Not a terminal, no --for: run until interrupted; a thread of its own prints a
    status line every second from what the loop hands over (the loop never waits for
    the output)."""
    bell = LoopHandover.of(part, 1.0).subscribe(1.0)
    ended = threading.Event()

    def status() -> None:
        last: LoopSnapshot | None = None
        while not ended.is_set():
            snap = bell.wait(0.2)
            if snap is None:
                continue
            if last is not None:
                f = snap.figures
                loads = snap.load_since(last)
                stderr().print(f"{f.cycles} cycles, {f.rate(snap.clock):.0f} Hz, {f.missed} "
                               f"missed, p99 {f.percentile(99) * 1e3:.3f} ms; "
                               + ", ".join(f"{n} {v:.1%}" for n, v in loads.items()))
            last = snap

    thread = threading.Thread(target=status, name="ucom-status", daemon=True)
    thread.start()
    try:
        while True:
            part.cycle()
    finally:
        ended.set()
        bell.close()
        thread.join(1.0)


try:
    from ucom_tools.cli.plot import plot as _plot
    remote.add_command(_plot)
except ImportError:  # pragma: no cover - while plot.py is written
    pass
