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

One exchange per bus: before anything is sent, :meth:`RemotePart.claim` listens on every
bus and refuses (BusError) where another host's exchange runs, unless forced.

A board that goes silent, or whose bus fails, is *lost* (``man/ucom-protocol.7``, RUN
TIME, Faults): ``on_fault="stop"`` (the default) stops every other board at once and
:meth:`cycle` raises :class:`~ucom_tools.ops.remote.faults.BoardLost`; ``"hold"`` runs
the others on, and with ``rejoin=True`` brings the board back when it returns
(:mod:`~ucom_tools.ops.remote.rejoin`), its joints held where they stand.  :attr:`lost`,
:attr:`faults`, :attr:`fault_hooks`, :meth:`valid` and :meth:`age` say what is current.

This module opens, checks, starts and stops; the jobs between live beside it: the
start-up check (:mod:`~ucom_tools.ops.remote.check`), the values by name
(:mod:`~ucom_tools.ops.remote.values`), the loop (:mod:`~ucom_tools.ops.remote.loop`),
what is reported (:mod:`~ucom_tools.ops.remote.report`, faults:
:mod:`~ucom_tools.ops.remote.faults`), in the modules of this package.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

import can

from ucom_tools.config import topology as topo_mod
from ucom_tools.config.attrtree.robot import RobotTrees, bind, with_files
from ucom_tools.errors import InputError, MissingInput, UcomError
from ucom_tools.ops.edges import EdgeRef, Names
from ucom_tools.ops.exchange import LISTEN_MIN_S, BusExchange, ExchangeWatch
from ucom_tools.ops.remote.check import BusCheck, check_bus, check_periods, tree_file
from ucom_tools.ops.remote.faults import STOP
from ucom_tools.ops.remote.loop import RemoteLoop
from ucom_tools.ops.remote.report import BoardCheck, CheckReport, MappingError, WriteEvent
from ucom_tools.ops.robot import BusHandle, ConnectSpec, Robot, open_robot
from ucom_tools.protocol.bootloader import BootloaderClient
from ucom_tools.protocol.link import Link
from ucom_tools.protocol.mca import BoardEdges
from ucom_tools.wire import mca
from ucom_tools.wire.ids import seq

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey


