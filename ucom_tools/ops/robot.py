"""Opening a robot: one python-can bus per CAN channel, real or virtual, with the boards
its topology expects on each.

With ``ConnectSpec.log`` (``--log FILE``) every frame received and sent on every bus the
robot opened is recorded into a python-can log (:class:`FrameLog`) until the robot is
closed; the format follows the file's extension, which is checked, like the directory,
before any bus is opened.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import can

from ucom_tools.config import topology as topo_mod
from ucom_tools.config.topology import BusSpec, Topology
from ucom_tools.errors import BusError, InputError, MissingInput, UcomError, WriteError
from ucom_tools.protocol.bootloader import BootloaderClient
from ucom_tools.protocol.link import Link
from ucom_tools.protocol.timeouts import DEFAULT, Timeouts
from ucom_tools.trace.logs import (
    FrameLog,
    check_buses,
)
from ucom_tools.transport.socketcand import SocketcandBus

T = TypeVar("T")


@dataclass(frozen=True)
class ConnectSpec:
    """How to reach the boards: a python-can interface and channels, or a virtual fleet."""

    interface: str | None = None
    channels: tuple[str, ...] = ()
    bitrate: int | None = None
    host: str | None = None
    port: int | None = None
    virtual: str | None = None
    topology: str | None = None
    state_dir: Path | None = None
    pace: bool = False
    origin: str = "command line"
    """Where the bus was named: "command line" or "environment"."""
    ignored: tuple[str, ...] = ()
    """Environment settings that named another bus and were ignored (``UCOM_X=value``)."""
    log: Path | None = None
    """Record every frame of every bus opened into this python-can log (``--log``)."""
    only: str | None = None
    """Open only this bus of the topology (``--bus NAME`` of the run-time commands): its
    channel is the one given for it (-c for every bus, in order), the one channel given,
    or, with none, the bus's name (a served fleet's channel)."""
    scenario: Path | None = None
    """With :attr:`virtual`: a scenario of injected faults for the in-process fleet
    (``--scenario FILE``; ``ucom(1)``, SCENARIOS)."""


TRANSPORT_MARGIN = {"virtual": 0.0, "socketcand": 0.25}
"""Seconds every wait adds for the transport (a network bus needs more than an adapter);
other interfaces: :data:`LOCAL_MARGIN`."""
LOCAL_MARGIN = 0.02
DEFAULT_BITRATE = 1_000_000


def transport_margin(kind: str) -> float:
    return TRANSPORT_MARGIN.get(kind, LOCAL_MARGIN)


ROUND_TRIPS = 4
"""A network bus's margin is this many of its measured round trips (there and back for
the request and the answer, and as much again for the server's scheduling) ..."""


def network_margin(round_trip_s: float | None) -> float:
    """The margin of a network bus whose round trip was measured on its connection
    (:attr:`SocketcandBus.round_trip_s`): :data:`ROUND_TRIPS` of them, at least
    :data:`LOCAL_MARGIN`; the fixed :data:`TRANSPORT_MARGIN` when none could be."""
    if round_trip_s is None:
        return TRANSPORT_MARGIN["socketcand"]
    return max(LOCAL_MARGIN, ROUND_TRIPS * round_trip_s)


@dataclass
class BusHandle:
    """One open bus with its protocol clients and the boards expected on it."""

    name: str
    bus: can.BusABC
    link: Link
    client: BootloaderClient
    expected: BusSpec | None
    virtual: bool

    def side_link(self) -> Link:
        """A link of its own on this bus's dispatcher, for a conversation beside the run
        time's own (its own subscriptions: answers are not taken from each other)."""
        h = self.link
        return Link(h.bus, h.name, bitrate=h.bitrate, margin=h.margin,
                    dispatcher=h.dispatcher)


