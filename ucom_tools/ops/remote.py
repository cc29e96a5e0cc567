"""The run-time part of the PC (``dsp_remote_part``, dissertation 5.2.2): a robot's boards
in the cyclic exchange, their edges under robot-wide names.

``RemotePart`` brings every board of the robot's trees up (``man/ucom-protocol.7``, RUN
TIME, Start sequence: program started if needed, descriptions checked against the
mapping tables, PAR and CI defaults, SO maps, MCA Start), then runs the PC's loop:
:meth:`RemotePart.cycle` waits for the next period, sends the CI maps due and MCA Alive on
every bus, and returns the latest SO values (latest-value semantics, as MCA2: nothing
queues).  ``part["Right Eye Target"] = 1000`` sets a value (a CI in a map goes out with
the next cycle, another CI or a PAR is written at once and acknowledged);
``part["Right Eye Joint Sensor"]`` reads one.  :meth:`RemotePart.stop` (and leaving the
``with`` block, whatever happened) stops every board: motors off.  A PC that stops
calling :meth:`cycle` stops sending MCA Alive, and the boards' watchdogs stop them.

Real buses: one thread does everything (no reader threads, so the GIL never keeps the
loop from its deadline).  Each cycle sleeps to its deadline on the wall clock (a short
spin for the last 0.1 ms), sends the frames due (one write per bus where the interface
can batch them: socketcand), then takes every frame the buses delivered meanwhile.
``realtime`` runs the loop's thread under SCHED_FIFO (:mod:`ucom_tools.ops.realtime`).
The in-process fleet in virtual time: the loop drives the fleet clock, nothing waits.

One exchange per bus: before anything is sent, :meth:`RemotePart.claim` listens on every
bus and refuses (BusError) where another host's exchange runs, unless forced.
"""

from __future__ import annotations

import difflib
import math
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path
from types import TracebackType
from typing import Any

import can

from ucom_tools.config import topology as topo_mod
from ucom_tools.config.attrtree.match import differences
from ucom_tools.config.attrtree.model import Board, Kind
from ucom_tools.config.attrtree.robot import RobotTrees, bind, with_files
from ucom_tools.errors import (
    BoardError,
    BusError,
    FrameError,
    InputError,
    UcomError,
    UcomTimeoutError,
)
from ucom_tools.ops.edges import EdgeRef, Names, spec_of
from ucom_tools.ops.exchange import BusExchange, ExchangeWatch, configure, edge_list
from ucom_tools.ops.realtime import RealtimeScheduling, precise_sleep
from ucom_tools.ops.remote_report import (
    BoardCheck,
    BoardEvent,
    CheckReport,
    LoopStats,
    MappingError,
    RawSnapshot,
    RemoteStop,
    Summary,
    Trace,
    Value,
    WriteEvent,
)
from ucom_tools.ops.robot import BusHandle, ConnectSpec, Robot, open_robot
from ucom_tools.protocol.bootloader import BootloaderClient
from ucom_tools.protocol.dispatch import share_clock
from ucom_tools.protocol.link import Link
from ucom_tools.protocol.mca import BoardEdges, values_of
from ucom_tools.wire import mca
from ucom_tools.wire import messages as wire_messages
from ucom_tools.wire.codes import ErrorCode
from ucom_tools.wire.ids import Function, seq

SPIN_S = 0.0001
"""The loop sleeps until this long before a deadline, then spins (a sleep wakes a little
late; the thread's timer slack is made small, see :func:`~ucom_tools.ops.realtime.
precise_sleep`)."""
DRAIN_EVERY_S = 0.001
"""At rates below 1 kHz the loop takes what the buses delivered at least this often while
it waits, so that no receive buffer fills."""
SWITCH_INTERVAL_S = 0.0001
"""While the loop runs, Python switches threads this often (default 5 ms: a second
thread, a live view say, could keep the loop from its deadline that long)."""
RECENT_SAMPLES = 2_000
"""The cycles a running view's lateness figures are taken over (the last 2 s at 1 kHz)."""
_KIND = {Kind.CI: mca.Kind.CI, Kind.SO: mca.Kind.SO, Kind.PAR: mca.Kind.PAR}



