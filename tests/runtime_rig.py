"""A host running the cyclic exchange with a virtual fleet, for the run-time tests: the
real clients (bootloader, MCA) on real virtual buses, the real start sequence
(:mod:`ucom_tools.ops.exchange`) and the planner's maps."""

from __future__ import annotations

from collections.abc import Callable

import can

from ucom_tools.config.attrtree.robot import RobotTrees, bind
from ucom_tools.config.topology import SOURCE_ROOT, load
from ucom_tools.ops.exchange import BusExchange
from ucom_tools.ops.robot import BusHandle, ConnectSpec, Robot
from ucom_tools.protocol.bootloader import BootloaderClient
from ucom_tools.protocol.link import Link
from ucom_tools.protocol.plan import BusPlan
from ucom_tools.virtual.board.runtime import McaRuntime
from ucom_tools.virtual.board.ucom import VirtualBoard
from ucom_tools.virtual.canbus import VirtualUcomBus
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.wire import mca

IMAGES = {"armar3": "firmware_images/armar3.fl.S", "lauron4": "firmware_images/lauron4.fl.S"}


def programmed(topology: str = "armar3", *, autostart: bool = False) -> Fleet:
    """The bundled robot with its program already in every board's flash."""
    return Fleet(load(topology).with_flashed(SOURCE_ROOT / IMAGES[topology],
                                             autostart=autostart))


class RunHost:
    """The PC side of one bus: a virtual CAN interface, a link and the product's
    :class:`~ucom_tools.ops.exchange.BusExchange` on it."""

    def __init__(self, fleet: Fleet, bus: str, *, trees: RobotTrees | None = None,
                 alive_ms: int = mca.ALIVE_DEFAULT_MS) -> None:
        self.fleet = fleet
        self.bus_name = bus
        self.can = VirtualUcomBus(bus, fleet=fleet)
        self.link = Link(self.can, bus)
        self.exchange = BusExchange(self.link, fleet.topology.bus(bus),
                                    trees or bind(fleet.topology), alive_ms=alive_ms)
        self.boot = self.exchange.boot
        self.mca = self.exchange.mca
        self.plan: BusPlan = self.exchange.plan
        self.configured = self.exchange.configured
        self.ci = self.exchange.ci
        self._closed = False

    @property
    def boards(self) -> list[VirtualBoard]:
        return self.fleet.boards[self.bus_name]

    def runtime(self, n: int) -> McaRuntime:
        app = self.boards[n - 1].application
        assert app is not None and app.runtime is not None
        return app.runtime

    def now(self) -> float:
        return self.link.dispatcher.clock()

    def numbers(self) -> list[int]:
        return [b.position + 1 for b in self.fleet.topology.bus(self.bus_name).boards]

    def start_programs(self) -> dict[int, mca.McaReady]:
        """Init and bootloader Start of every board; their MCA Ready."""
        init = self.boot.init_chain()
        assert init.numbers == self.numbers()
        return self.exchange.start_programs(init.numbers)

    def configure_all(self) -> None:
        self.exchange.configure_all(self.numbers())

    def start_exchange(self) -> None:
        self.exchange.start_exchange()

    def bring_up(self) -> None:
        self.start_programs()
        self.configure_all()
        self.start_exchange()

    def stop_alive(self) -> None:
        """The PC stops sending MCA Alive (its CI maps keep going)."""
        for t in self.exchange.tasks:
            if "Alive" in t.name:
                self.link.dispatcher.cancel(t)

    def run(self, ms: int, *, each: Callable[[int], None] | None = None) -> None:
        """``ms`` milliseconds of the exchange on this bus (the fleet clock follows);
        ``each(k)`` runs at the start of millisecond k."""
        t0 = self.now()
        for k in range(ms):
            if each is not None:
                each(k)
            self.exchange.pump(t0 + (k + 1) * 0.001)

    def set_ci(self, board: int, name: str, raw: int) -> None:
        self.exchange.set_ci(board, name, raw)

    def so(self, board: int, name: str) -> int | None:
        return self.exchange.so(board, name)

    def close(self) -> None:
        """The PC goes away (again: nothing happens)."""
        if not self._closed:
            self._closed = True
            self.exchange.close()
            self.can.shutdown()


def bring_up_robot(fleet: Fleet) -> list[RunHost]:
    """Every bus of ``fleet`` started and configured, then every exchange started
    together (no bus waits long enough for another's watchdog)."""
    hosts = [RunHost(fleet, bus) for bus in fleet.buses]
    for h in hosts:
        h.start_programs()
        h.configure_all()
    for h in hosts:
        h.start_exchange()
    return hosts


def run_robot(hosts: list[RunHost], ms: int, *,
              each: Callable[[int], None] | None = None) -> None:
    """``ms`` milliseconds of the exchange on every bus at once."""
    t0 = hosts[0].now()
    for k in range(ms):
        if each is not None:
            each(k)
        until = t0 + (k + 1) * 0.001
        for h in hosts:
            h.exchange.pump(until)


def robot_of(fleet: Fleet, *, wrap: Callable[[can.BusABC], can.BusABC] | None = None,
             ) -> Robot:
    """An ops-level Robot on ``fleet``'s buses (``wrap`` puts e.g. a LossyBus around
    each), as ``open_robot`` makes for ``--virtual``."""
    buses = {}
    for spec in fleet.topology.buses:
        bus: can.BusABC = VirtualUcomBus(spec.name, fleet=fleet)
        if wrap is not None:
            bus = wrap(bus)
        link = Link(bus, spec.name, bitrate=spec.bitrate)
        buses[spec.name] = BusHandle(spec.name, bus, link, BootloaderClient(link), spec,
                                     virtual=True)
    return Robot(ConnectSpec(virtual=fleet.topology.name), buses, fleet.topology)
