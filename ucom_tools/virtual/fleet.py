"""A fleet: every bus and board of one topology, built and (optionally) persisted.

``state_dir`` keeps each board's non-volatile memory (flash, bootloader record with the
AutoStart flag) across restarts, like power cycles of the real robot.  ``defect`` makes
every board that does not name its own defect in the topology a mutant board
(:mod:`~ucom_tools.virtual.board.mutants`).  ``scenario`` times injected faults (a power loss, a
reset, bus-off, a cut cable, the emergency stop: :mod:`ucom_tools.config.scenario`) from
each bus's first MCA Alive; :meth:`Fleet.inject` applies one at once
(:mod:`~ucom_tools.virtual.injected`).
"""

from __future__ import annotations

import os
import re
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can

from ucom_tools.config import topology as topo
from ucom_tools.config.scenario import InjectedFault, Scenario
from ucom_tools.config.topology import BoardSpec, Topology
from ucom_tools.errors import BusError, InputError, TopologyError, UcomError
from ucom_tools.plugons import PLUG_ON_BOARDS
from ucom_tools.virtual.board import mutants
from ucom_tools.virtual.board.port import Identity
from ucom_tools.virtual.board.ucom import VirtualBoard
from ucom_tools.virtual.bus.clock import FleetClock, RealtimeDriver
from ucom_tools.virtual.bus.simbus import TX_QUEUE, SimBus
from ucom_tools.virtual.injected import Injector
from ucom_tools.wire.transfer import TransferPlan

HOST_AHEAD_US = 2000.0
"""How far ahead of a lagging paced fleet's present a host's frame may be ready."""
ROOM_POLL_S = 0.0002
"""How often a host waiting for room in its transmit queue looks again."""
INJECT_TIMEOUT_S = 5.0
"""How long :meth:`Fleet.inject` waits for a paced fleet's driver to apply a fault."""


