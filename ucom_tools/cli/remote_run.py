"""``ucom remote run``'s work (and ``gateway canopen``'s, which adds a consumer): the
robot opened, the consumers' process started (live view, ``--record``, ``--zenoh``,
``--foxglove``, the gateway), the boards checked against their trees and started, the
loop run until its end, every board stopped, and the end reported
(:mod:`ucom_tools.cli.run_summary`)."""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import click
from rich.markup import escape

from ucom_tools.cli import run_summary as say
from ucom_tools.cli.consumers import END_S, ConsumerProcess, ExtraConsumer, error_of
from ucom_tools.cli.exitcodes import EXIT_BUS, EXIT_FAILED
from ucom_tools.cli.options import connection_json, parse_sets
from ucom_tools.cli.output import emit_json, stderr
from ucom_tools.cli.tables import shown_path
from ucom_tools.config import topology as topo
from ucom_tools.errors import InputError, UcomError
from ucom_tools.net.keys import check_rate, robot_id
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.realtime import frozen_heap
from ucom_tools.ops.remote import RemotePart
from ucom_tools.ops.remote.faults import HOLD, STOP, BoardLost
from ucom_tools.ops.remote.feed import ConsumersGone, LoopFeed, Quit
from ucom_tools.ops.remote.part import robot_trees
from ucom_tools.ops.remote.publish import LoopHandover, LoopSnapshot
from ucom_tools.ops.remote.report import MappingError, RemoteStop, Summary
from ucom_tools.ops.robot import ConnectSpec, open_robot
from ucom_tools.signals import Terminated, interrupt_exit_code
from ucom_tools.trace.logs import check_buses, log_extension
from ucom_tools.viewers.foxglove_msgs import parse_address
from ucom_tools.wire import mca

MCAP_EVENTS_HZ = 10.0
"""Snapshots a second an MCAP --record asks for: its events and lost boards are placed
among the values this often (the values themselves come with every change)."""


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
def part_of(args: tuple[str, ...], spec: ConnectSpec, **kwargs: Any) -> Iterator[RemotePart]:
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


def one_bus(spec: ConnectSpec, bus_name: str | None) -> ConnectSpec:
    if bus_name is None:
        return spec
    if spec.virtual:
        raise InputError("--bus with --virtual: the run time takes the whole robot",
                         key="--bus")
    return replace(spec, only=bus_name)

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


# ---------------------------------------------------------------------- the run
@dataclass(frozen=True, kw_only=True)
class RunOptions:
    """What ``remote run``'s options ask for (``remote.run_options``)."""

    sets: tuple[str, ...] = ()
    seconds: float | None = None
    rate: float = 1000.0
    alive_ms: int = mca.ALIVE_DEFAULT_MS
    record: str | None = None
    record_hz: float | None = None
    periods: tuple[str, ...] = ()
    force: bool = False
    realtime: bool = False
    zenoh_endpoint: str | None = None
    zenoh_config: str | None = None
    allow_writes: bool = False
    publish_hz: float = 100.0
    on_fault: str = STOP
    rejoin: bool = False
    foxglove: str | None = None
    spec: ConnectSpec
    bus_name: str | None = None
    as_json: bool = False

    @property
    def sharing(self) -> bool:
        return self.zenoh_endpoint is not None or self.zenoh_config is not None


@dataclass
class _Ending:
    """How the run ended: an interrupt's exit code, why it stopped, the consumers'
    failure, what the stop could not stop."""

    interrupted: int = 0
    how: str = ""
    consumer_error: UcomError | None = None
    problems: list[str] = field(default_factory=list)
    loads: dict[str, float] = field(default_factory=dict)
    network: Any = None
    recorded: dict[str, int] = field(default_factory=dict)


def run_robot(ctx: click.Context, robot_or_trees: tuple[str, ...], *,
              extra: ExtraConsumer | None = None, **options: Any) -> None:
    """``remote run``'s work; ``extra`` adds a consumer to the consumers' process (the
    CANopen gateway of ``gateway canopen``)."""
    o = RunOptions(**options)
    if o.rejoin and o.on_fault != HOLD:
        raise click.UsageError("--rejoin needs --on-fault hold: under --on-fault stop a "
                               "lost board ends the run", ctx=ctx)
    wanted = parse_sets(o.sets)
    cycles = _parse_periods(o.periods)
    fox = parse_address(o.foxglove) if o.foxglove is not None else None  # exit 3 at once
    if o.allow_writes and not o.sharing and fox is None:
        raise InputError("writes from the network need the network: give --zenoh or "
                         "--foxglove", key="--allow-writes")
    if o.record is not None:  # checked up front; the file is written by the consumers
        log_extension(o.record, key="record")
    _check_record_rate(o.record, o.record_hz, o.rate)
    view = o.seconds is None and sys.stdout.isatty() and not o.as_json
    spec = one_bus(o.spec, o.bus_name)
    with ExitStack() as stack, part_of(  # the consumers' process closed after the part
            robot_or_trees, spec, rate_hz=o.rate, alive_ms=o.alive_ms,
            periods=cycles or None, realtime=o.realtime, on_fault=o.on_fault,
            rejoin=o.rejoin) as part:
        run = _Run(o, spec, part, view, extra, fox)
        run.prepare(stack)
        refs = [(part.names.resolve(n, key="--set", kinds=(mca.Kind.CI, mca.Kind.PAR)), v)
                for n, v in wanted]
        run.loop([(ref, ref.raw(v, key="--set")) for ref, v in refs])
        run.end()
        run.report()
    run.exit(ctx)


