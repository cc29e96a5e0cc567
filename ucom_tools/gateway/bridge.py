"""The gateway at work (``ucom gateway canopen``): every joint of a running robot a CiA 402
drive on a CANopen bus, between the run time's hand-over and the CANopen node runtime.

One :class:`~ucom_tools.gateway.joint_drive.JointDrive` per joint joins its node
(:mod:`ucom_tools.gateway.node`, on canopen's ``LocalNode``) to its drive
(:class:`~ucom_tools.gateway.cia402.Drive402`) and to its board's edges in the run
(:class:`Source`: the loop's snapshots and its :meth:`~Source.drive` writes; in the loop's
process a ``LocalRun``, in the consumers' process a ``Mirror``). :class:`Gateway` makes one
node runtime per CANopen bus, each
with its own thread; a joint's drive runs only on its bus's thread:

- a master's write of a drive object (SDO or RPDO) updates the joint's
  :class:`~ucom_tools.gateway.cia402_objects.ObjectValues`; an SDO's, and a new
  controlword by RPDO, run the drive at once (the effect is in 0x6041 when the SDO's
  confirmation goes; no edge of the controlword is lost), other RPDO values at the SYNC
  that applies them (synchronous) or at the next turn of the cycle;
- a SYNC runs every drive of the bus (CSP takes 0x607A) before the TPDOs are built;
- once a cycle, a drive runs again where a newer snapshot came, a write is pending or
  its time-based rules (windows, homing, the quick stop's brake) may have moved on
  (every :data:`~ucom_tools.gateway.joint_drive.IDLE_S` at least);
- each run stores 0x6041, 0x6061, 0x603F, 0x6064 and 0x606C into the node, sends the
  drive's EMCYs, and hands the axis's edges that changed to the loop (Command, Target,
  TargetVel, Reset Offset; the PARs Reset PWM and Max Velocity only when they differ
  from what the board has).

The causes of FAULT (``man/ucom-gateway.7``, FAULTS): the joint's board lost (a level
while the run time reports it lost), its watchdog latched (a level from its WATCHDOG
Error until it rejoins), any Error it sends (an event), and on the CANopen side the
master gone (the master watch: heartbeat consumer or SYNC timeout) or the bus failing.
NMT stop switches the joint off ("disable voltage"); a reset node or reset communication
makes a new drive (the objects back to their defaults).

Writes of the board's other edges (manufacturer objects 0x2000-0x3FFF, by SDO or RPDO)
go to the loop as they come, after the dictionary's range check; a write to an edge of a
lost board is aborted (0x08000022).  SO edges (0x4000-) read what the latest snapshot
holds.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import can
from canopen import ObjectDictionary

from ucom_tools.errors import InputError
from ucom_tools.gateway import dictionary
from ucom_tools.gateway.buses import by_bus
from ucom_tools.gateway.cia402_objects import (
    DriveFault,
    FaultCause,
    State402,
)
from ucom_tools.gateway.codes import NmtCommand, NmtState, StateChange
from ucom_tools.gateway.joint_drive import IDLE_S, JointDrive, SharedCommand, Source
from ucom_tools.gateway.joints import Joint, Role
from ucom_tools.gateway.load import CANOPEN_BITRATE, WARN_SHARE, pdo_load
from ucom_tools.gateway.node import NodeCallbacks, NodeRuntime
from ucom_tools.ops.remote.image import PartImage
from ucom_tools.ops.remote.publish import LoopSnapshot

log = logging.getLogger("ucom.gateway")
_now = time.monotonic

LOAD_SYNCS = 50
"""SYNCs over which the master's SYNC rate is measured for the bus load warning."""
INF = float("inf")
SYNCED_GAP_S = 2 * IDLE_S
"""SYNCs at most this far apart run a bus's drives: a joint that moved waits for the
next SYNC (its TPDOs carry it then) instead of running its drive at every snapshot (250
a second: three times the drive's work of 100 SYNCs a second, all for nothing)."""


@dataclass(frozen=True)
class CanopenBus:
    """One CANopen bus of the gateway: its python-can bus and the UCoM buses whose joints
    it carries (empty: every joint not on another)."""

    bus: can.BusABC
    spec: str
    """As given (``socketcand:CO0@127.0.0.1:29536``), for messages."""
    ucom_buses: tuple[str, ...] = ()