@dataclass
class Robot:
    """Every open bus of one robot."""

    spec: ConnectSpec
    buses: dict[str, BusHandle]
    topology: Topology | None
    timeouts: Timeouts = field(default=DEFAULT)
    log: FrameLog | None = None
    """The ``--log`` recording of every bus, closed (kept) by :meth:`close`."""

    @property
    def virtual_time(self) -> bool:
        """Every bus is the in-process fleet running in virtual time (not paced)."""
        return bool(self.buses) and all(h.virtual for h in self.buses.values()) and \
            not self.spec.pace

    def select(self, name: str | None) -> list[BusHandle]:
        if name is None:
            return list(self.buses.values())
        if name not in self.buses:
            raise InputError(f"no bus {name!r}; buses: {', '.join(self.buses)}", key="bus")
        return [self.buses[name]]

    def each(self, work: Callable[[BusHandle], T], name: str | None = None, *,
             cancel: threading.Event | None = None) -> list[T]:
        """``work`` on every selected bus (``name``: one), in bus order, by the rule of
        :meth:`each_until_stopped`.  The first exception, after every bus has finished its
        work; a :class:`KeyboardInterrupt` in this thread while the buses work sets
        ``cancel`` (their work's own stop) and is raised once they ended."""
        collect, stop = self._each(work, name, cancel)
        if stop is not None:
            raise stop
        return collect()

    def each_until_stopped(self, work: Callable[[BusHandle], T], name: str | None = None,
                           *, cancel: threading.Event | None = None
                           ) -> tuple[list[T], KeyboardInterrupt | None]:
        """``work`` on every selected bus (``name``: one), in bus order: all buses at once,
        one thread each (a robot's buses are independent: init, Info, flash take the time
        of the slowest bus, not the sum), or one after the other in virtual time, where
        the fleet clock is driven by whoever waits and threads would only take turns.
        The first exception, after every bus has finished its work.  A
        :class:`KeyboardInterrupt` in this thread while the buses work sets ``cancel``
        (their work's own stop) and is returned, with every bus's result, once they
        ended (None: none came)."""
        collect, stop = self._each(work, name, cancel)
        return collect(), stop

    def _each(self, work: Callable[[BusHandle], T], name: str | None,
              cancel: threading.Event | None
              ) -> tuple[Callable[[], list[T]], KeyboardInterrupt | None]:
        """The one rule of :meth:`each` and :meth:`each_until_stopped`: every bus's work
        done, then how to collect the results (raising the first exception) and the
        interrupt that came meanwhile."""
        handles = self.select(name)
        if len(handles) == 1 or self.virtual_time:
            results = [work(h) for h in handles]
            return lambda: results, None
        stop: KeyboardInterrupt | None = None
        with ThreadPoolExecutor(max_workers=len(handles),
                                thread_name_prefix="ucom-bus") as pool:
            futures = [pool.submit(work, h) for h in handles]
            try:
                wait(futures)
            except KeyboardInterrupt as e:
                stop = e
                if cancel is not None:
                    cancel.set()
                wait(futures)
        return lambda: [f.result() for f in futures], stop

    def close(self, *, keep_log: bool = True) -> None:
        """Shut every bus down, then end the ``--log`` recording: renamed into place
        (``keep_log``), or discarded (after bad input: nothing is written).  Raises
        :class:`LogError` (no file left) when the recording could not be written."""
        unsaved: list[str] = []
        for h in self.buses.values():
            if self.log is not None:
                self.log.detach(h.name, h.link.dispatcher)
            failures = getattr(h.bus, "state_failures", None)  # the virtual fleet's --state
            if callable(failures):
                with contextlib.suppress(Exception):
                    unsaved += failures()
            with contextlib.suppress(Exception):
                h.bus.shutdown()
        log, self.log = self.log, None
        if log is not None:
            if keep_log:
                log.close()
            else:
                log.discard()
        if unsaved:
            raise WriteError(f"the virtual boards' state could not be saved ({unsaved[0]}"
                             + (f"; {len(unsaved) - 1} more board(s)" if len(unsaved) > 1
                                else "")
                             + "); the state directory keeps the flash as it was before")


# ------------------------------------------------------------------------ --log
def open_robot(spec: ConnectSpec, timeouts: Timeouts = DEFAULT) -> Robot:
    """Open every bus of ``spec``; raises :class:`BusError` with one clear line.  With
    ``spec.log`` every frame of every bus is recorded until :meth:`Robot.close` (the file
    is checked before any bus is opened: InputError, key ``log``)."""
    log = FrameLog(spec.log) if spec.log is not None else None
    try:
        robot = _open(spec, timeouts)
    except BaseException:
        if log is not None:
            log.discard()
        raise
    if log is not None:
        try:
            check_buses(log.extension, robot.buses, log.path, "log")
        except InputError:
            robot.close(keep_log=False)
            log.discard()
            raise
        robot.log = log
        for h in robot.buses.values():
            log.attach(h.name, h.link.dispatcher)
    return robot