class RemotePart(RemoteLoop):
    """A robot's run time from the PC (see the module docstring)."""

    def __init__(self, robot: Robot, trees: RobotTrees, *, rate_hz: float = 1000.0,
                 alive_ms: int = mca.ALIVE_DEFAULT_MS,
                 periods: dict[str, int] | None = None, realtime: bool = False,
                 on_fault: str = STOP, rejoin: bool = False) -> None:
        if robot.topology is None:
            raise MissingInput("the run time needs the robot's topology (which board runs "
                               "which tree)", key="topology")
        if not 1 <= rate_hz <= 10_000:
            raise InputError(f"rate must be 1..10000 Hz, not {rate_hz:g}", key="rate_hz")
        period_ms = 1000.0 / rate_hz
        if period_ms > alive_ms / 2:  # MCA Alive goes out with the cycles, at most
            raise InputError(
                f"at {rate_hz:g} Hz the loop sends MCA Alive every {period_ms:g} ms, and the "
                f"boards' watchdog ({alive_ms} ms) wants it at least every {alive_ms / 2:g} "
                f"ms: the boards would stop their motors; raise the rate to "
                f"{2000.0 / alive_ms:g} Hz or more"
                + (f", or the watchdog to {math.ceil(2 * period_ms)} ms or more"
                   if 2 * period_ms <= mca.ALIVE_MAX_MS else ""), key="rate_hz")
        if periods:
            check_periods(periods, trees)
        exchanges: dict[str, BusExchange] = {}
        for name, h in robot.buses.items():
            spec = h.expected or robot.topology.bus(name)
            exchanges[name] = BusExchange(h.link, spec, trees, alive_ms=alive_ms,
                                          timeouts=robot.timeouts, periods=periods)
        super().__init__(robot, exchanges, 1.0 / rate_hz, realtime=realtime,
                         on_fault=on_fault, rejoin=rejoin)
        self.trees = trees
        self.report: CheckReport | None = None
        self._described: dict[BoardKey, BoardEdges] = {}
        self._digests: dict[BoardKey, int | None] = {}
        self._serials: dict[BoardKey, int] = {}
        """(bus, seq ID) -> the board's serial number, from the start's init chain."""
        if rejoin:
            from ucom_tools.ops.remote.rejoin import Rejoin

            self.conversations.rejoiner = lambda bus, n, delay: Rejoin(self, bus, n, delay)
        from ucom_tools.ops.remote.par_write import ParWrite

        self.conversations.par_writer = lambda ref, raw: ParWrite(self, ref, raw)
        self.conversations.par_failed = self._par_failed
        self._claimed = False
        self._owns_robot = False
        self.writes: list[WriteEvent] = []
        """Values set from elsewhere than this process (the network), with their origin and
        what came of them: kept as the run's events."""
        self.share: Any = None
        """The network share (:class:`ucom_tools.net.share.RobotShare`) when the part is
        shared (:func:`ucom_tools.net.share.share`); closed with the part."""

    def _par_failed(self, ref: EdgeRef, raw: int, how: str) -> None:
        """A PAR write the loop did not wait for was not acknowledged: kept in the run's
        writes (its value is back to what it was)."""
        self.writes.append(WriteEvent(round(self._clock() - self.stats.started_clock, 4),
                                      ref.unique, str(ref.value(raw)), "not waited for",
                                      f"failed: {how}"))

    @classmethod
    def open(cls, robot: str, *, virtual: bool = False, state_dir: str | Path | None = None,
             interface: str | None = None, channels: Sequence[str] = (),
             host: str | None = None, port: int | None = None, bitrate: int | None = None,
             trees: Sequence[str | Path] = (), start: bool = True, force: bool = False,
             scenario: str | Path | None = None, **kwargs: Any) -> RemotePart:
        """The run-time part of ``robot`` (a bundled topology or a topology file) on its
        buses: the in-process virtual fleet (``virtual``, flash kept in ``state_dir``),
        or a python-can ``interface`` with ``channels`` (or a socketcand ``host`` and
        ``port``).  ``trees`` replace the robot's trees of the same Prefix.  Started
        (:meth:`start`, with ``force``) unless ``start`` is false; as a context manager
        it always stops the boards and closes the buses at the end.  Shared on the
        robot's network: :func:`ucom_tools.net.share.open_shared` (the same arguments
        and the Zenoh ones).  ``scenario``: with ``virtual``, a scenario file of injected
        faults for the fleet (``ucom(1)``, SCENARIOS)."""
        if virtual:
            spec = ConnectSpec(virtual=robot,
                               state_dir=Path(state_dir) if state_dir is not None else None,
                               scenario=Path(scenario) if scenario is not None else None)
        else:
            spec = ConnectSpec(interface, tuple(channels), bitrate, host, port,
                               topology=robot,
                               scenario=Path(scenario) if scenario is not None else None)
        r = open_robot(spec)
        try:
            part = cls(r, robot_trees(r, trees), **kwargs)
        except BaseException:
            r.close()
            raise
        part._owns_robot = True
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
                watch.listen(ExchangeWatch.listen_time(
                    h.link, x.plan.alive_ms, 0.0 if self.virtual else LISTEN_MIN_S))
                watch.check(h.name)

        self._each_bus(listen)

    # ------------------------------------------------------------------ check
    def check(self) -> CheckReport:
        """Init every bus, start each board's program if needed, fetch its descriptions
        and compare them with its tree block: every difference, nothing written."""
        found = self._each_bus(lambda h, x: check_bus(h, x, self.trees))
        boards: list[BoardCheck] = []
        refs: list[EdgeRef] = []
        self._digests.clear()  # (of the descriptions read before, if any)
        for (h, _), bus in zip(self._handles(), found, strict=True):
            assert isinstance(bus, BusCheck)
            boards += bus.boards
            refs += bus.refs
            self._described.update({(h.name, n): e for n, e in bus.described.items()})
            self._serials.update({(h.name, n): s for n, s in bus.serials.items()})
        self.report = CheckReport(tuple(boards))
        order = {(b.bus, b.board): i for i, b in enumerate(boards)}
        self.names = Names(sorted(refs, key=lambda r: order[(r.bus, r.board)]))
        return self.report

    def described(self, bus: str, board: int) -> BoardEdges | None:
        """The edges board ``board`` of ``bus`` described in :meth:`check`."""
        return self._described.get((bus, board))

    def digest(self, bus: str, board: int) -> int | None:
        """The digest of the edges board ``board`` of ``bus`` described in :meth:`check`
        (computed once: a rejoin compares the board's with it), None if it described none."""
        key = (bus, board)
        if key not in self._digests:
            edges = self._described.get(key)
            self._digests[key] = None if edges is None else edges.digest()
        return self._digests[key]

    def serial(self, bus: str, board: int) -> int:
        """The serial number of board ``board`` of ``bus``, as its Init Ack gave it in
        :meth:`check` (KeyError before)."""
        return self._serials[(bus, board)]

    def par_values(self, bus: str, board: int) -> list[tuple[EdgeRef, int]]:
        """The PAR values the PC wrote to a board (its tree's defaults and what was set
        since), by edge: what a rejoin writes again."""
        return [(ref, raw) for ref, raw in self._par.items()
                if ref.bus == bus and ref.board == board]

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
                x.configure_board(n, self.trees.board(h.name, spec.position),
                                  tree_file=str(tree_file(self.trees, h.name, spec.position)),
                                  edges=self._described[(h.name, n)])

        self._each_bus(configure_bus)
        self.names = Names(r for r in self.names if (r.bus, r.board) in good)
        self._bind_values()
        self._start_loop()
        return report

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
        self.stats.ended_clock = self._clock()
        self.conversations.end()
        problems: list[str] = []
        failed = set(self._failed)
        for h, x in self._handles():  # as at the start: while the boards are stopped one
            if h.name not in failed:  # by one (each asked, maybe again), no other's
                x.start_alive()  # watchdog fires

        def stop_bus(h: BusHandle, x: BusExchange) -> list[str]:
            out: list[str] = []
            if h.name in failed:
                return out  # its boards are lost; their watchdogs stop them
            for n in list(x.configured):
                if (h.name, n) in self._lost:  # told to stop when it was lost, and again
                    with contextlib.suppress(UcomError):  # here, unacknowledged: it is not
                        x.link.send_raw(*mca.encode(  # there to answer (or its rejoin was
                            mca.McaStart(mca.StartOp.STOP), seq(n)))  # cut short)
                    continue
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
            self._end_loop()
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


def robot_trees(robot: Robot, files: Sequence[str | Path] = ()) -> RobotTrees:
    """The robot's trees (its topology names them), with the blocks of ``files`` in place
    of the robot's blocks of the same Prefix."""
    if robot.topology is None:
        raise MissingInput("the run time needs the robot's topology (which board runs "
                           "which tree)", key="topology")
    return with_files(bind(robot.topology), files)


__all__ = ["RemotePart", "robot_trees"]