class Gateway:
    """Every joint of ``joints`` a CiA 402 node on its CANopen bus (see the module
    docstring): :meth:`start`, :meth:`close`."""

    def __init__(self, joints: Iterable[Joint], image: PartImage, source: Source,
                 buses: Iterable[CanopenBus], *, cycle: float = 0.001,
                 dictionaries: Mapping[int, ObjectDictionary] | None = None) -> None:
        self.image = image
        self.source = source
        self.cycle = cycle
        self.drives: dict[int, JointDrive] = {}
        self._groups: list[tuple[CanopenBus, list[JointDrive]]] = []
        self.runtimes: list[NodeRuntime] = []
        self._bus_faults: dict[int, DriveFault | None] = {}
        self._shared: dict[tuple[str, int], SharedCommand] = {}
        self._owned: list[Any] = []
        """What :meth:`serve` opened, closed with the gateway (last first)."""
        self._dictionaries = dict(dictionaries or {})
        """Node ID -> its dictionary where already built (:func:`dictionaries`)."""
        joints = list(joints)
        buses = list(buses)
        running = set(image.bitrates)  # (--bus NAME: only that bus's joints)
        joints = [j for j in joints if j.bus in running]
        for i, mine in by_bus(buses, joints, lambda j: j.bus).items():
            if mine:
                self._groups.append((buses[i], [self._joint(j) for j in mine]))
        self._load_warned: set[int] = set()
        self.master_events: list[tuple[float, str, str, str]] = []
        """(seconds since the start, the CANopen bus, 'lost' or 'back', why) as the master
        watches said."""
        self._started = _now()

    def _joint(self, joint: Joint) -> JointDrive:
        jd = JointDrive(joint, self.image, self.source)
        command = joint.edge(Role.COMMAND)
        if command is not None and command.shared:
            shared = self._shared.get(jd.board)
            if shared is None:
                shared = self._shared[jd.board] = SharedCommand(
                    joint.board.model.command_off)
            jd.shared = shared
        self.drives[joint.node_id] = jd
        return jd

    @property
    def groups(self) -> list[tuple[CanopenBus, list[JointDrive]]]:
        return self._groups

    def start(self) -> Gateway:
        """Every node's boot-up on its bus, the runtimes' threads running."""
        try:
            for b, group in self._groups:
                ods = {jd.node_id: self._dictionaries.get(jd.node_id)
                       or dictionary.to_canopen(dictionary.build(jd.joint)) for jd in group}
                by_id = {jd.node_id: jd for jd in group}
                runtime = NodeRuntime(b.bus, ods, self._callbacks(len(self.runtimes),
                                                                  by_id), cycle=self.cycle)
                for jd in group:
                    jd.bind(runtime, self.image)
                self.runtimes.append(runtime)
                self._bus_faults[len(self.runtimes) - 1] = None
                runtime.start()
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        """Stop the nodes (they fall silent: a master's heartbeat consumer notices); what
        :meth:`serve` opened is closed too."""
        for runtime in self.runtimes:
            runtime.close()
        for closing in reversed(self._owned):
            closing()
        self._owned = []

    def __enter__(self) -> Gateway:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @classmethod
    def serve(cls, part: Any, canopen: Iterable[str], *, rate_hz: float = 500.0,
              cycle: float = 0.001) -> Gateway:
        """The gateway of a started :class:`~ucom_tools.ops.remote.RemotePart` in this
        process (the Python face of ``ucom gateway canopen``): ``canopen`` as
        ``--canopen`` takes them (``virtual:co`` for a master in this process too), the
        loop's snapshots at ``rate_hz``.  The part's loop must run (``part.run``,
        ``part.cycle()``); :meth:`close` (or ``with``) stops the nodes and closes the
        buses it opened."""
        from ucom_tools.gateway import buses as buses_mod
        from ucom_tools.gateway import joints as joints_mod
        from ucom_tools.ops.remote.feed import LocalRun

        topology = part.robot.topology
        if topology is None:
            raise InputError("the part's robot has no topology: the gateway finds its "
                             "joints there")
        specs = [buses_mod.parse(text) for text in canopen]
        buses_mod.check(specs, list(part.robot.buses))
        run = LocalRun(part, rate_hz)
        image = run.image
        if image is None:
            run.close()
            raise InputError("start the part first (part.start()): the gateway needs its "
                             "boards' edges")
        opened: list[tuple[buses_mod.CanopenSpec, can.BusABC]] = []
        try:
            for spec in specs:
                opened.append((spec, buses_mod.open_bus(spec)))
            gateway = cls(joints_mod.find(topology).joints, image, run,
                          [CanopenBus(bus, spec.text, spec.ucom_buses)
                           for spec, bus in opened], cycle=cycle)
        except BaseException:
            for _, bus in opened:
                bus.shutdown()
            run.close()
            raise
        gateway._owned = [run.close, *(bus.shutdown for _, bus in opened)]
        return gateway.start()

    # ------------------------------------------------------------ callbacks
    def _callbacks(self, number: int, by_id: dict[int, JointDrive]) -> NodeCallbacks:
        return _BusCallbacks(self, number, by_id).callbacks()

    def _master_event(self, number: int, event: str, reason: str) -> None:
        spec = self._groups[number][0].spec
        self.master_events.append((round(_now() - self._started, 4), spec, event, reason))
        if event == "lost":
            log.warning("%s: the CANopen master is gone (%s): its joints off, their nodes in "
                        "FAULT", spec, reason)
        else:
            log.info("%s: the CANopen master is back (%s); a fault reset clears FAULT", spec,
                     reason)

    # ------------------------------------------------------------ reporting
    def states(self) -> dict[int, State402]:
        """Each node's drive state now."""
        return {node: jd.drive.state for node, jd in self.drives.items()}

    def stats(self) -> dict[str, Any]:
        """``--json``'s ``gateway``: each CANopen bus's figures, each node's state."""
        out_buses = []
        for (b, group), runtime in zip(self._groups, self.runtimes, strict=False):
            st = runtime.stats()
            out_buses.append({
                "canopen": b.spec, "nodes": [jd.node_id for jd in group],
                "frames_in": st.frames_in, "frames_out": st.frames_out, "syncs": st.syncs,
                "send_errors": st.send_errors, "rpdo_errors": st.rpdo_errors,
                "sync_cpu_s": round(st.sync_cpu_s, 6),
                "thread_cpu_s": round(st.thread_cpu_s, 6),
                "master_lost": runtime.master_lost})
        nodes = []
        for node, jd in sorted(self.drives.items()):
            last = jd.last
            nodes.append({"node_id": node, "name": jd.joint.name, "bus": jd.board[0],
                          "board": jd.board[1], "state": jd.drive.state.text,
                          "statusword": None if last is None else last.statusword,
                          "error_code": None if last is None else last.error_code,
                          "nmt": runtime_state(self, node)})
        return {"buses": out_buses, "nodes": nodes,
                "master": [{"time": t, "canopen": spec, "event": event, "reason": reason}
                           for t, spec, event, reason in self.master_events]}


