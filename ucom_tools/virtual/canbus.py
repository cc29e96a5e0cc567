"""The virtual fleet as a python-can interface: ``can.Bus(interface="ucom_virtual", ...)``.

Registered through the ``can.interface`` entry point, so every python-can tool and every
``ucom`` command reaches the virtual boards like real hardware.  Channel ``"CAN0"`` with
``topology="armar3"``, or ``"armar3/CAN0"`` for short.

In virtual time (the default) the host drives the fleet clock: ``send`` runs it until the
frame is on the wire, ``recv`` until a frame arrives or the timeout has passed in virtual
time - a timeout costs no wall time.  Every bus of a fleet shares that clock.  With
``realtime=True`` a clock thread paces the fleet to the wall clock and ``recv`` waits for
real.  ``scenario="FILE"`` gives the fleet a scenario of injected faults (``ucom(1)``,
SCENARIOS); it is part of the shared fleet's key, as the topology, ``state_dir`` and
``realtime`` are.  :attr:`VirtualUcomBus.state` is python-can's controller state:
error-passive while no other node acknowledges this host's frames (a cut cable, every
board of the bus powered off or bus-off), else active.
"""

from __future__ import annotations

import queue
import time
from collections import deque
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

import can

from ucom_tools.errors import UcomError
from ucom_tools.protocol.frames import DataFrame, data_frame, received_message
from ucom_tools.signals import deferred
from ucom_tools.virtual.bus.simbus import TX_QUEUE, SimBus
from ucom_tools.virtual.fleet import Fleet, release_shared, shared_fleet
from ucom_tools.wire.canbits import MAX_EXTENDED_ID

if TYPE_CHECKING:
    from ucom_tools.protocol.buscontract import VirtualTimeBus

INF: Final = float("inf")


class HostPort:
    """The host's attachment to a simulated bus; collects the frames it receives."""

    def __init__(self, sim: SimBus, fleet: Fleet, realtime: bool, channel: str) -> None:
        self.sim = sim
        self.fleet = fleet
        """Its ``epoch`` stamps the frames (read per frame: a paced fleet's epoch moves on
        after a pause, :data:`~ucom_tools.virtual.bus.clock.SLIP_US`)."""
        self.channel = channel
        self.realtime = realtime
        self.inbox: deque[can.Message | DataFrame] = deque()
        """Virtual time: what arrived and was not yet taken, a standard data frame as a
        :data:`~ucom_tools.protocol.frames.DataFrame` (:meth:`message` builds its
        message), an extended one as a message."""
        self.rt_inbox: queue.SimpleQueue[can.Message] = queue.SimpleQueue()

    def on_frame(self, arbitration_id: int, data: bytes, t_end: float,
                 extended: bool = False) -> None:
        stamp = self.fleet.epoch + t_end / 1e6
        if self.realtime:
            self.rt_inbox.put(data_frame(stamp, arbitration_id, bytearray(data),
                                         is_extended_id=extended, is_rx=True,
                                         channel=self.channel))
        elif extended:
            self.inbox.append(data_frame(stamp, arbitration_id, bytearray(data),
                                         is_extended_id=True, is_rx=True,
                                         channel=self.channel))
        else:
            self.inbox.append((arbitration_id, data if type(data) is bytes else bytes(data),
                               stamp))

    def message(self, item: can.Message | DataFrame) -> can.Message:
        """The message of an item of :attr:`inbox`."""
        if not isinstance(item, tuple):
            return item
        return received_message(item, self.channel)

    def on_extended_frame(self, arbitration_id: int, data: bytes, t_end: float) -> None:
        """A frame with a 29-bit identifier (another host's: boards send none)."""
        self.on_frame(arbitration_id, data, t_end, extended=True)


def _init_error(err: UcomError) -> can.CanInitializationError:
    """python-can's error for a bus that cannot be opened, caused by ``err``: the CLI
    gives the cause's own exit code (``__cause__`` set by hand: see compiled.py)."""
    error = can.CanInitializationError(str(err))
    error.__cause__ = err
    return error


