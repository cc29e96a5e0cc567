"""The gateway at work (``ucom gateway canopen``): every joint of a running robot a CiA 402
drive on a CANopen bus, between the run time's hand-over and the CANopen node runtime.

One :class:`JointDrive` per joint joins its node (:mod:`ucom_tools.gateway.node`, on
canopen's ``LocalNode``) to its drive (:class:`~ucom_tools.gateway.cia402.Drive402`) and
to its board's edges in the run (:class:`Source`: the loop's snapshots and its
:meth:`~Source.drive` writes; in the loop's process a ``LocalRun``, in the consumers'
process a ``Mirror``).  :class:`Gateway` makes one node runtime per CANopen bus, each
with its own thread; a joint's drive runs only on its bus's thread:

- a master's write of a drive object (SDO or RPDO) updates the joint's
  :class:`~ucom_tools.gateway.cia402_objects.ObjectValues` and runs the drive at once;
- a SYNC runs every drive of the bus (CSP takes 0x607A) before the TPDOs are built;
- once a cycle, a drive runs again where a newer snapshot came, a write is pending or
  its time-based rules (windows, homing, the quick stop's brake) may have moved on
  (every :data:`IDLE_S` at least);
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
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from functools import partial
from typing import Any, Protocol

import can
from canopen import ObjectDictionary
from canopen.sdo import SdoAbortedError

from ucom_tools.edgelists.armar3 import Command
from ucom_tools.edgelists.model import EdgeKind
from ucom_tools.errors import InputError, UcomError
from ucom_tools.gateway import dictionary
from ucom_tools.gateway.cia402 import Drive402
from ucom_tools.gateway.cia402_objects import (
    DriveConfig,
    DriveOutputs,
    Fault,
    FaultCause,
    JointReport,
    ObjectValues,
    State402,
)
from ucom_tools.gateway.codes import NmtCommand, NmtState, SdoAbort, StateChange
from ucom_tools.gateway.joints import BoardEdge, Joint, Role
from ucom_tools.gateway.node import NodeCallbacks, NodeRuntime
from ucom_tools.gateway.pdo import compile_pdos, find
from ucom_tools.gateway.slave import SlaveNode
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.remote_image import PartImage
from ucom_tools.ops.remote_publish import LoopSnapshot
from ucom_tools.protocol.plan import Load
from ucom_tools.wire import mca
from ucom_tools.wire.canbits import unstuffed_bits, worst_frame_bits
from ucom_tools.wire.codes import ErrorCode

log = logging.getLogger("ucom.gateway")

IDLE_S = 0.01
"""The longest a drive in a state with time-based rules (:data:`_TIMED`: windows,
homing, the quick stop's brake, the fault reaction) goes without an update."""
_TIMED = frozenset((State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE,
                    State402.FAULT_REACTION_ACTIVE))

OBJECT_FIELDS: Mapping[tuple[int, int], str] = {
    (0x6040, 0): "controlword", (0x6060, 0): "modes_of_operation",
    (0x607A, 0): "target_position", (0x60FF, 0): "target_velocity",
    (0x6081, 0): "profile_velocity", (0x6067, 0): "position_window",
    (0x6068, 0): "position_window_time", (0x606D, 0): "velocity_window",
    (0x606E, 0): "velocity_window_time", (0x606F, 0): "velocity_threshold",
    (0x6070, 0): "velocity_threshold_time", (0x6065, 0): "following_error_window",
    (0x6066, 0): "following_error_time_out", (0x605A, 0): "quick_stop_option",
    (0x6098, 0): "homing_method", (0x607C, 0): "home_offset",
    (0x607D, 1): "min_position_limit", (0x607D, 2): "max_position_limit",
}
"""The drive's objects (:class:`ObjectValues`' fields) by index and sub-index."""


class Source(Protocol):
    """The run as the gateway sees it: ``LocalRun`` in the loop's process, ``Mirror`` in
    the consumers' process."""

    @property
    def latest(self) -> LoopSnapshot | None: ...

    def drive(self, items: list[tuple[str, int]]) -> None: ...


@dataclass(frozen=True)
class CanopenBus:
    """One CANopen bus of the gateway: its python-can bus and the UCoM buses whose joints
    it carries (empty: every joint not on another)."""

    bus: can.BusABC
    spec: str
    """As given (``socketcand:CO0@127.0.0.1:29536``), for messages."""
    ucom_buses: tuple[str, ...] = ()


def drive_config(joint: Joint) -> DriveConfig:
    """A joint's :class:`DriveConfig`: its tree's values and its edges' ranges."""
    def edge(role: Role) -> BoardEdge | None:
        return joint.edge(role)

    def rng(role: Role, fallback: tuple[int, int]) -> tuple[int, int]:
        e = edge(role)
        return fallback if e is None else (e.spec.minimum, e.spec.maximum)

    def default(role: Role, fallback: int) -> int:
        e = edge(role)
        return fallback if e is None else e.default

    base = DriveConfig()
    scale = joint.board.model.velocity_scale
    vmax = default(Role.MAX_VELOCITY, 1)
    return DriveConfig(
        max_velocity=max(0, vmax * scale // 1000) if scale != 1000 else vmax,
        min_position=default(Role.MIN_POSITION, base.min_position),
        max_position=default(Role.MAX_POSITION, base.max_position),
        reset_offset=default(Role.RESET_OFFSET, 0), reset_pwm=default(Role.RESET_PWM, 0),
        target_range=rng(Role.TARGET, base.target_range),
        target_vel_range=rng(Role.TARGET_VEL, base.target_vel_range),
        reset_offset_range=rng(Role.RESET_OFFSET, base.reset_offset_range),
        max_velocity_range=base.max_velocity_range,
        reset_pwm_range=rng(Role.RESET_PWM, base.reset_pwm_range))


class JointDrive:
    """One joint: its node, its drive and its board's edges (see the module docstring).
    Everything runs on its bus's runtime thread."""

    def __init__(self, joint: Joint, image: PartImage, source: Source) -> None:
        self.joint = joint
        self._image = image
        self._source = source
        self.node_id = joint.node_id
        self.config = drive_config(joint)
        self.drive = Drive402(self.config)
        self.runtime: NodeRuntime | None = None
        self._send = source.drive
        names = image.names
        target = self._ref(names, Role.TARGET)
        if target is None:
            raise InputError(f"{joint.name}: the running part has no edge "
                             f"'{joint.unique(Role.TARGET)}' (is {joint.where} running its "
                             "tree's program?)")
        self.board = (target.bus, target.board)
        self._position = self._ref(names, Role.JOINT_SENSOR)
        self._velocity = self._ref(names, Role.VELOCITY)
        self._answer = self._ref(names, Role.RESET_ANSWER)
        self.so_wanted = frozenset(r for r in (self._position, self._velocity, self._answer)
                                   if r is not None)
        model = joint.board.model
        self._commands = {Command.OFF: model.command_off,
                          Command.POSITION: model.command_position,
                          Command.VELOCITY: model.command_velocity,
                          Command.HOMING: model.command_homing}
        self._vscale = model.velocity_scale
        self._out_names = {role: joint.unique(role) for role in (
            Role.COMMAND, Role.TARGET, Role.TARGET_VEL, Role.RESET_OFFSET, Role.RESET_PWM,
            Role.MAX_VELOCITY)}
        self._refs_by_name: dict[str, EdgeRef] = {}
        for role in self._out_names:
            ref = self._ref(names, role)
            if ref is not None:
                self._refs_by_name[ref.unique] = ref
        self._sent: dict[str, int] = {}
        self._manufacturer: dict[int, BoardEdge] = {
            dictionary.manufacturer_index(e): e for e in joint.board.edges}
        self._so_refs: dict[int, EdgeRef] = {}
        for index, e in self._manufacturer.items():
            if e.kind is EdgeKind.SO:
                try:
                    self._so_refs[index] = names.resolve(e.unique)
                except UcomError:  # an edge the running part does not name
                    continue
        self.objects = self.config.defaults()
        self._dirty = True
        self._seen_snapshot = -1
        self._seeded = False
        self._stale = False
        self._last_update = -1.0
        self._report = JointReport()
        self._latched = False
        self._events_seen = 0
        self._faults_seen = 0
        self._event_faults: list[Fault] = []
        self._master: Fault | None = None
        self.last: DriveOutputs | None = None
        self.lost_for_writes = False

    def _ref(self, names: Any, role: Role) -> EdgeRef | None:
        """The running part's edge in ``role`` (None where the program has none or the
        part does not name it)."""
        name = self.joint.unique(role)
        if name is None:
            return None
        try:
            ref: EdgeRef = names.resolve(name)
        except UcomError:
            return None
        return ref

    # ------------------------------------------------------------ set up
    def bind(self, runtime: NodeRuntime, image: PartImage) -> None:
        """Join the node: the drive's objects as the dictionary has them now."""
        self.runtime = runtime
        node = runtime.node(self.node_id)
        node.local.add_read_callback(self._read)
        self.objects = self._objects_from(node)

    def _objects_from(self, node: Any) -> ObjectValues:
        values: dict[str, int] = {}
        defaults = self.config.defaults()
        for (index, sub), name in OBJECT_FIELDS.items():
            try:
                values[name] = int(node.get(index, sub))
            except Exception:  # not in this joint's dictionary: the drive's default
                values[name] = getattr(defaults, name)
        return ObjectValues(**values)

    def reset(self) -> None:
        """A reset node / reset communication: a new drive, the objects as stored now."""
        self.drive = Drive402(self.config)
        if self.runtime is not None:
            self.objects = self._objects_from(self.runtime.node(self.node_id))
        self._dirty = True

    # ------------------------------------------------------------ the master's writes
    def on_write(self, index: int, subindex: int, value: Any, snap: LoopSnapshot | None
                 ) -> bool:
        """A master's write of an application object; True when the drive should run now.
        Raises ``SdoAbortedError`` to refuse it (SDO only)."""
        field = OBJECT_FIELDS.get((index, subindex))
        if field is not None:
            self.objects = replace(self.objects, **{field: int(value)})
            self._dirty = True
            return True
        edge = self._manufacturer.get(index)
        if edge is None or edge.kind is EdgeKind.SO or subindex:
            return False
        if snap is not None and snap.stale(*self.board):
            raise SdoAbortedError(SdoAbort.DEVICE_STATE)
        self._send([(edge.unique, int(value))])
        self._sent[edge.unique] = int(value)
        return False

    def _read(self, index: int, subindex: int, od: Any) -> int | None:
        """canopen's read callback: an SO edge from the latest snapshot."""
        ref = self._so_refs.get(index)
        if ref is None or subindex:
            return None
        snap = self._source.latest
        if snap is None:
            return None
        return self._image.raw_so(snap.values, frozenset((ref,))).get(ref)

    # ------------------------------------------------------------ running
    def observe(self, snap: LoopSnapshot, raws: Mapping[EdgeRef, int]) -> None:
        """A new snapshot (``raws``: its SO values the group reads): the joint's report
        and its board's state; the drive is due where either changed."""
        self._seen_snapshot = snap.number
        if not self._seeded:
            self._seed(snap)
        position = raws.get(self._position) if self._position is not None else None
        velocity = raws.get(self._velocity, 0) if self._velocity is not None else 0
        answer = raws.get(self._answer, 0) if self._answer is not None else 0
        valid = snap.running and position is not None and not snap.stale(*self.board)
        report = JointReport(self._report.position if position is None else position,
                             velocity, valid, answer)
        if report != self._report:
            self._report = report
            self._dirty = True
        if (snap.events_total != self._events_seen or snap.faults_total != self._faults_seen
                or snap.stale(*self.board) != self._stale):
            self._dirty = True

    def _seed(self, snap: LoopSnapshot) -> None:
        """What the board has now of the edges the drive sets: sent only where it differs."""
        self._seeded = True
        values = snap.values
        for name in self._out_names.values():
            if name is None:
                continue
            ref = self._refs_by_name.get(name)
            if ref is None:
                continue
            raw = (values.ci.get(ref.bus, {}).get((ref.board, ref.index))
                   if ref.kind is mca.Kind.CI else values.par.get(ref))
            if raw is not None:
                self._sent[name] = raw

    def due(self, now: float) -> bool:
        """Is an update due: something changed, or the state has time-based rules and
        :data:`IDLE_S` passed."""
        return self._dirty or (self.drive.state in _TIMED and
                               now - self._last_update >= IDLE_S)

    def faults(self, snap: LoopSnapshot | None, bus_fault: Fault | None) -> list[Fault]:
        """The causes of FAULT present now (levels) and newly come (events)."""
        out: list[Fault] = []
        if bus_fault is not None:
            out.append(bus_fault)
        if snap is None:
            return out
        lost = snap.lost.get(self.board)
        self._stale = lost is not None
        if lost is not None:
            ms = max(0, int((snap.clock - snap.figures.started_clock - lost.since) * 1000))
            out.append(Fault(FaultCause.BOARD_LOST, detail=min(ms, 0xFFFFFFFF)))
        if snap.events_total != self._events_seen:
            for event in LoopSnapshot.newer(snap.events, snap.events_total,
                                            self._events_seen):
                if (event.bus, event.board) == self.board:
                    self._event_faults.append(Fault(FaultCause.BOARD_ERROR,
                                                    code=int(event.code) & 0x7F))
                    if event.code is ErrorCode.WATCHDOG:
                        self._latched = True
            self._events_seen = snap.events_total
        if snap.faults_total != self._faults_seen:
            for fault in LoopSnapshot.newer(snap.faults, snap.faults_total,
                                            self._faults_seen):
                if (fault.bus, fault.board) == self.board and fault.event == "rejoined":
                    self._latched = False
                    self._sent.clear()  # the board has the run time's values now
                    self._seeded = False
            self._faults_seen = snap.faults_total
        if self._latched:
            out.append(Fault(FaultCause.BOARD_LATCHED))
        if self._event_faults:
            out.extend(self._event_faults)
            self._event_faults = []
        return out

    def update(self, now: float, snap: LoopSnapshot | None, bus_fault: Fault | None, *,
               sync: bool = False) -> DriveOutputs:
        """Run the drive: its objects into the node, its EMCYs out, its edges to the loop."""
        runtime = self.runtime
        assert runtime is not None
        faults = self.faults(snap, bus_fault)
        out = self.drive.update(now, self.objects, self._report, faults, sync=sync)
        self._dirty = False
        self._last_update = now
        node, report, last = self.node_id, self._report, self.last
        if last is None or last.statusword != out.statusword:
            runtime.set(node, 0x6041, 0, out.statusword)
        if last is None or last.mode_display != out.mode_display:
            runtime.set(node, 0x6061, 0, out.mode_display)
        if last is None or last.error_code != out.error_code:
            runtime.set(node, 0x603F, 0, out.error_code)
        runtime.set(node, 0x6064, 0, report.position)
        runtime.set(node, 0x606C, 0, report.velocity)
        for emcy in out.emcys:
            runtime.emcy(node, emcy.code, emcy.register, emcy.data)
        if snap is not None and not self._stale:
            self._hand_over(out)
        self.last = out
        return out

    def _hand_over(self, out: DriveOutputs) -> None:
        """The axis's edges that changed, to the loop."""
        names = self._out_names
        items: list[tuple[str, int]] = []
        command = self._commands.get(out.command)
        wanted = ((Role.COMMAND, command), (Role.TARGET, out.target),
                  (Role.TARGET_VEL, out.target_vel), (Role.RESET_OFFSET, out.reset_offset),
                  (Role.RESET_PWM, out.reset_pwm if out.command == Command.HOMING else None),
                  (Role.MAX_VELOCITY, out.max_velocity * 1000 // self._vscale))
        for role, value in wanted:
            name = names.get(role)
            if name is None or value is None or self._sent.get(name) == value:
                continue
            items.append((name, value))
            self._sent[name] = value
        if items:
            self._send(items)


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
        self._bus_faults: dict[int, Fault | None] = {}
        self._dictionaries = dict(dictionaries or {})
        """Node ID -> its dictionary where already built (:func:`dictionaries`)."""
        joints = list(joints)
        buses = list(buses)
        assigned: set[str] = set()
        for b in buses:
            assigned.update(b.ucom_buses)
        for b in buses:
            mine = [j for j in joints if (j.bus in b.ucom_buses if b.ucom_buses
                                          else j.bus not in assigned)]
            if mine:
                group = [self._joint(j) for j in mine]
                self._groups.append((b, group))
        self.master_events: list[tuple[int, str, str]] = []
        """(CANopen bus number, 'lost' or 'back', why) as the master watches said."""

    def _joint(self, joint: Joint) -> JointDrive:
        jd = JointDrive(joint, self.image, self.source)
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
        for runtime in self.runtimes:
            runtime.close()

    def final(self, snap: LoopSnapshot | None) -> None:
        """The run ended: every joint's last update (its FAULT and EMCY where its board
        was lost) before the nodes fall silent."""
        del snap  # each runtime thread runs its drives once more at its next tick

    # ------------------------------------------------------------ callbacks
    def _callbacks(self, number: int, by_id: dict[int, JointDrive]) -> NodeCallbacks:
        group = tuple(by_id.values())
        source, image = self.source, self.image
        wanted = frozenset().union(*(jd.so_wanted for jd in group))
        seen = [-1]

        def on_write(node_id: int, index: int, subindex: int, value: Any) -> None:
            jd = by_id.get(node_id)
            if jd is not None and jd.on_write(index, subindex, value, source.latest):
                jd.update(_now(), source.latest, self._bus_faults[number])

        def on_state(change: StateChange) -> None:
            jd = by_id.get(change.node_id)
            if jd is None:
                return
            if change.command in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION) \
                    or change.new is NmtState.INITIALISING:
                jd.reset()
            elif change.new is NmtState.STOPPED:
                jd.drive.disable_voltage()
                jd.update(_now(), source.latest, self._bus_faults[number])

        def observe() -> LoopSnapshot | None:
            snap = source.latest
            if snap is not None and snap.number != seen[0]:
                seen[0] = snap.number
                raws = image.raw_so(snap.values, wanted)
                for jd in group:
                    jd.observe(snap, raws)
            return snap

        def on_sync(counter: int | None) -> None:
            snap, now, fault = observe(), _now(), self._bus_faults[number]
            for jd in group:
                jd.update(now, snap, fault, sync=True)

        def on_tick(now: float) -> None:
            snap, fault = observe(), self._bus_faults[number]
            for jd in group:
                if jd.due(now):
                    jd.update(now, snap, fault)

        def master_lost(reason: str) -> None:
            cause = (FaultCause.SYNC_TIMEOUT if "SYNC" in reason
                     else FaultCause.BUS_OFF if "bus" in reason.lower()
                     else FaultCause.MASTER_HEARTBEAT)
            self._bus_faults[number] = Fault(cause)
            self.master_events.append((number, "lost", reason))
            now, snap = _now(), source.latest
            for jd in group:
                jd.update(now, snap, self._bus_faults[number])

        def master_back(reason: str) -> None:
            self._bus_faults[number] = None
            self.master_events.append((number, "back", reason))

        return NodeCallbacks(on_write=on_write, on_state=on_state, on_sync=on_sync,
                             on_tick=on_tick, master_lost=master_lost,
                             master_back=master_back)

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
        return {"buses": out_buses, "nodes": nodes}


def dictionaries(joints: Iterable[Joint]) -> dict[int, ObjectDictionary]:
    """Every joint's object dictionary (before the boards run: about 3 ms a joint)."""
    return {j.node_id: dictionary.to_canopen(dictionary.build(j)) for j in joints}


def runtime_state(gateway: Gateway, node: int) -> str | None:
    runtime = gateway.drives[node].runtime
    return None if runtime is None else runtime.state(node).name


def _now() -> float:
    import time
    return time.monotonic()


def pdo_load(nodes: Iterable[ObjectDictionary | SlaveNode], rate_hz: float, *,
             sync_counter: bool = False) -> Load:
    """What a group of nodes' enabled PDOs and the SYNC put on their CANopen bus at
    ``rate_hz`` SYNCs a second, counted as ``remote`` counts a UCoM bus's load (per
    second; ``worst_bits_per_s / bitrate`` is the share of the bus with every stuff bit
    a frame can need): the SYNC (1 byte with ``sync_counter``), each synchronous TPDO
    every n-th SYNC (type n; type 0 every SYNC), each RPDO and each event-driven TPDO
    once a SYNC (a master that writes every SYNC, values that change every SYNC).
    Heartbeats, EMCYs and SDO are not counted.  Each node's PDOs as its dictionary
    stores them, or a :class:`SlaveNode`'s as its master has configured them."""
    frames: list[tuple[int, float]] = [(1 if sync_counter else 0, 1.0)]  # (bytes, a SYNC)
    for n in nodes:
        od, read = (n.od, n.read) if isinstance(n, SlaveNode) else (n, partial(_stored, n))
        tpdos, rpdos = compile_pdos(od, read, lambda i, sub, size: {sub: bytes(size)},
                                    int(getattr(od, "node_id", 0) or 0))
        for t in tpdos:
            every = t.trans_type if t.trans_type <= 240 else 1
            frames.append((sum(e.bits for e in t.entries) // 8, 1.0 / max(1, every)))
        frames += [(r.length, 1.0) for r in rpdos]
    return Load(rate_hz * sum(k for _, k in frames),
                rate_hz * sum(k * unstuffed_bits(size) for size, k in frames),
                rate_hz * sum(k * worst_frame_bits(size) for size, k in frames))


def _stored(od: ObjectDictionary, index: int, subindex: int) -> int:
    var = find(od, index, subindex)
    return int((var.value if var.value is not None else var.default) or 0)


__all__ = ["IDLE_S", "OBJECT_FIELDS", "CanopenBus", "Gateway", "JointDrive", "Source",
           "dictionaries", "drive_config", "pdo_load"]