class _Run:
    """One run: the part, its consumers' process and feed, how it ended."""

    def __init__(self, o: RunOptions, spec: ConnectSpec, part: RemotePart, view: bool,
                 extra: ExtraConsumer | None, fox: tuple[str, int] | None) -> None:
        self.o, self.spec, self.part, self.view = o, spec, part, view
        self.extra, self.fox = extra, fox
        self.failed = False  # a board stopped by its watchdog, or still lost at the end
        self.bus_failed = False
        self.summary = Summary()
        self.ending = _Ending()
        self.consumers: ConsumerProcess | None = None
        self.feed: LoopFeed | None = None
        self.before: dict[str, tuple[float, int]] | None = None

    # ------------------------------------------------------------------ before the start
    def prepare(self, stack: ExitStack) -> None:
        """The run's checks that need the part, the consumers' process, the claim on the
        buses and the mapping check: each failure before any board is started."""
        o, part = self.o, self.part
        if o.sharing or self.fox is not None:
            check_rate(o.publish_hz, 1.0 / part.period_s)
        if o.record is not None:  # exit 3 before the exchange starts
            try:
                check_buses(log_extension(o.record, key="record"), part.robot.buses,
                            Path(o.record), "record")
            except InputError as err:
                raise InputError(f"{err.reason} (or --bus for one bus)",
                                 key="record") from None
        if not o.as_json:
            say.plan_notes(part)
        if o.record is not None or o.sharing or self.view or self.extra is not None \
                or self.fox:
            # the view, the recording, the share and the gateway in a process of their
            # own: none of them holds the lock this process's loop needs
            # (ops/remote/feed.py)
            self._start_consumers(stack)
        part.claim(force=o.force)  # another host's exchange: exit 4, nothing sent
        report = part.check()
        if not report.ok:
            if o.as_json and not o.force:
                emit_json({"connection": connection_json(self.spec), "started": False,
                           "boards": say.check_json(report)})
            elif not o.as_json:
                say.print_check(report)
            if not o.force:
                raise MappingError(report)
            stderr().print("[yellow]ucom: --force: starting only the boards that match "
                           "their trees[/]")

    def _start_consumers(self, stack: ExitStack) -> None:
        o, part, extra = self.o, self.part, self.extra
        config = _consumers_config(part, o.record, self.view, o.zenoh_endpoint,
                                   o.zenoh_config, o.allow_writes, o.publish_hz, o.force)
        config["record_hz"] = o.record_hz
        if extra is not None:
            config[extra.name] = extra.config
        if self.fox is not None:
            config["foxglove"] = {"host": self.fox[0], "port": self.fox[1],
                                  "allow_writes": o.allow_writes, "publish_hz": o.publish_hz}
        self.consumers = consumers = ConsumerProcess(config)
        stack.callback(consumers.close)
        record_mcap = o.record is not None and o.record.lower().endswith(".mcap")
        self.feed = feed = consumers.feed(
            part, frames=o.record is not None, rate_hz=max(
                (o.publish_hz if o.sharing or self.fox else 0.0),
                (10.0 if self.view else 0.0), 1.0, MCAP_EVENTS_HZ if record_mcap else 0.0,
                extra.rate_hz if extra is not None else 0.0))
        feed.attach_frames()  # from the check on, as a recording always did
        self.ending.recorded = _frames_seen(part)
        ready = consumers.wait_ready(feed)  # exit 3 or 4 before the buses
        if o.as_json:
            return
        if extra is not None and extra.announce is not None:
            extra.announce(ready.get(extra.name))
        writes = "allowed" if o.allow_writes else "refused"
        served = ready.get("foxglove")
        if served:
            stderr().print(f"[dim]foxglove: {escape(served['url'])}, values at "
                           f"{o.publish_hz:g} Hz, writes {writes}[/]", soft_wrap=True)
            if self.spec.virtual and not self.spec.pace:
                stderr().print("[yellow]foxglove: the virtual fleet runs on its own "
                               "clock, faster than the wall clock: a viewer sees the run "
                               "fast-forwarded; give --pace, or serve the fleet (ucom "
                               "fleet serve), to watch it as a robot runs[/]", soft_wrap=True)
        net = ready.get("zenoh")
        if net:
            stderr().print(f"[dim]zenoh: robot {escape(net['robot'])} "
                           + (f"joined through {escape(net['joined'])}" if net["joined"]
                              else f"on {escape(net['where'])}")
                           + f", values at {net['publish_hz']:g} Hz, writes {writes}[/]",
                           soft_wrap=True)

    # ------------------------------------------------------------------ the loop
    def loop(self, raws: list[tuple[EdgeRef, int]]) -> None:
        """Start the boards, set --set's values, run until the end; from the first
        board's start on, Ctrl-C stops the boards started."""
        o, part, feed, ending = self.o, self.part, self.feed, self.ending
        part.on_values = self.summary  # on the loop's thread: a few dict look-ups a change
        if feed is not None:
            feed.attach()
        try:
            with frozen_heap():
                part.start(force=o.force)
                if feed is not None:
                    feed.send_image()
                for ref, raw in raws:
                    part.set(ref, ref.value(raw))
                self.before = part.traffic()
                if o.seconds is not None:
                    part.run(o.seconds)
                elif self.view:
                    while True:  # until the view is quit, Ctrl-C, a stop
                        part.cycle()
                else:
                    _run_plain(part)
        except KeyboardInterrupt as e:  # Ctrl-C, SIGTERM, SIGHUP: stop every board
            ending.interrupted = interrupt_exit_code(e)
            ending.how = f"terminated ({e.name})" if isinstance(e, Terminated) \
                else "interrupted"
        except RemoteStop as e:  # from the network, with --allow-writes
            ending.how = str(e)
        except (BoardLost, Quit):  # --on-fault stop (every other board stopped); view's q
            pass
        except ConsumersGone as e:  # the view, the recording or the share failed
            ending.how = str(e)
            ending.consumer_error = e
        finally:
            part.on_values = None

    # ------------------------------------------------------------------ the end
    def end(self) -> None:
        """Every board stopped; the consumers told and waited for (the recording
        committed, the terminal given back)."""
        part, feed, ending = self.part, self.feed, self.ending
        if self.before is not None:
            ending.loads = part.load_between(self.before, part.traffic())
        ending.problems = part.stop()
        if feed is None or self.consumers is None:
            return
        feed.end()
        ending.recorded = {n: c - ending.recorded.get(n, 0)
                           for n, c in _frames_seen(part).items()}
        got = feed.wait_for("ended", END_S)
        if got is not None:
            ending.network = feed.stats.get("network")
            if got[1] and ending.consumer_error is None:
                ending.consumer_error = error_of(got[1], got[2], got[3])
        elif ending.consumer_error is None:
            ending.consumer_error = UcomError(
                "the consumers' process (live view, --record, --zenoh) "
                + ("ended without saying how" if feed.gone
                   else f"did not end within {END_S:g} s"))
        if isinstance(ending.consumer_error, ConsumersGone) and feed.ended is not None:
            ending.consumer_error = error_of(*feed.ended)

    def report(self) -> None:
        """What happened, as text or ``--json``."""
        o, part, ending, feed, extra = self.o, self.part, self.ending, self.feed, self.extra
        if ending.how:
            stderr().print(f"[yellow]{escape(ending.how)}: "
                           + (f"{len(ending.problems)} board(s) could not be stopped"
                              if ending.problems else "every board stopped") + "[/]")
        still_lost = sorted(part.lost.values(), key=lambda b: (b.bus, b.board))
        if part.scheduling is not None and part.scheduling.refused:
            stderr().print(f"[yellow]ucom: --realtime: {escape(part.scheduling.refused)}; "
                           "the loop ran at normal priority[/]", soft_wrap=True)
        stopped = say.watchdog_stops(part.events, part.faults)
        self.failed = bool(stopped or still_lost)
        self.bus_failed = bool(part.failed_buses)
        if not o.as_json:
            say.print_summary(part, self.summary, ending.loads)
            for p in ending.problems:
                stderr().print(f"[red]ucom: could not stop {escape(p)}: its watchdog "
                               "stops it[/]", soft_wrap=True)
            say.print_events(part.events)
            say.print_faults(part, still_lost)
            if stopped:
                say.print_loop_away(part)
            say.print_writes(part.writes)
            return
        emit_json({"connection": connection_json(self.spec), "started": True,
                   "interrupted": bool(ending.interrupted),
                   "boards": say.boards_json(part),
                   "run": say.stats_json(part, ending.loads), "not_stopped": ending.problems,
                   "events": [say.event_json(e) for e in part.events],
                   "faults": [say.fault_json(f) for f in part.faults],
                   "lost": [{"bus": b.bus, "board": b.board, "where": b.where,
                             "since": b.since, "seen": b.seen, "status": b.status}
                            for b in still_lost],
                   "network": ending.network,
                   **({"foxglove": feed.stats.get("foxglove") if feed else None}
                      if self.fox is not None else {}),
                   **({"record": {"file": o.record, "frames": ending.recorded}}
                      if o.record is not None else {}),
                   **({extra.name: say.extra_json(feed, extra.name)}
                      if extra is not None else {}),
                   "writes": [say.write_json(w) for w in part.writes]})

    def exit(self, ctx: click.Context) -> None:
        """The exit code: the consumers' failure, an interrupt's, a failed bus (4), a
        board stopped by its watchdog or still lost (1)."""
        if self.ending.consumer_error is not None:
            raise self.ending.consumer_error
        if self.ending.interrupted:
            ctx.exit(self.ending.interrupted)
        if self.bus_failed:
            ctx.exit(EXIT_BUS)
        if self.failed:
            ctx.exit(EXIT_FAILED)