class Fleet:
    """The virtual boards and buses of one topology."""

    def __init__(self, topology: Topology, *, state_dir: Path | None = None,
                 realtime: bool = False, defect: str | None = None,
                 client_loss: float = 0.0, seed: int = 0,
                 scenario: Scenario | None = None) -> None:
        self.defect = mutants.check(defect)
        if scenario is not None:
            scenario.check(topology)  # before anything is built: the caller's mistake
        """The defect of every board whose topology entry names none (None: they conform)."""
        if not 0.0 <= client_loss < 1.0:
            raise InputError(f"a share of frames lost must be in [0, 1), not {client_loss:g}",
                             key="client_loss")
        self.client_loss = client_loss
        """The share of frames lost between each served client and its bus, each way
        (``fleet serve --loss``: a lossy link to the PC, as in the tests' LossyBus)."""
        self.seed = seed
        """Seeds the losses (a client's generator: ``seed`` + its number)."""
        self.topology = topology
        self.state_dir = state_dir
        self.realtime = realtime
        self.epoch = time.time()
        self.buses: dict[str, SimBus] = {}
        self.boards: dict[str, list[VirtualBoard]] = {}
        self.clock = FleetClock()
        """One time base for every bus and board of the fleet."""
        self._driver: RealtimeDriver | None = None
        self._pending: dict[int, int] = {}
        """Frames per host handed to the driver and not yet on a bus's queue."""
        self._pending_lock = threading.Lock()
        if state_dir is not None:
            _state_dir(state_dir)
        for bus_spec in topology.buses:
            sim = SimBus(bus_spec.name, bus_spec.bitrate, self.clock)
            boards = []
            for b in bus_spec.boards:
                board = VirtualBoard(sim, Identity(b.position, b.placement, b.board, b.serial,
                                                   b.fixed_id, b.fpga),
                                     timing=topology.timing, powered=False,
                                     state_file=self._state_file(bus_spec.name, b),
                                     defect=b.defect or defect)
                if b.flashed is not None and not board.nv.record.flash_valid:
                    install_program(board, b, topology.source, bus_spec.name)
                sim.attach(board)
                sim.chain.append(board)
                if b.init_link_broken:
                    sim.broken_before.add(b.position)
                boards.append(board)
            for board, b in zip(boards, bus_spec.boards, strict=True):
                if b.powered:
                    board.power_on(0.0)
            self.buses[bus_spec.name] = sim
            self.boards[bus_spec.name] = boards
        self.scenario = scenario
        """The timed injected faults (None: none)."""
        self.injector = Injector(topology, self.buses, self.boards, self.clock)
        """The injected faults: in progress, and the scenario's to come."""
        if scenario is not None:
            self.injector.arm(scenario)
        if realtime:
            self._driver = RealtimeDriver(
                self.clock, f"{topology.name} ({', '.join(b.name for b in topology.buses)})")
            self._driver.on_slip = self._slipped
            # the virtual time's zero is the driver's start, not the start of building the
            # boards (a busy machine took milliseconds for them: frames were stamped that
            # much before they were on the bus)
            self.epoch = time.time() - self._driver.now_us() / 1e6
            self._driver.start()

    @classmethod
    def load(cls, name_or_path: str, *, state_dir: Path | None = None,
             realtime: bool = False, defect: str | None = None,
             scenario: Scenario | None = None) -> Fleet:
        mutants.check(defect)  # before the topology: a wrong name is the caller's mistake
        return cls(topo.load(name_or_path), state_dir=state_dir, realtime=realtime,
                   defect=defect, scenario=scenario)

    def inject(self, fault: InjectedFault) -> str:
        """Apply ``fault`` now (its ``at_s`` is not looked at) and return what was done in
        a sentence, e.g. "CAN0 board 3 (head right) powered off for 1 s"; it ends by
        itself ``for_s`` later (:attr:`injector` keeps it meanwhile, :meth:`snapshot`
        shows it).  A bus or board the fleet lacks is an :class:`InputError` naming what
        it has.  Thread-safe: on a paced fleet the driver applies it in its thread (within
        :data:`INJECT_TIMEOUT_S`, else :class:`BusError`), at the wall clock's time; else
        at the clock's present."""
        fault.check(self.topology)
        driver = self._driver
        if driver is None or driver.in_driver_thread():
            with self.clock.lock:
                return self.injector.apply(fault, self.clock.now)
        done = threading.Event()
        result: list[str | BaseException] = []

        def apply() -> None:
            try:
                result.append(self.injector.apply(fault, self.clock.now))
            except BaseException as err:  # handed to the caller's thread
                result.append(err)
            finally:
                done.set()

        driver.submit(apply)
        driver.poke()
        if not done.wait(INJECT_TIMEOUT_S):
            raise BusError(f"the fleet {self.name} did not apply the fault in "
                           f"{INJECT_TIMEOUT_S:g} s (its driver is not running)")
        outcome = result[0]
        if isinstance(outcome, BaseException):
            raise outcome
        return outcome

    def _state_file(self, bus: str, board_spec: BoardSpec) -> Path | None:
        if self.state_dir is None:
            return None
        safe = re.sub(r"[^A-Za-z0-9_-]+", "_",
                      f"{bus}-{board_spec.position + 1}-{board_spec.placement}")
        return self.state_dir / safe

    @property
    def name(self) -> str:
        return self.topology.name

    def bus(self, name: str) -> SimBus:
        try:
            return self.buses[name]
        except KeyError:
            raise UcomError(f"fleet {self.name!r} has no bus {name!r}; buses: "
                            + ", ".join(self.buses)) from None

    def _slipped(self, pause_us: float) -> None:
        """The driver's time base moved on by a pause (:data:`~ucom_tools.virtual.bus.clock.
        SLIP_US`): so does the epoch, so that frames are stamped with the wall clock's
        time at which they are on the simulated bus."""
        self.epoch += pause_us / 1e6

    def now_us(self, sim: SimBus | None = None) -> float:
        """The fleet's time now: the wall clock's when paced, else the clock's."""
        if self._driver is not None:
            return self._driver.now_us()
        return self.clock.now

    @property
    def driver(self) -> RealtimeDriver | None:
        """The thread that paces the fleet (None: not paced, or closed)."""
        return self._driver

    def watch(self, sock: socket.socket, on_readable: Callable[[], None],
              on_stop: Callable[[], None]) -> bool:
        """Have the paced driver read ``sock``: ``on_readable()`` in its thread, holding
        the lock, whenever it is readable (:meth:`RealtimeDriver.watch`); False when the
        fleet is not paced (then the caller reads it)."""
        driver = self._driver
        if driver is None:
            return False
        driver.submit(lambda: driver.watch(sock, on_readable, on_stop))
        driver.poke()  # at once, not at its next step
        return True

    def unwatch(self, sock: socket.socket, timeout: float = 1.0) -> None:
        """The driver no longer reads ``sock`` once this returns (or the driver is gone,
        or ``timeout`` passed): then it may be closed."""
        driver = self._driver
        if driver is None or not driver.running:
            return
        done = threading.Event()

        def unwatch() -> None:
            driver.unwatch(sock)
            done.set()

        driver.submit(unwatch)
        driver.poke()
        done.wait(timeout)

    def after_step(self, work: Callable[[], None]) -> bool:
        """Call ``work()`` after the paced driver's running step, outside the fleet's lock
        (only from the driver thread: a node's ``on_frame``); False when the fleet is not
        paced (then nothing is called: the caller does its work itself)."""
        driver = self._driver
        if driver is None:
            return False
        driver.after_step(work)
        return True

    def send_paced(self, sim: SimBus, sender: object, arbitration_id: int, data: bytes,
                   *, timeout: float | None, alive: Callable[[], bool] | None = None,
                   extended: bool = False) -> None:
        """A frame from a host of a paced fleet (a socketcand client, ``--pace``), ready
        now: handed to the driver thread, which queues it at its next step, so a busy
        fleet never keeps the host waiting for its lock.  Blocks while the host has
        :data:`~ucom_tools.virtual.bus.simbus.TX_QUEUE` frames waiting (its transmit queue);
        ``can.CanOperationError`` after ``timeout`` seconds of that, or when ``alive()``
        turns false.  ``extended``: a 29-bit identifier (:meth:`SimBus.send`)."""

        deadline = None if timeout is None else time.monotonic() + timeout
        while sim.queued.get(sender, 0) + self._pending.get(id(sender), 0) >= TX_QUEUE:
            if (alive is not None and not alive()) or \
                    (deadline is not None and time.monotonic() >= deadline):
                raise can.CanOperationError("transmit buffer full")
            time.sleep(ROOM_POLL_S)
        driver = self._driver
        if driver is None:  # stopped (closing): the frame waits on its bus for ever
            with sim.lock:
                _send(sim, sender, sim.now, arbitration_id, data, extended)
            return
        t = driver.now_us()
        key = id(sender)
        with self._pending_lock:
            self._pending[key] = self._pending.get(key, 0) + 1

        def queue() -> None:
            with self._pending_lock:
                self._pending[key] -= 1
            # ready at the wall clock's time; but a fleet that fell behind the wall clock
            # takes it in its own present (at most HOST_AHEAD_US ahead), so that a slow
            # machine does not look to the boards like a host that went quiet
            _send(sim, sender, min(t, self.clock.now + HOST_AHEAD_US), arbitration_id, data,
                  extended)

        driver.submit(queue, t)

    def run_for(self, seconds: float) -> None:
        """Let ``seconds`` of virtual time pass (a fleet not paced to real time)."""
        if self.realtime:
            raise RuntimeError("a paced fleet runs by itself")
        with self.clock.lock:
            self.clock.run_until(self.clock.now + seconds * 1e6)

    def close(self) -> None:
        if self._driver is not None:
            self._driver.stop()
            self._driver = None

    def snapshot(self) -> dict[str, Any]:
        """The fleet as plain data (``ucom fleet show --json``)."""
        buses = []
        for name, sim in self.buses.items():
            with sim.lock:
                elapsed = max(sim.now, 1e-9)
                boards = [{
                    "position": b.identity.position + 1,
                    "placement": b.identity.placement,
                    "board": b.identity.board,
                    "plug_on": {"name": PLUG_ON_BOARDS[b.identity.board].name,
                                "carries": PLUG_ON_BOARDS[b.identity.board].carries},
                    "serial": f"0x{b.identity.serial:08X}",
                    "fixed_id": b.identity.fixed_id or None,
                    "seq_id": b.seq_id or None,
                    "powered": b.powered,
                    "state": b.state.text if b.powered else "off",
                    "program": _program(b),
                    "autostart": b.nv.record.autostart,
                    "leds": b.leds(),
                    "plug_on_board_id": b.fpga.plug_board_id,
                    "fpga": {"board_id": b.fpga.config.board_id,
                             "app_id": b.fpga.config.app_id,
                             "version": b.fpga.config.version,
                             "ikl": b.fpga.config.ikl, "ikh": b.fpga.config.ikh,
                             "neutral": b.fpga.neutral},
                    "init_pins": b.pins(),
                    "can_errors": b.can_errors,
                    "bus_off": b.bus_off,
                    "runtime": _runtime(b),
                    **({"defect": b.defect} if b.defect else {}),
                } for b in self.boards[name]]
                buses.append({
                    "name": name, "bitrate": sim.bitrate, "boards": boards,
                    "broken_init_links": sorted(p + 1 for p in sim.broken_before),
                    "stats": {"frames": sim.stats.frames, "bits": sim.stats.bits,
                              "busy_us": round(sim.stats.busy_us, 1),
                              "load": round(sim.stats.load(elapsed), 4)},
                })
        with self.clock.lock:
            injected = self.injector.snapshot()
        return {"topology": self.topology.name, "description": self.topology.description,
                "buses": buses, "injected": injected}