def dictionaries(joints: Iterable[Joint]) -> dict[int, ObjectDictionary]:
    """Every joint's object dictionary (before the boards run: about 3 ms a joint)."""
    return {j.node_id: dictionary.to_canopen(dictionary.build(j)) for j in joints}


def runtime_state(gateway: Gateway, node: int) -> str | None:
    runtime = gateway.drives[node].runtime
    return None if runtime is None else runtime.state(node).name


__all__ = ["CanopenBus", "Gateway", "JointDrive", "SharedCommand", "Source", "dictionaries"]


class _BusCallbacks:
    """What one CANopen bus's node runtime calls (:class:`NodeCallbacks`): its joints'
    drives run on writes, NMT changes, SYNCs and the runtime's turns, from the latest
    snapshot; the master's loss and return."""

    def __init__(self, gateway: Gateway, number: int, by_id: dict[int, JointDrive]) -> None:
        self.gateway, self.number, self.by_id = gateway, number, by_id
        self.group = tuple(by_id.values())
        self.wanted = frozenset().union(*(jd.so_wanted for jd in self.group))
        self.seen = -1  # the snapshot last observed
        self.syncs: list[float] = []  # SYNC times, for the rate's check
        self.told: tuple[bool, int, int] | None = None  # news() last said
        self.last_sync = -INF  # the latest SYNC ...
        self.sync_gap = INF  # ... and the time since the one before

    def callbacks(self) -> NodeCallbacks:
        return NodeCallbacks(on_write=self.on_write, on_state=self.on_state,
                             on_sync=self.on_sync, on_tick=self.on_tick,
                             master_lost=self.master_lost, master_back=self.master_back)

    @property
    def fault(self) -> DriveFault | None:
        return self.gateway._bus_faults[self.number]

    def on_write(self, node_id: int, index: int, subindex: int, value: Any) -> None:
        jd = self.by_id.get(node_id)
        if jd is None:
            return
        source = self.gateway.source
        now = jd.on_write(index, subindex, value, source.latest)
        if now is None:
            return
        if now or not self.gateway.runtimes[self.number].node(node_id).applying:
            # an SDO's at once (its effect in 0x6041 by its confirmation), a new
            # controlword's at once (no edge lost); other RPDO values at the SYNC that
            # applies them or the next turn (CSP's 0x607A every SYNC ran each drive twice
            # a SYNC)
            jd.update(_now(), source.latest, self.fault)

    def on_state(self, change: StateChange) -> None:
        jd = self.by_id.get(change.node_id)
        if jd is None:
            return
        if change.command in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION) \
                or change.new is NmtState.INITIALISING:
            jd.reset()
        elif change.new is NmtState.STOPPED:
            jd.drive.disable_voltage()
            jd.update(_now(), self.gateway.source.latest, self.fault)

    def observe(self) -> LoopSnapshot | None:
        """The latest snapshot, handed to every joint once."""
        snap = self.gateway.source.latest
        if snap is not None and snap.number != self.seen:
            self.seen = snap.number
            raws = self.gateway.image.raw_so(snap.values, self.wanted)
            for jd in self.group:
                jd.observe(snap, raws)
        return snap

    def check_rate(self, now: float) -> None:
        """Once the master's SYNC rate is known: warn where the PDOs it configured need
        more of the bus than it has (once a bus)."""
        syncs, gateway, number = self.syncs, self.gateway, self.number
        syncs.append(now)
        if len(syncs) < LOAD_SYNCS:
            return
        rate = (len(syncs) - 1) / (syncs[-1] - syncs[0]) if syncs[-1] > syncs[0] else 0.0
        syncs.clear()
        if rate <= 0 or number in gateway._load_warned:
            return
        runtime = gateway.runtimes[number]
        load = pdo_load([runtime.node(jd.node_id) for jd in self.group
                         if runtime.state(jd.node_id) is NmtState.OPERATIONAL], rate)
        share = load.worst_bits_per_s / CANOPEN_BITRATE
        if share > WARN_SHARE:
            gateway._load_warned.add(number)
            log.warning("%s: SYNC at %.0f Hz with these PDOs needs %.0f%% of a 1 Mbit/s bus "
                        "(every stuff bit counted): TPDOs will come late or not at all; map "
                        "fewer objects, put fewer joints on this bus or SYNC less often",
                        gateway._groups[number][0].spec, rate, share * 100)

    def synced(self, now: float) -> bool:
        """Do the master's SYNCs run the drives at least every :data:`IDLE_S` (a joint
        that moved waits for the next, as a CiA 402 drive samples at SYNC); not once one
        is overdue."""
        return self.sync_gap <= SYNCED_GAP_S and now - self.last_sync <= 1.5 * self.sync_gap

    def on_sync(self, counter: int | None) -> None:
        now = _now()
        self.sync_gap, self.last_sync = now - self.last_sync, now
        if self.number not in self.gateway._load_warned:
            self.check_rate(now)
        snap, fault = self.observe(), self.fault
        for jd in self.group:
            jd.update(now, snap, fault, sync=True)

    def on_tick(self, now: float) -> float | None:
        """The drives due.  Where SYNCs run the drives (each SYNC observes the latest
        snapshot too), the next turn when the next SYNC is overdue: the runtime wakes for
        the master's frames, not every cycle for nothing."""
        synced = self.synced(now)
        if synced and not self.news():  # the joints' new values wait for the SYNC
            snap = self.gateway.source.latest
        else:
            snap = self.observe()
        fault = self.fault
        for jd in self.group:
            if jd.due(now, synced):
                jd.update(now, snap, fault)
        return self.last_sync + 1.5 * self.sync_gap if synced else None

    def news(self) -> bool:
        """Has the latest snapshot news the drives take at once: the loop's end, the
        boards' events or faults (a board lost or back)."""
        snap = self.gateway.source.latest
        if snap is None or snap.number == self.seen:
            return False
        key = (snap.running, snap.events_total, snap.faults_total)
        if key == self.told:
            return False
        self.told = key
        return True

    def master_lost(self, reason: str) -> None:
        cause = (FaultCause.SYNC_TIMEOUT if "SYNC" in reason
                 else FaultCause.BUS_OFF if "bus" in reason.lower()
                 else FaultCause.MASTER_HEARTBEAT)
        self.gateway._bus_faults[self.number] = DriveFault(cause)
        self.gateway._master_event(self.number, "lost", reason)
        now, snap = _now(), self.gateway.source.latest
        for jd in self.group:
            jd.update(now, snap, self.fault)

    def master_back(self, reason: str) -> None:
        self.gateway._bus_faults[self.number] = None
        self.gateway._master_event(self.number, "back", reason)