def _open(spec: ConnectSpec, timeouts: Timeouts) -> Robot:
    if spec.virtual:
        return _open_virtual(spec, timeouts)
    if spec.scenario is not None:
        raise InputError("a scenario of injected faults is for the in-process virtual fleet "
                         "(a served fleet is given its scenario where it is served)",
                         key="scenario")
    topology = topo_mod.load(spec.topology) if spec.topology else None
    if not spec.interface:
        raise MissingInput("no CAN interface given", key="interface")
    channels = list(spec.channels)
    expected: list[BusSpec | None]
    if topology is not None and spec.only is not None:
        channels, expected = _only(topology, spec.only, channels)
    elif topology is not None:
        if not channels:
            channels = [b.name for b in topology.buses]
        if len(channels) > len(topology.buses):
            raise InputError(f"{len(channels)} channels given, topology {topology.name!r} has "
                             f"{len(topology.buses)} buses", key="channels")
        expected = list(topology.buses[:len(channels)])
    else:
        if not channels:
            raise MissingInput("no channel given", key="channels")
        expected = [None] * len(channels)
    kwargs: dict[str, Any] = {}
    if spec.bitrate:
        kwargs["bitrate"] = spec.bitrate
    if spec.host:
        kwargs["host"] = spec.host
    if spec.port:
        kwargs["port"] = spec.port
    socketcand = spec.interface == "socketcand"
    if socketcand and (not spec.host or not spec.port):
        raise MissingInput("the socketcand interface needs a host and a port", key="host")
    buses: dict[str, BusHandle] = {}
    with _closed_on_failure(buses):
        for channel, exp in zip(channels, expected, strict=True):
            try:
                if socketcand:
                    assert spec.host is not None and spec.port is not None
                    bus: can.BusABC = SocketcandBus(channel, spec.host, spec.port)
                else:
                    bus = can.Bus(interface=spec.interface, channel=channel, **kwargs)
            except can.CanInitializationError as err:
                raise BusError(_one_line(err) if socketcand else
                               f"cannot open {spec.interface} channel {channel!r}: "
                               f"{_one_line(err)}") from err
            except (can.CanError, OSError, ValueError, ImportError, TypeError,
                    NotImplementedError) as err:
                raise BusError(f"cannot open {spec.interface} channel {channel!r}: "
                               f"{_one_line(err)}") from err
            name = exp.name if exp is not None else channel
            bitrate = spec.bitrate or (exp.bitrate if exp is not None else DEFAULT_BITRATE)
            margin = network_margin(bus.round_trip_s) if isinstance(bus, SocketcandBus) \
                else transport_margin(spec.interface)
            link = Link(bus, name, bitrate=bitrate, margin=margin)
            buses[name] = BusHandle(name, bus, link, BootloaderClient(link, timeouts), exp,
                                    virtual=False)
    return Robot(spec, buses, topology, timeouts=timeouts)


def _only(topology: Topology, name: str, channels: list[str],
          ) -> tuple[list[str], list[BusSpec | None]]:
    """The channel and the bus of :attr:`ConnectSpec.only`."""
    names = [b.name for b in topology.buses]
    if name not in names:
        raise InputError(f"{topology.name!r} has no bus {name!r}; its buses: "
                         + ", ".join(names), key="only")
    index = names.index(name)
    if not channels:
        channel = name
    elif len(channels) == 1:
        channel = channels[0]
    elif len(channels) == len(names):
        channel = channels[index]
    else:
        raise InputError(f"bus {name} chosen with {len(channels)} channels: give its channel "
                         f"alone, or one for each of the {len(names)} buses in order",
                         key="channels")
    return [channel], [topology.buses[index]]


def _open_virtual(spec: ConnectSpec, timeouts: Timeouts) -> Robot:
    """The virtual fleet through python-can's registered ``ucom_virtual`` interface: one
    process-wide fleet per topology, shared by its buses and released with the last."""
    assert spec.virtual is not None
    topology = topo_mod.load(spec.virtual)
    buses: dict[str, BusHandle] = {}
    with _closed_on_failure(buses):
        for b in topology.buses:
            try:
                extra: dict[str, Any] = {} if spec.scenario is None else {
                    "scenario": str(spec.scenario)}
                bus = can.Bus(interface="ucom_virtual", channel=f"{spec.virtual}/{b.name}",
                              state_dir=spec.state_dir, realtime=spec.pace, **extra)
            except can.CanError as err:
                if isinstance(err.__cause__, UcomError):
                    raise err.__cause__ from None
                raise BusError(f"cannot open the virtual bus {b.name}: {_one_line(err)}") \
                    from err
            margin = transport_margin("virtual") if not spec.pace else LOCAL_MARGIN
            link = Link(bus, b.name, bitrate=b.bitrate, margin=margin)
            buses[b.name] = BusHandle(b.name, bus, link, BootloaderClient(link, timeouts), b,
                                      virtual=True)
    return Robot(spec, buses, topology, timeouts=timeouts)


@contextlib.contextmanager
def _closed_on_failure(buses: dict[str, BusHandle]) -> Iterator[None]:
    """Shut down the buses opened so far when opening the next one fails."""
    try:
        yield
    except BaseException:
        for h in buses.values():
            with contextlib.suppress(Exception):
                h.bus.shutdown()
        raise


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return text[0] if text else type(err).__name__
