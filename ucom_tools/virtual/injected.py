"""Injected faults applied to a virtual fleet: at once (:meth:`Injector.apply`, what
``Fleet.inject`` and ``ucom fleet fault`` do) or timed by a scenario (:meth:`Injector.arm`).

The faults themselves are defined in :mod:`ucom_tools.config.scenario`; each is carried
out as the hardware does it, by the board (:meth:`~ucom_tools.virtual.board.ucom.VirtualBoard.
lose_power`, :meth:`~ucom_tools.virtual.board.ucom.VirtualBoard.enter_bus_off`, ...) and the
bus (:meth:`~ucom_tools.virtual.bus.simbus.SimBus.cut_cable`).  Faults that overlap add up: a
board is powered while no power fault holds it off (an emergency stop during a board's
own power-off ends the later of the two), and so for bus-off and a cut cable.  A board
its topology leaves unpowered stays so.

A scenario's times count from the first MCA Alive the fleet receives on the bus (the start
of the exchange), on each bus from its own: a node of each bus that has faults to come
(:class:`_FirstAlive`) looks at the PC's frames until that Alive, then leaves the bus, so
that no frame pays for the faults afterwards.  Everything runs on the fleet clock, holding
the fleet's lock: in virtual time deterministically, paced on the wall clock.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, Final

from ucom_tools.config.scenario import FaultKind, InjectedFault, Scenario
from ucom_tools.config.topology import Topology
from ucom_tools.virtual.board.ucom import VirtualBoard
from ucom_tools.virtual.bus.clock import FleetClock
from ucom_tools.virtual.bus.simbus import SimBus
from ucom_tools.wire.ids import Function

log = logging.getLogger("ucom.fleet")
_ALIVE: Final = int(Function.MCA_ALIVE)


@dataclass
class Active:
    """A fault in progress: what, since and until when (fleet time, microseconds), and
    the sentence that said what was done."""

    fault: InjectedFault
    since_us: float
    until_us: float
    text: str

    def as_dict(self) -> dict[str, Any]:
        return {**self.fault.as_dict(), "since_s": round(self.since_us / 1e6, 6),
                "until_s": round(self.until_us / 1e6, 6), "done": self.text}


class Injector:
    """The injected faults of one fleet: ``buses`` and ``boards`` by bus name (the
    fleet's), on ``clock``; ``topology`` names them (the fleet's buses only)."""

    def __init__(self, topology: Topology, buses: Mapping[str, SimBus],
                 boards: Mapping[str, Sequence[VirtualBoard]], clock: FleetClock) -> None:
        self.topology = topology
        self.buses = buses
        self.boards = boards
        self.clock = clock
        self.active: list[Active] = []
        """The faults in progress, in the order they began."""
        self._off: dict[VirtualBoard, int] = {}
        """Per board, the power faults that hold it off."""
        self._bus_off: dict[VirtualBoard, int] = {}
        self.watchers: dict[str, _FirstAlive] = {}
        """Per bus, the node that waits for its first MCA Alive (until it came)."""
        self.started: dict[str, float] = {}
        """Per bus, the time of its first MCA Alive, once a scenario counts from it."""

    # ------------------------------------------------------------------ scenarios
    def arm(self, scenario: Scenario) -> None:
        """Time ``scenario``'s faults (checked against the topology before) from each
        bus's first MCA Alive."""
        for name, sim in self.buses.items():
            faults = scenario.of_bus(name)
            if faults:
                watcher = _FirstAlive(name, faults, self._begin)
                self.watchers[name] = watcher
                sim.attach(watcher)

    def _begin(self, bus: str, faults: tuple[InjectedFault, ...], t: float) -> None:
        """The first MCA Alive on ``bus`` came at ``t``: its faults are due from there."""
        self.started[bus] = t
        watcher = self.watchers.pop(bus, None)
        sim = self.buses[bus]
        if watcher is not None:  # after this delivery: it iterates the bus's nodes
            self.clock.at(t, lambda _when: sim.detach(watcher))
        for fault in faults:
            self.clock.at(t + fault.at_s * 1e6, self._due(fault, bus))

    def _due(self, fault: InjectedFault, bus: str) -> Callable[[float], None]:
        def apply(t: float) -> None:
            text = self.apply(fault, t, only=bus if fault.bus is None else None)
            log.info("scenario, %g s after the first MCA Alive on %s: %s", fault.at_s, bus,
                     text)
        return apply

    # ------------------------------------------------------------------ applying
    def apply(self, fault: InjectedFault, t: float, *, only: str | None = None) -> str:
        """Begin ``fault`` at ``t`` (holding the fleet's lock) and time its end; returns
        what was done in a sentence.  ``only``: a fault of the whole robot on this bus
        alone (a scenario's, from the bus's own first MCA Alive)."""
        kind = fault.kind
        end = t + fault.for_s * 1e6
        if kind is FaultKind.CABLE:
            assert fault.bus is not None
            sim = self.buses[fault.bus]
            sim.cut_cable()
            self._at(end, lambda _t: sim.mend_cable())
        elif kind is FaultKind.BUS_OFF:
            board = self._board(fault)
            self._bus_off[board] = self._bus_off.get(board, 0) + 1
            if self._bus_off[board] == 1:
                board.enter_bus_off()
            self._at(end, lambda _t: self._bus_on(board))
        elif kind is FaultKind.ESTOP:
            boards = [b for name, bs in self.boards.items() if only in (None, name)
                      for b in bs]
            off = [b for b in boards if self._power_down(b, t)]
            self._at(end, lambda when: self._power_up(off, when, announce=False))
        else:  # power-off, reset: the DSP resets as at power-on, after the reset time
            board = self._board(fault)
            reset = kind is FaultKind.RESET
            if reset:
                end += board.timing.reset_us
            off = [board] if self._power_down(board, t) else []
            self._at(end, lambda when: self._power_up(off, when, announce=reset))
        text = self.describe(fault, only)
        active = Active(fault, t, end, text)
        self.active.append(active)
        self._at(end, lambda _t: self._ended(active))
        return text

    def describe(self, fault: InjectedFault, only: str | None = None) -> str:
        """The sentence :meth:`apply` returns."""
        topology = self.topology
        if only is not None:
            topology = replace(topology, buses=(topology.bus(only),))
        return fault.describe(topology, topology.timing.reset_us / 1e6)

    def _at(self, t: float, callback: Callable[[float], None]) -> None:
        self.clock.at(t, callback)

    def _board(self, fault: InjectedFault) -> VirtualBoard:
        assert fault.bus is not None and fault.board is not None
        return self.boards[fault.bus][fault.board - 1]

    def _power_down(self, board: VirtualBoard, t: float) -> bool:
        """One more fault holds ``board`` off (False: it is unpowered by its topology,
        no fault's to end)."""
        holds = self._off.get(board, 0)
        if holds == 0 and not board.powered:
            return False
        self._off[board] = holds + 1
        if holds == 0:
            board.lose_power(t)
        return True

    def _power_up(self, boards: list[VirtualBoard], t: float, *, announce: bool) -> None:
        for board in boards:
            holds = self._off.get(board, 0) - 1
            if holds > 0:
                self._off[board] = holds
                continue
            self._off.pop(board, None)
            board.regain_power(t, announce=announce)

    def _bus_on(self, board: VirtualBoard) -> None:
        holds = self._bus_off.get(board, 0) - 1
        if holds > 0:
            self._bus_off[board] = holds
            return
        self._bus_off.pop(board, None)
        board.leave_bus_off()

    def _ended(self, active: Active) -> None:
        if active in self.active:
            self.active.remove(active)

    def snapshot(self) -> list[dict[str, Any]]:
        """The faults in progress as plain data (``ucom fleet show --json``), times in
        seconds of the fleet's clock."""
        return [a.as_dict() for a in self.active]


class _FirstAlive:
    """A node on a bus that waits for the PC's first MCA Alive (a generic frame of
    function 26), then hands the bus's scenario faults to :meth:`Injector._begin`.  As a
    board's CAN controller, it is offered only the PC's frames and no CI maps; it
    acknowledges nothing (``listening``)."""

    takes_board_frames = False
    listening = False

    def __init__(self, bus: str, faults: tuple[InjectedFault, ...],
                 begin: Callable[[str, tuple[InjectedFault, ...], float], None]) -> None:
        self.bus = bus
        self.faults = faults
        self.begin = begin
        self.seen = False

    def takes_ci_map(self, number: int) -> bool:
        return False

    def on_frame(self, arbitration_id: int, data: bytes, t_end: float) -> None:
        if not self.seen and arbitration_id >> 6 == _ALIVE and not arbitration_id & 0x20:
            self.seen = True
            self.begin(self.bus, self.faults, t_end)