class VirtualUcomBus(can.BusABC):
    """A python-can bus whose peers are the virtual UCoMs of a fleet."""

    def __init__(self, channel: Any = None, *, topology: str | None = None,
                 state_dir: str | Path | None = None, fleet: Fleet | None = None,
                 realtime: bool = False, receive_own_messages: bool = False,
                 scenario: str | Path | None = None, **kwargs: Any) -> None:
        name = str(channel or "")
        self._shared = fleet is None
        if fleet is None:
            if topology is None:
                if "/" not in name:
                    raise can.CanInitializationError(
                        "virtual UCoM bus: give channel 'TOPOLOGY/BUS' (e.g. 'armar3/CAN0') "
                        "or topology=...")
                topology, name = name.rsplit("/", 1)
            try:
                fleet = shared_fleet(topology, Path(state_dir) if state_dir else None,
                                     realtime, scenario)
            except UcomError as err:
                raise _init_error(err) from err
        elif scenario is not None:
            raise can.CanInitializationError(
                "virtual UCoM bus: scenario= is for the shared fleet of a topology; a Fleet "
                "given takes its scenario when it is built (Fleet(..., scenario=...))")
        elif "/" in name:
            name = name.rsplit("/", 1)[1]
        if not name:
            name = next(iter(fleet.buses))
        try:
            self.sim = fleet.bus(name)
        except UcomError as err:
            if self._shared:
                release_shared(fleet)
            raise _init_error(err) from err
        self.fleet = fleet
        self.realtime = fleet.realtime
        self.receive_own_messages = receive_own_messages
        self.port = HostPort(self.sim, fleet, self.realtime, name)
        self.sim.attach(self.port)
        self.channel_info = f"virtual UCoM bus {fleet.name}/{name}"
        super().__init__(channel=name, **kwargs)

    @property
    def state(self) -> can.BusState:
        """python-can's controller state: ``PASSIVE`` (error-passive) while no other node of the bus
        would acknowledge a frame of this host (:meth:`SimBus.acknowledged`: the cable to
        the boards cut, every board powered off or bus-off, and no other host), else
        ``ACTIVE``."""
        if self.sim.acknowledged(self.port):
            return can.BusState.ACTIVE
        return can.BusState.PASSIVE

    @state.setter
    def state(self, new_state: can.BusState) -> None:
        raise NotImplementedError("the virtual UCoM bus's state follows its nodes")

    def clock(self) -> float:
        """Seconds on this bus's time base: the fleet clock's virtual time, or the wall
        clock when the fleet runs in real time.  Timeouts given to :meth:`recv` count on
        it."""
        if self.realtime:
            return time.monotonic()
        return self.sim.now / 1e6

    def stamp(self) -> float:
        """A timestamp on the base of this bus's received frames: the fleet's epoch plus
        its time (virtual, or paced to the wall clock)."""
        return self.fleet.epoch + self.fleet.now_us(self.sim) / 1e6

    # ------------------------------------------------------------------ send
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send a data frame, standard or extended (the boards ignore extended ones, other
        hosts of the bus receive them); remote, error and CAN FD frames are refused."""
        if msg.is_fd or msg.is_remote_frame or msg.is_error_frame:
            raise can.CanOperationError("the virtual UCoM bus carries CAN 2.0 data frames "
                                        "only (no remote, error or CAN FD frames)")
        extended = bool(msg.is_extended_id)
        if not 0 <= msg.arbitration_id <= (MAX_EXTENDED_ID if extended else 0x7FF):
            raise can.CanOperationError(
                f"identifier 0x{msg.arbitration_id:X} has more than "
                f"{29 if extended else 11} bits")
        if msg.dlc > 8:
            raise can.CanOperationError(f"DLC {msg.dlc}: at most 8")
        self._send(msg.arbitration_id, bytes(msg.data[:msg.dlc]), extended, timeout)

    def send_data(self, arbitration_id: int, data: bytes, timeout: float | None = None,
                  ) -> None:
        """:meth:`send` of a standard data frame given by its identifier and data, without
        a ``can.Message`` (:meth:`~ucom_tools.protocol.dispatch.Dispatcher.send_data`:
        the run time's frames); the same errors."""
        if not 0 <= arbitration_id <= 0x7FF:
            raise can.CanOperationError(f"identifier 0x{arbitration_id:X} has more than "
                                        "11 bits")
        if len(data) > 8:
            raise can.CanOperationError(f"DLC {len(data)}: at most 8")
        self._send(arbitration_id, data if type(data) is bytes else bytes(data), False,
                   timeout)

    def _send(self, ident: int, data: bytes, extended: bool, timeout: float | None) -> None:
        sim, port = self.sim, self.port
        if self.realtime:
            self.fleet.send_paced(sim, port, ident, data, timeout=timeout, extended=extended)
            if self.receive_own_messages:
                port.on_frame(ident, data, self.fleet.now_us(sim), extended)
            return
        with deferred, sim.lock:  # a signal waits for the step (ucom_tools.signals)
            if sim.send_alone(port, sim.now, ident, data, extended=extended) is None:
                # virtual time: queue the frame like an adapter's TX queue; the clock
                # runs on when the host waits (or here, while the queue is full)
                if sim.queued.get(port, 0) >= TX_QUEUE:
                    sim.run_until(INF, stop=lambda: sim.queued.get(port, 0) < TX_QUEUE)
                sim.send(port, sim.now, ident, data, extended=extended)
        if self.receive_own_messages:
            port.on_frame(ident, data, sim.now, extended)

    # ------------------------------------------------------------------ receive
    def recv(self, timeout: float | None = None) -> can.Message | None:
        """Next frame that passes the filters; in virtual time ``timeout`` is virtual."""
        if self.realtime:
            return super().recv(timeout)
        sim = self.sim
        with deferred, sim.lock:
            deadline = INF if timeout is None else sim.now + timeout * 1e6
            while True:
                got = self._next_virtual(deadline)
                if got is None:
                    return None
                if self._matches_filters(got):
                    return got

    def advance_frames(self, timeout: float) -> list[can.Message | DataFrame] | None:
        """Run the fleet clock ``timeout`` seconds of virtual time on (every bus of the
        fleet runs) and return every frame this bus received by then, in order, at once,
        a standard data frame as a :data:`~ucom_tools.protocol.frames.DataFrame`
        (:meth:`message_of` builds the message ``recv`` gives): what
        :meth:`~ucom_tools.protocol.dispatch.Dispatcher.pump` does instead of one
        :meth:`recv` per frame.  None where that is not the same: in real time, or with
        filters (then ``recv`` applies them)."""
        if self.realtime or self._filters:
            return None
        sim = self.sim
        with deferred, sim.lock:
            sim.run_until(sim.now + timeout * 1e6)
            inbox = self.port.inbox
            out = list(inbox)
            inbox.clear()
        return out

    def message_of(self, frame: DataFrame) -> can.Message:
        """The message :meth:`recv` gives for a frame :meth:`advance_frames` handed over."""
        return self.port.message(frame)

    def _next_virtual(self, deadline: float) -> can.Message | None:
        port, sim = self.port, self.sim
        inbox = port.inbox
        if not inbox:
            if deadline == INF and sim.next_event_time() is None:
                return None  # nothing can ever arrive in virtual time
            sim.run_until(deadline, stop=lambda: bool(inbox))
        if inbox:
            return port.message(inbox.popleft())
        return None

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.realtime:
            try:
                return self.port.rt_inbox.get(timeout=timeout), False
            except queue.Empty:
                return None, False
        with deferred, self.sim.lock:
            deadline = INF if timeout is None else self.sim.now + timeout * 1e6
            got = self._next_virtual(deadline)
        return got, False

    def state_failures(self) -> list[str]:
        """Why boards of this bus could not save their flash to the state directory (their
        files there keep the state before); empty when all is saved."""
        return [b.nv.save_failure for b in self.fleet.boards.get(self.sim.name, ())
                if b.nv.save_failure]

    def shutdown(self) -> None:
        if self._is_shutdown:
            return
        self.sim.detach(self.port)
        if self._shared:
            release_shared(self.fleet)
        super().shutdown()


if TYPE_CHECKING:  # mypy checks that the bus keeps the contract the dispatcher relies on
    def _keeps_the_bus_contract(bus: VirtualUcomBus) -> VirtualTimeBus:
        return bus