class RemotePart:
    """A robot's run time from the PC (see the module docstring)."""

    def __init__(self, robot: Robot, trees: RobotTrees, *, rate_hz: float = 1000.0,
                 alive_ms: int = mca.ALIVE_DEFAULT_MS,
                 periods: dict[str, int] | None = None, realtime: bool = False) -> None:
        if robot.topology is None:
            raise InputError("the run time needs the robot's topology (which board runs "
                             "which tree): give --topology FILE or a robot name",
                             key="--topology")
        if not 1 <= rate_hz <= 10_000:
            raise InputError(f"rate must be 1..10000 Hz, not {rate_hz:g}", key="--rate")
        period_ms = 1000.0 / rate_hz
        if period_ms > alive_ms / 2:  # MCA Alive goes out with the cycles, at most
            raise InputError(
                f"at {rate_hz:g} Hz the loop sends MCA Alive every {period_ms:g} ms, and the "
                f"boards' watchdog ({alive_ms} ms) wants it at least every {alive_ms / 2:g} "
                f"ms: the boards would stop their motors; raise the rate to "
                f"{2000.0 / alive_ms:g} Hz or more"
                + (f", or the watchdog to {math.ceil(2 * period_ms)} ms or more"
                   if 2 * period_ms <= mca.ALIVE_MAX_MS else ""), key="--rate")
        self.robot = robot
        self.trees = trees
        self.period_s = 1.0 / rate_hz
        self.virtual = robot.virtual_time
        if periods:
            _check_periods(periods, trees)
        self.exchanges: dict[str, BusExchange] = {}
        for name, h in robot.buses.items():
            spec = h.expected or robot.topology.bus(name)
            self.exchanges[name] = BusExchange(h.link, spec, trees, alive_ms=alive_ms,
                                               timeouts=robot.timeouts, periods=periods)
        self.names = Names(())
        self.stats = LoopStats(self.period_s)
        self.report: CheckReport | None = None
        self._described: dict[tuple[str, int], BoardEdges] = {}
        self._numbers: dict[str, list[int]] = {}
        self._running = False
        self._k = 0
        self._deadline = 0.0
        self._so_cache: dict[tuple[str, int], tuple[int, list[int]]] = {}
        self._par: dict[EdgeRef, int] = {}
        self._map_refs: dict[tuple[str, int], list[EdgeRef | None]] = {}
        self._seen: dict[tuple[str, int], int] = {}
        self._last_raw: dict[EdgeRef, int] = {}
        self._switch: float | None = None
        self._prepared = False
        self._claimed = False
        self.events: list[BoardEvent] = []
        """What the boards reported while the exchange ran (their Error messages)."""
        self._event_subs: list[tuple[Any, Any]] = []
        self._batching: list[tuple[str, Any]] = []
        """The buses whose frames of a cycle go out in one write (``hold``/``release``:
        :class:`~ucom_tools.transport.socketcand.SocketcandBus`)."""
        self.scheduling: RealtimeScheduling | None = (
            RealtimeScheduling() if realtime and not robot.virtual_time else None)
        """``realtime``: the loop's thread under SCHED_FIFO from its first cycle to the stop
        (``scheduling.active``; ``scheduling.refused`` says why not).  Not in virtual time,
        where the loop drives the clock and nothing waits for the wall."""
        """The buses' sockets when every bus has one (select() waits on them), else []."""
        self._owns_robot = False
        self.each_cycle: list[Callable[[], None]] = []
        """Called on the loop's thread at the end of every cycle, after the sends (the
        network share, :mod:`ucom_tools.net.share`: writes from the network are applied
        here, and a snapshot handed to its publishing thread every few cycles).  What is
        called here must not wait for anything."""
        self.writes: list[WriteEvent] = []
        """Values set from elsewhere than this process (the network), with their origin and
        what came of them: kept as the run's events."""
        self.share: Any = None
        """The network share (:class:`ucom_tools.net.share.RobotShare`) when the part is
        shared (:meth:`open` with ``zenoh``); closed with the part."""
        self.on_values: Callable[[float, EdgeRef, Value], None] | None = None
        """Called with (time, edge, value) for every SO value a cycle saw change (and its
        first), and for every CI or PAR value set (recorders); the time on the base of the
        bus's frame timestamps, as --record logs the frames."""

    @classmethod
    def open(cls, robot: str, *, virtual: bool = False, state_dir: str | Path | None = None,
             interface: str | None = None, channels: Sequence[str] = (),
             host: str | None = None, port: int | None = None, bitrate: int | None = None,
             trees: Sequence[str | Path] = (), start: bool = True, force: bool = False,
             zenoh: str | None = None, zenoh_config: str | Path | None = None,
             allow_writes: bool = False, publish_hz: float = 100.0,
             **kwargs: Any) -> RemotePart:
        """The run-time part of ``robot`` (a bundled topology or a topology file) on its
        buses: the in-process virtual fleet (``virtual``, flash kept in ``state_dir``),
        or a python-can ``interface`` with ``channels`` (or a socketcand ``host`` and
        ``port``).  ``trees`` replace the robot's trees of the same Prefix.  Started
        (:meth:`start`, with ``force``) unless ``start`` is false; as a context manager
        it always stops the boards and closes the buses at the end.

        ``zenoh`` (an endpoint, ``"tcp/127.0.0.1:7447"``) and/or ``zenoh_config`` (a Zenoh
        JSON5 file) share the running part on the network (:func:`ucom_tools.net.share.
        share`: structure, values at ``publish_hz``, writes only with ``allow_writes``);
        refused (BusError) where the robot already runs on that network, unless
        ``force``."""
        if virtual:
            spec = ConnectSpec(virtual=robot,
                               state_dir=Path(state_dir) if state_dir is not None else None)
        else:
            spec = ConnectSpec(interface, tuple(channels), bitrate, host, port,
                               topology=robot)
        r = open_robot(spec)
        try:
            part = cls(r, robot_trees(r, trees), **kwargs)
        except BaseException:
            r.close()
            raise
        part._owns_robot = True
        if zenoh is not None or zenoh_config is not None:
            from ucom_tools.net.share import share  # the engine only where it is asked for

            try:
                s = share(part, endpoint=zenoh, config_file=zenoh_config,
                          allow_writes=allow_writes, publish_hz=publish_hz, force=force)
                if start:  # the names known before the start: declared while nothing runs
                    part.claim(force=force)
                    part.check()
                    s.declare()
            except BaseException:
                part.close()
                raise
        if start:
            try:
                part.start(force=force)
            except BaseException:
                part.close()
                raise
        return part

    @classmethod
    def on_buses(cls, robot: str, buses: Mapping[str, can.BusABC], **kwargs: Any,
                 ) -> RemotePart:
        """The run-time part of ``robot`` on python-can buses you opened yourself, by
        the topology's bus names (``{"CAN0": can.Bus(...)}``); you shut them down."""
        topology = topo_mod.load(robot)
        handles = {}
        for name, bus in buses.items():
            try:
                spec = topology.bus(name)
            except KeyError:
                raise InputError(f"robot {topology.name!r} has no bus {name!r}; its buses: "
                                 + ", ".join(b.name for b in topology.buses)) from None
            link = Link(bus, name, bitrate=spec.bitrate)
            handles[name] = BusHandle(name, bus, link, BootloaderClient(link), spec,
                                      virtual=False)
        r = Robot(ConnectSpec(topology=robot), handles, topology)
        return cls(r, robot_trees(r), **kwargs)

    # ------------------------------------------------------------------ buses
    def _handles(self) -> list[tuple[BusHandle, BusExchange]]:
        return [(self.robot.buses[n], x) for n, x in self.exchanges.items()]

    def _each_bus(self, work: Callable[[BusHandle, BusExchange], object]) -> list[object]:
        """``work`` on every bus: in parallel on real buses, one after the other in
        virtual time (one clock)."""
        pairs = self._handles()
        if self.virtual or len(pairs) == 1:
            return [work(h, x) for h, x in pairs]
        with ThreadPoolExecutor(max_workers=len(pairs), thread_name_prefix="ucom-bus") as pool:
            return list(pool.map(lambda p: work(*p), pairs))

    # ------------------------------------------------------------------ other hosts
    def claim(self, *, force: bool = False) -> None:
        """Listen on every bus before anything is sent to it, for the boards' watchdog time
        and the transport's margin: :class:`~ucom_tools.errors.BusError` when another host
        runs the cyclic exchange on one of them (MCA Alive or CI maps this host did not
        send), unless ``force``.  :meth:`start` claims first unless it was done."""
        self._claimed = True
        if force:
            return

        def listen(h: BusHandle, x: BusExchange) -> None:
            with ExchangeWatch(h.link) as watch:
                watch.listen(ExchangeWatch.listen_time(h.link, x.plan.alive_ms))
                watch.check(h.name)

        self._each_bus(listen)

    # ------------------------------------------------------------------ check
    def check(self) -> CheckReport:
        """Init every bus, start each board's program if needed, fetch its descriptions
        and compare them with its tree block: every difference, nothing written."""
        refs: list[EdgeRef] = []

        def one_bus(h: BusHandle, x: BusExchange) -> list[BoardCheck]:
            out = []
            init = h.client.init_chain()
            self._numbers[h.name] = init.numbers
            for spec in x.bus.boards:
                n = spec.position + 1
                where = x.where(n)
                try:
                    block = self.trees.board(h.name, spec.position)
                except KeyError:
                    continue  # no tree: not part of the run time
                base = BoardCheck(h.name, n, where, block.prefix,
                                  str(self._tree_file(h.name, spec.position)))
                if n not in init.numbers:
                    out.append(_with(base, error="did not answer the init chain"))
                    continue
                try:
                    ready = x.start_programs([n])[n]
                    edges = x.mca.describe(seq(n), (ready.ci, ready.so, ready.par))
                except (BoardError, UcomTimeoutError) as err:
                    out.append(_with(base, error=str(err)))
                    continue
                self._described[(h.name, n)] = edges
                found = tuple(differences(block, edge_list(edges)))
                if not found:
                    refs.extend(_refs_of(h.name, n, x.where(n), block, edges))
                out.append(_with(base, program=f"{ready.ci}/{ready.so}/{ready.par}",
                                 differences=found))
            return out

        boards: list[BoardCheck] = []
        for part in self._each_bus(one_bus):
            assert isinstance(part, list)
            boards += part
        self.report = CheckReport(tuple(boards))
        order = {(b.bus, b.board): i for i, b in enumerate(boards)}
        self.names = Names(sorted(refs, key=lambda r: order[(r.bus, r.board)]))
        return self.report

    def _tree_file(self, bus: str, position: int) -> Path | str:
        """The file the tree block of a board comes from (a replacing file, or the
        topology's)."""
        for b in self.trees.boards:
            if b.bus == bus and b.spec.position == position:
                return b.file
        return ""

    def described(self, bus: str, board: int) -> BoardEdges | None:
        """The edges board ``board`` of ``bus`` described in :meth:`check`."""
        return self._described.get((bus, board))

    # ------------------------------------------------------------------ start
    def start(self, *, force: bool = False) -> CheckReport:
        """Check, then configure every matching board (tree defaults, maps) and start the
        exchange on every bus.  A mismatch raises :class:`MappingError` and starts
        nothing, unless ``force``: then only the matching boards run.  Another host's
        exchange on a bus (:meth:`claim`) raises BusError, unless ``force``."""
        if not self._claimed:
            self.claim(force=force)
        report = self.report or self.check()
        if not report.ok and not force:
            raise MappingError(report)
        good = {(b.bus, b.board) for b in report.boards if b.ok}
        if not good:
            raise MappingError(report)

        def configure_bus(h: BusHandle, x: BusExchange) -> None:
            for spec in x.bus.boards:
                n = spec.position + 1
                if (h.name, n) not in good:
                    continue
                block = self.trees.board(h.name, spec.position)
                c = configure(x.mca, seq(n), x.where(n), block, x.plan,
                              tree_file=str(self._tree_file(h.name, spec.position)),
                              edges=self._described[(h.name, n)])
                x.configured[n] = c
                for index in range(len(c.edges.ci)):
                    x.ci.setdefault((n, index), 0)
                for unique, raw in c.written.items():
                    e = block.edge(unique)
                    if e.kind is Kind.CI:
                        x.ci[(n, e.index)] = raw

        self._each_bus(configure_bus)
        self.names = Names(r for r in self.names if (r.bus, r.board) in good)
        self._par = {}
        self._map_refs = {}
        by_slot = {(r.bus, r.board, r.index): r for r in self.names if r.kind is mca.Kind.SO}
        for bus, x in self.exchanges.items():
            for m in x.plan.so_maps:
                if m.board in x.configured:
                    self._map_refs[(bus, m.number)] = [by_slot.get((bus, m.board, i))
                                                       for i in m.edges]
        for ref in self.names:
            if ref.kind is mca.Kind.PAR:
                written = self.exchanges[ref.bus].configured[ref.board].written
                if ref.unique in written:
                    self._par[ref] = written[ref.unique]
        # MCA Alive as periodic frames while the boards are started one by one (an answer
        # that has to be asked for again must not let the first ones' watchdogs fire);
        # from the first cycle on, the loop sends it
        if self.virtual:
            share_clock([h.link.dispatcher for h, _ in self._handles()])
        else:
            for h, _ in self._handles():  # until the loop polls them itself
                h.link.dispatcher.start()
        for _, x in self._handles():
            x.start_alive()
        for _, x in self._handles():
            x.start_exchange(periodic=False)
        self._running = True
        clock = self._clock()
        self._listen_for_events(clock)
        self.stats = LoopStats(self.period_s, started_wall=time.perf_counter(),
                               started_clock=clock)
        self._deadline = clock
        self._k = 0
        if not self.virtual:
            for h, _ in self._handles():
                h.link.dispatcher.stop()
            self._switch = sys.getswitchinterval()
            sys.setswitchinterval(SWITCH_INTERVAL_S)
        self.cycle()
        for _, x in self._handles():
            x.stop_tasks()
        return report

    # ------------------------------------------------------------------ the loop
    def _clock(self) -> float:
        first = next(iter(self.robot.buses.values()))
        return first.link.clock()

    def cycle(self) -> Mapping[str, Value | None]:
        """Wait for the next period, send the CI maps due and MCA Alive on every bus, and
        return the latest SO values by name."""
        if not self._running:
            raise UcomError("the exchange is not running (start() it first)")
        if not self._prepared:
            self._prepare()  # once, in the loop's own thread
        self._wait(self._deadline)
        now = self._clock()
        late = now - self._deadline
        if late >= self.period_s:  # the loop came a whole period late or more
            skipped = int(late // self.period_s)
            self.stats.missed += skipped
            self._deadline += skipped * self.period_s
            self._k += skipped
            late -= skipped * self.period_s
        self.stats.late.append(late)
        batching = self._batching
        for _, bus in batching:
            bus.hold()
        try:
            for x in self.exchanges.values():
                x.send_cycle(self._deadline)
        except BaseException:
            for _, bus in batching:
                bus.release(write=False)
            raise
        for name, bus in batching:
            try:
                bus.release()
            except can.CanError as err:
                raise BusError(f"{name}: cannot send: {err}") from err
        if not self.virtual:
            self._drain()  # after the sends: what came during the period, as fresh as can be
        self.stats.cycles += 1
        self._k += 1
        self._deadline += self.period_s
        if self.on_values is not None:
            self._report_so()
        for hook in self.each_cycle:
            hook()
        return self.so

    def _listen_for_events(self, started: float) -> None:
        """From now on every Error a board sends is kept in :attr:`events` (a watchdog
        that stopped a board's motors above all: the loop goes on, the board does not)."""
        for d, sub in self._event_subs:
            d.unsubscribe(sub)
        self._event_subs = []
        for h, x in self._handles():
            def on_error(msg: can.Message, h: BusHandle = h, x: BusExchange = x) -> None:
                try:
                    address, err = wire_messages.decode(msg.arbitration_id,
                                                        bytes(msg.data))
                except FrameError:
                    return
                assert isinstance(err, wire_messages.Error)
                n = address.number
                self.events.append(BoardEvent(
                    round(h.link.clock() - started, 4), h.name, n, x.where(n), err.code,
                    f"its watchdog stopped every motor: no MCA Alive for {err.detail} ms "
                    "(stopped until MCA Start)" if err.code is ErrorCode.WATCHDOG
                    else err.describe()))
            d = h.link.dispatcher
            self._event_subs.append((d, d.subscribe(
                lambda msg: msg.arbitration_id >> 6 == Function.ERROR,
                f"{h.name} board errors", on_frame=on_error)))

    def _prepare(self) -> None:
        """The loop's thread: SCHED_FIFO (``realtime``), precise sleeps; and the buses
        whose frames of a cycle can go out in one write."""
        self._prepared = True
        rt = self.scheduling
        if rt is not None:
            rt.enter()
        if not self.virtual:
            precise_sleep()
        self._batching = [(h.name, h.link.dispatcher.bus) for h, _ in self._handles()
                          if not self.virtual and callable(
                              getattr(h.link.dispatcher.bus, "hold", None))]

    def _drain(self) -> int:
        """Take and dispatch every frame the buses have delivered (without waiting)."""
        return sum(h.link.dispatcher.drain() for h, _ in self._handles())

    def _wait(self, deadline: float) -> None:
        """Until ``deadline``: in virtual time by driving the fleet clock; on real buses by
        sleeping (one thread does everything, no reader threads, so the GIL never keeps
        the loop from its deadline), spinning the last :data:`SPIN_S`; the frames that
        come meanwhile are taken after the cycle's sends (:meth:`cycle`), or every
        :data:`DRAIN_EVERY_S` while a long period passes."""
        if self.virtual:
            for h, _ in self._handles():
                h.link.dispatcher.pump(deadline)
            return
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return
            if remaining > SPIN_S:
                time.sleep(min(DRAIN_EVERY_S, remaining - SPIN_S))
                if deadline - time.monotonic() > DRAIN_EVERY_S:
                    self._drain()

    def run(self, seconds: float, each: Callable[[RemotePart], None] | None = None) -> None:
        """Cycle for ``seconds`` (of the bus clock), calling ``each(self)`` every cycle."""
        end = self._clock() + seconds
        while self._clock() < end:
            self.cycle()
            if each is not None:
                each(self)

    # ------------------------------------------------------------------ values
    def _map_values(self, bus: str, number: int) -> list[int] | None:
        """The decoded values of SO map ``number`` of ``bus`` (decoded once per frame)."""
        x = self.exchanges[bus]
        frame = x.mca.image.frames.get(number)
        if frame is None:
            return None
        count = x.mca.image.counts[number]
        cached = self._so_cache.get((bus, number))
        if cached is None or cached[0] != count:
            m = next(m for m in x.plan.so_maps if m.number == number)
            records = x.configured[m.board].edges.so
            cached = (count, values_of(frame, [records[i] for i in m.edges]))
            self._so_cache[(bus, number)] = cached
        return cached[1]

    def _so(self, ref: EdgeRef) -> int | None:
        for m in self.exchanges[ref.bus].plan.maps_of(ref.board):
            if ref.index in m.edges:
                values = self._map_values(ref.bus, m.number)
                return None if values is None else values[m.edges.index(ref.index)]
        return None

    def _report_so(self) -> None:
        """Hand every SO value of the maps that came since the last cycle to on_values."""
        assert self.on_values is not None
        for (bus, number), refs in self._map_refs.items():
            image = self.exchanges[bus].mca.image
            count = image.counts.get(number, 0)
            if count == self._seen.get((bus, number), 0):
                continue
            self._seen[(bus, number)] = count
            values = self._map_values(bus, number)
            if values is None:
                continue
            stamp = image.stamps[number]
            last = self._last_raw
            for ref, raw in zip(refs, values, strict=True):
                if ref is not None and last.get(ref) != raw:
                    last[ref] = raw
                    self.on_values(stamp, ref, ref.value(raw))

    def snapshot(self) -> RawSnapshot:
        """Every value's raw state as it is now, for another thread to decode
        (:meth:`decode`): references to the maps' latest frames (bytes, never changed in
        place) and copies of the CI and PAR values, a few dict copies per bus.  The loop's
        thread takes it (:attr:`each_cycle`); nothing is decoded here."""
        frames, stamps, ci = {}, {}, {}
        for bus, x in self.exchanges.items():
            image = x.mca.image
            frames[bus] = dict(image.frames)
            stamps[bus] = dict(image.stamps)
            ci[bus] = dict(x.ci)
        return RawSnapshot(self._clock(), frames, stamps, ci, dict(self._par))

    def decode(self, snap: RawSnapshot) -> dict[EdgeRef, tuple[float, Value]]:
        """(time stamp, value) of every edge a :meth:`snapshot` holds a value of: an SO's
        stamped with its map's frame, a CI's and a PAR's with the snapshot's time (both
        on the base of the bus's frame time stamps).  Reads only what :meth:`start` set
        up, so any thread may call it while the loop runs."""
        out: dict[EdgeRef, tuple[float, Value]] = {}
        for (bus, number), refs in self._map_refs.items():
            frame = snap.frames[bus].get(number)
            if frame is None:
                continue
            x = self.exchanges[bus]
            m = next(m for m in x.plan.so_maps if m.number == number)
            records = x.configured[m.board].edges.so
            raws = values_of(frame, [records[i] for i in m.edges])
            stamp = snap.stamps[bus].get(number, snap.clock)
            for ref, raw in zip(refs, raws, strict=True):
                if ref is not None:
                    out[ref] = (stamp, ref.value(raw))
        for ref in self.names:
            if ref.kind is mca.Kind.CI:
                sent = snap.ci[ref.bus].get((ref.board, ref.index))
                if sent is not None:
                    out[ref] = (snap.clock, ref.value(sent))
            elif ref.kind is mca.Kind.PAR and ref in snap.par:
                out[ref] = (snap.clock, ref.value(snap.par[ref]))
        return out

    @property
    def running(self) -> bool:
        """Between :meth:`start` and :meth:`stop`."""
        return self._running

    def raw(self, name: str | EdgeRef) -> int | None:
        """The raw value of an edge: SO the latest from its map (None before the first,
        or when it is not cyclic), CI what the PC sends, PAR what the PC wrote."""
        ref = name if isinstance(name, EdgeRef) else self.names.resolve(name)
        if ref.kind is mca.Kind.SO:
            return self._so(ref)
        if ref.kind is mca.Kind.CI:
            return self.exchanges[ref.bus].ci.get((ref.board, ref.index))
        return self._par.get(ref)

    def cyclic(self, name: str | EdgeRef) -> bool:
        """Does the edge travel in a process-data map (a CI the loop sends every period,
        an SO the board sends)?  Others are written, or read, on request."""
        ref = name if isinstance(name, EdgeRef) else self.names.resolve(name)
        plan = self.exchanges[ref.bus].plan
        if ref.kind is mca.Kind.CI:
            return any((ref.board, ref.index) in c.slots for c in plan.ci_maps)
        if ref.kind is mca.Kind.SO:
            return any(ref.index in m.edges for m in plan.maps_of(ref.board))
        return False

    def __getitem__(self, name: str) -> Value | None:
        ref = self.names.resolve(name)
        raw = self.raw(ref)
        return None if raw is None else ref.value(raw)

    def __setitem__(self, name: str, value: object) -> None:
        self.set(name, value)

    def set(self, name: str | EdgeRef, value: object, *, key: str | None = None) -> EdgeRef:
        """Set a CI or PAR by name, in the edge's unit; range-checked before anything is
        sent (InputError)."""
        ref = name if isinstance(name, EdgeRef) else self.names.resolve(
            name, key=key, kinds=(mca.Kind.CI, mca.Kind.PAR))
        if ref.kind is mca.Kind.SO:
            raise InputError(f"{ref.qualified} is a sensor output; only CI and PAR edges "
                             "can be set", key=key)
        raw = ref.raw(value, what=key)
        x = self.exchanges[ref.bus]
        if ref.kind is mca.Kind.CI:
            x.set_ci(ref.board, ref.generic, raw)
        else:
            x.mca.write(seq(ref.board), mca.Kind.PAR, ref.index, [raw],
                        x.configured[ref.board].edges.par)
            self._par[ref] = raw
        if self.on_values is not None:  # stamped as the frames are (SO values, --record)
            self.on_values(x.link.dispatcher.stamp(), ref, ref.value(raw))
        return ref

    @property
    def so(self) -> Mapping[str, Value | None]:
        """The latest SO values by name, looked up when read (nothing is copied)."""
        return _SoView(self)

    def values(self, kinds: tuple[mca.Kind, ...] = tuple(mca.Kind)) -> dict[str, Value]:
        """Every known value of the given kinds by name (SO: the latest that arrived)."""
        out: dict[str, Value] = {}
        for ref in self.names:
            if ref.kind in kinds:
                raw = self.raw(ref)
                if raw is not None:
                    out[self.names.name_of(ref)] = ref.value(raw)
        return out

    # ------------------------------------------------------------------ figures
    def traffic(self) -> dict[str, tuple[float, int]]:
        """(bus clock, bits seen so far) per bus: two of them give the load between."""
        return {n: (h.link.clock(), h.link.dispatcher.bits)
                for n, h in self.robot.buses.items()}

    def load_between(self, a: dict[str, tuple[float, int]], b: dict[str, tuple[float, int]],
                     ) -> dict[str, float]:
        """The measured load of each bus between two :meth:`traffic` snapshots."""
        out = {}
        for n, h in self.robot.buses.items():
            t0, bits0 = a[n]
            t1, bits1 = b[n]
            out[n] = (bits1 - bits0) / ((t1 - t0) * h.link.bitrate) if t1 > t0 else 0.0
        return out

    # ------------------------------------------------------------------ the end
    def stop(self) -> list[str]:
        """Stop every board's exchange (MCA Start STOP: motors off) and the readers;
        returns what could not be stopped (those boards stop by their watchdog)."""
        if not self._running:
            return []
        self._running = False
        problems: list[str] = []

        def stop_bus(h: BusHandle, x: BusExchange) -> list[str]:
            out = []
            for n in list(x.configured):
                try:
                    x.mca.start(seq(n), mca.StartOp.STOP)
                except UcomError as err:
                    out.append(f"{x.where(n)}: {err}")
            return out

        try:
            for part in self._each_bus(stop_bus):
                assert isinstance(part, list)
                problems += part
        finally:
            for _, x in self._handles():
                x.stop_tasks()
            if self.scheduling is not None:
                self.scheduling.leave()
            self._prepared = False
            if self._switch is not None:
                sys.setswitchinterval(self._switch)
                self._switch = None
        return problems

    def close(self) -> None:
        """Stop the boards (see :meth:`stop`) and let go of the buses (closing them if
        :meth:`open` opened them) and of the network share."""
        try:
            self.stop()
        finally:
            if self.share is not None:
                share, self.share = self.share, None
                share.close()
            for x in self.exchanges.values():
                x.close()
            if self._owns_robot:
                self._owns_robot = False
                self.robot.close()

    def __enter__(self) -> RemotePart:
        """The ``with`` block's end always stops the boards and lets go of the buses."""
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def _with(base: BoardCheck, **changes: object) -> BoardCheck:
    return replace(base, **changes)  # type: ignore[arg-type]


def _refs_of(bus: str, n: int, where: str, block: Board, edges: BoardEdges,
             ) -> Iterator[EdgeRef]:
    """The edges of one board whose tree block matches its description."""
    first = {k: sum(len(edges.of(j)) for j in mca.Kind if j < k) for k in mca.Kind}
    for e in block.edges:
        kind = _KIND[e.kind]
        index = e.index - first[kind]
        yield EdgeRef(bus, n, where, block.prefix, e.unique, e.generic, kind, index,
                      spec_of(kind, edges.of(kind)[index]))


def _check_periods(periods: dict[str, int], trees: RobotTrees) -> None:
    """Every name of ``periods`` must be an edge of a program the robot's trees map."""
    from ucom_tools.config.attrtree.match import program_of

    names: set[str] = set()
    for b in trees.boards:
        program = program_of(b.board)
        if program is not None:
            names |= {e.name for e in program.edges}
    for name in periods:
        if name not in names:
            close = difflib.get_close_matches(name, sorted(names), n=3)
            hint = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
            raise InputError(f"no program edge called {name!r} (periods name the programs' "
                             f"generic edges, as in the trees' mapping tables){hint}",
                             key="--period")


class _SoView(Mapping[str, "Value | None"]):
    """:attr:`RemotePart.so`: a read-only view of the latest SO values by name."""

    def __init__(self, part: RemotePart) -> None:
        self._part = part

    def __getitem__(self, name: str) -> Value | None:
        ref = self._part.names.resolve(name)
        if ref.kind is not mca.Kind.SO:
            raise KeyError(name)
        raw = self._part.raw(ref)
        return None if raw is None else ref.value(raw)

    def __iter__(self) -> Iterator[str]:
        names = self._part.names
        return (names.name_of(r) for r in names if r.kind is mca.Kind.SO)

    def __len__(self) -> int:
        return sum(1 for r in self._part.names if r.kind is mca.Kind.SO)


def robot_trees(robot: Robot, files: Sequence[str | Path] = ()) -> RobotTrees:
    """The robot's trees (its topology names them), with the blocks of ``files`` in place
    of the robot's blocks of the same Prefix."""
    if robot.topology is None:
        raise InputError("the run time needs the robot's topology (which board runs which "
                         "tree)", key="--topology")
    return with_files(bind(robot.topology), files)


__all__ = ["RECENT_SAMPLES", "BoardCheck", "BoardEvent", "CheckReport", "LoopStats",
           "MappingError", "RawSnapshot", "RemotePart", "RemoteStop", "Summary", "Trace",
           "Value", "WriteEvent", "robot_trees"]