def _runtime(board: VirtualBoard) -> dict[str, Any] | None:
    """The running program's exchange: state, cycle time, load, overruns."""
    app = board.application
    if app is None or app.runtime is None or not board.powered:
        return None
    rt = app.runtime
    return {"program": rt.spec.name, "state": rt.state.name, "cycle_us": rt.model.loop_us(),
            "load": round(rt.load(), 3), "cycles": rt.stats.cycles,
            "overruns": rt.stats.overruns, "watchdog_ms": rt.alive_ms}


def _program(board: VirtualBoard) -> dict[str, Any] | None:
    rec = board.nv.record
    if not rec.flash_valid:
        return None
    return {"name": rec.name, "progid": f"0x{rec.progid:08X}", "size_words": rec.size_words}


def _state_dir(path: Path) -> None:
    """Make sure ``path`` is a usable state directory (InputError naming it if not)."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise InputError(f"{path}: must name a directory; this is a file",
                         key="state_dir") from None
    except OSError as err:
        raise InputError(f"cannot create the state directory: {err.strerror or err}",
                         file=str(path)) from None
    if not os.access(path, os.R_OK | os.W_OK | os.X_OK):
        raise InputError("cannot use the state directory: no permission to read and write "
                         "it", file=str(path))


def _send(sim: SimBus, sender: object, t: float, arbitration_id: int, data: bytes,
          extended: bool) -> None:
    """``sim.send``; the keyword only for an extended frame (a standard frame is queued
    with the call it always had)."""
    if extended:
        sim.send(sender, t, arbitration_id, data, extended=True)
    else:
        sim.send(sender, t, arbitration_id, data)


def install_program(board: VirtualBoard, board_spec: BoardSpec, source: str, bus: str) -> None:
    """Put a topology's initial program into a board's flash, as if flashed earlier."""
    from ucom_tools.image.formats import load_image  # the image layer is only needed here

    assert board_spec.flashed is not None
    try:
        stat = board_spec.flashed.stat()
        key = (str(board_spec.flashed.resolve()), stat.st_mtime_ns, stat.st_size)
        plan = _PLANS.get(key)
        if plan is None:
            plan = load_image(board_spec.flashed).plan(when_epoch=stat.st_mtime)
            if len(_PLANS) >= PLANS_KEPT:
                _PLANS.pop(next(iter(_PLANS)))
            _PLANS[key] = plan
    except OSError as err:
        raise TopologyError(f"the S-record file it names cannot be read: "
                            f"{err.strerror or err}", file=source, line=board_spec.line,
                            key=f"{bus}, board {board_spec.position + 1} ({board_spec.placement}), "
                            "program") from None
    except UcomError as err:
        raise TopologyError(f"the S-record file it names is not usable: {err}", file=source,
                            line=board_spec.line, key=f"{bus}, board {board_spec.position + 1} "
                            f"({board_spec.placement}), program") from None
    board.nv.install(plan)
    board.nv.record.autostart = board_spec.autostart


PLANS_KEPT = 8
"""Transfer plans of topology images kept (by file, modification time and size): a
fleet's boards mostly run one image, and parsing it and planning its transfer costs
about 30 ms a board (0.3 s for ARMAR-III, at every fleet a test or command builds)."""

_PLANS: dict[tuple[str, int, int], TransferPlan] = {}


_Key = tuple[str, str, bool, str]
_SHARED: dict[_Key, Fleet] = {}
_USERS: dict[_Key, int] = {}
_SHARED_LOCK = threading.Lock()


def _key(name_or_path: str, state_dir: Path | None, realtime: bool,
         scenario: str | Path | None) -> _Key:
    return (name_or_path, str(state_dir or ""), realtime, str(scenario or ""))


def shared_fleet(name_or_path: str, state_dir: Path | None = None,
                 realtime: bool = False, scenario: str | Path | None = None) -> Fleet:
    """The process-wide fleet for a topology, so several bus objects share its boards
    (one per state directory, pace and scenario file: ``scenario`` names a scenario of
    injected faults, :meth:`Scenario.load`).

    Each call counts as one user; :func:`release_shared` ends a use, and the fleet is
    closed and forgotten when its last user is gone, so the next one powers up anew."""
    key = _key(name_or_path, state_dir, realtime, scenario)
    with _SHARED_LOCK:
        fleet = _SHARED.get(key)
        if fleet is None:
            loaded = Scenario.load(scenario) if scenario else None
            fleet = _SHARED[key] = Fleet.load(name_or_path, state_dir=state_dir,
                                              realtime=realtime, scenario=loaded)
        _USERS[key] = _USERS.get(key, 0) + 1
        return fleet


def release_shared(fleet: Fleet) -> None:
    """One user of a shared fleet is done with it."""
    with _SHARED_LOCK:
        for key, f in list(_SHARED.items()):
            if f is fleet:
                _USERS[key] -= 1
                if _USERS[key] <= 0:
                    del _SHARED[key], _USERS[key]
                    f.close()
                return


def forget_shared() -> None:
    """Drop every shared fleet (tests, console restarts)."""
    with _SHARED_LOCK:
        for f in _SHARED.values():
            f.close()
        _SHARED.clear()
        _USERS.clear()
