"""One joint of the gateway at work (:mod:`ucom_tools.gateway.bridge`): its CANopen node,
its CiA 402 drive (:class:`~ucom_tools.gateway.cia402.Drive402`) and its board's edges in
the run, joined (:class:`JointDrive`); the drive's objects by index
(:data:`OBJECT_FIELDS`); a board's one Command edge shared by its joints
(:class:`SharedCommand`, LAURON-IV's Leg Mode).  Everything here runs on the thread of the
joint's CANopen bus (``ucom_tools.gateway.node``)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from typing import Any, Protocol

from canopen.sdo import SdoAbortedError

from ucom_tools.edgelists.armar3 import Command
from ucom_tools.edgelists.model import EdgeKind
from ucom_tools.errors import InputError, UcomError
from ucom_tools.gateway import dictionary
from ucom_tools.gateway.cia402 import Drive402
from ucom_tools.gateway.cia402_objects import (
    DriveConfig,
    DriveFault,
    DriveOutputs,
    FaultCause,
    JointReport,
    ObjectValues,
    State402,
)
from ucom_tools.gateway.codes import SdoAbort
from ucom_tools.gateway.joints import BoardEdge, Joint, Role
from ucom_tools.gateway.node import NodeRuntime
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.remote.image import PartImage
from ucom_tools.ops.remote.publish import LoopSnapshot
from ucom_tools.wire import mca
from ucom_tools.wire.codes import ErrorCode

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
        modes = int(dictionary.supported_modes(joint))
        self._modes = frozenset(m for bit, m in ((0x01, 1), (0x04, 3), (0x20, 6), (0x80, 8))
                                if modes & bit) | {0}
        """0x6060's values this joint takes (0x6502's modes, and no mode)."""
        self._out_names = {role: self._qualified_role(role) for role in (
            Role.COMMAND, Role.TARGET, Role.TARGET_VEL, Role.RESET_OFFSET, Role.RESET_PWM,
            Role.MAX_VELOCITY)}
        self._refs_by_name: dict[str, EdgeRef] = {}
        for role in self._out_names:
            ref = self._ref(names, role)
            if ref is not None:
                self._refs_by_name[ref.qualified] = ref
        self._sent: dict[str, int] = {}
        self._defaults = {self._qualified(e.unique): e.default for e in joint.board.edges}
        self._manufacturer: dict[int, BoardEdge] = {
            dictionary.manufacturer_index(e): e for e in joint.board.edges}
        self._so_refs: dict[int, EdgeRef] = {}
        for index, e in self._manufacturer.items():
            if e.kind is EdgeKind.SO:
                try:
                    self._so_refs[index] = names.resolve(self._qualified(e.unique))
                except UcomError:  # an edge the running part does not name
                    continue
        self.objects = self.config.defaults()
        self._dirty = True
        """The drive must run: a master's write, a reset, the board's events or faults."""
        self._moved = False
        """The joint's report changed (its position, velocity, answer): the drive runs at
        the next SYNC where a master sends them often enough, else at the next turn."""
        self._seen_snapshot = -1
        self._seeded = False
        self._stale = False
        self._last_update = -1.0
        self._report = JointReport()
        self._latched = False
        self._events_seen = 0
        self._faults_seen = 0
        self._event_faults: list[DriveFault] = []
        self._master: DriveFault | None = None
        self.last: DriveOutputs | None = None
        self.shared: SharedCommand | None = None
        """The board's Command edge where all its joints share it (LAURON-IV)."""

    def _qualified(self, unique: str) -> str:
        """``Prefix/unique``: the part's name of an edge of this joint's board, one board
        whatever other boards call their edges (each LAURON-IV leg has an "Alpha")."""
        return f"{self.joint.board.prefix}/{unique}"

    def _qualified_role(self, role: Role) -> str | None:
        unique = self.joint.unique(role)
        return None if unique is None else self._qualified(unique)

    def _ref(self, names: Any, role: Role) -> EdgeRef | None:
        """The running part's edge in ``role`` (None where the program has none or the
        part does not name it)."""
        name = self._qualified_role(role)
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
        serial = image.serials.get(self.board)
        if serial is not None:  # the board's own, where the topology names none
            runtime.set(self.node_id, 0x1018, 4, serial & 0xFFFFFFFF)
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
                 ) -> bool | None:
        """A master's write of an application object: None where it is not the drive's;
        else the drive is due, and True where it must run before the next write can come
        (a new controlword: each of its edges counts, a fault reset's above all), False
        where its next turn will do.  Raises ``SdoAbortedError`` to refuse it (SDO
        only)."""
        field = OBJECT_FIELDS.get((index, subindex))
        if field is not None:
            if index == 0x6060 and int(value) not in self._modes:
                raise SdoAbortedError(SdoAbort.VALUE_RANGE)  # (an RPDO's: not taken)
            changed = index == 0x6040 and int(value) != self.objects.controlword
            self.objects = replace(self.objects, **{field: int(value)})
            self._dirty = True
            return changed
        edge = self._manufacturer.get(index)
        if edge is None or edge.kind is EdgeKind.SO or subindex:
            return None
        if snap is not None and snap.stale(*self.board):
            raise SdoAbortedError(SdoAbort.DEVICE_STATE)
        name = self._qualified(edge.unique)
        self._send([(name, int(value))])
        self._sent[name] = int(value)
        return None

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
            self._moved = True
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
            if raw is None:  # a PAR the run wrote at the start: the tree's value
                raw = self._defaults.get(name)
            if raw is not None:
                self._sent[name] = raw
                if self.shared is not None and name == self._out_names.get(Role.COMMAND):
                    self.shared.sent = raw

    def due(self, now: float, synced: bool = False) -> bool:
        """Is an update due: a write, a reset or the board's events and faults changed;
        or, unless ``synced`` (a master's SYNCs run the drive at least every
        :data:`IDLE_S`, :func:`~ucom_tools.gateway.bridge` knows), the joint's report
        changed or the state has time-based rules and :data:`IDLE_S` passed."""
        return self._dirty or (not synced and (
            self._moved or (self.drive.state in _TIMED
                            and now - self._last_update >= IDLE_S)))

    def faults(self, snap: LoopSnapshot | None, bus_fault: DriveFault | None) -> list[DriveFault]:
        """The causes of FAULT present now (levels) and newly come (events)."""
        out: list[DriveFault] = []
        if bus_fault is not None:
            out.append(bus_fault)
        if snap is None:
            return out
        lost = snap.lost.get(self.board)
        self._stale = lost is not None
        if lost is not None:  # detail: when it was lost (ms into the exchange), one
            ms = max(0, int(lost.since * 1000))  # value for the whole loss: one EMCY
            out.append(DriveFault(FaultCause.BOARD_LOST, detail=min(ms, 0xFFFFFFFF)))
        if snap.events_total != self._events_seen:
            for event in LoopSnapshot.newer(snap.events, snap.events_total,
                                            self._events_seen):
                if (event.bus, event.board) == self.board:
                    self._event_faults.append(DriveFault(FaultCause.BOARD_ERROR,
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
            out.append(DriveFault(FaultCause.BOARD_LATCHED))
        if self._event_faults:
            out.extend(self._event_faults)
            self._event_faults = []
        return out

    def update(self, now: float, snap: LoopSnapshot | None, bus_fault: DriveFault | None, *,
               sync: bool = False) -> DriveOutputs:
        """Run the drive: its objects into the node, its EMCYs out, its edges to the loop."""
        runtime = self.runtime
        assert runtime is not None
        faults = self.faults(snap, bus_fault)
        out = self.drive.update(now, self.objects, self._report, faults, sync=sync)
        self._dirty = self._moved = False
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
            if name is None or value is None:
                continue
            if role is Role.COMMAND and self.shared is not None:
                value = self.shared.want(self.node_id, value)
                sent = self.shared.sent
                self.shared.sent = value
            else:
                sent = self._sent.get(name)
                self._sent[name] = value
            if sent != value:
                items.append((name, value))
        if items:
            self._send(items)


class SharedCommand:
    """A board's one Command edge for all its joints (LAURON-IV's ``Leg Mode``): off only
    while every joint of the board asks for off, else the mode the joint that last asked
    for one (other than off) wants: an enabled joint is never switched off by its
    neighbour's drive, and the leg runs one mode at a time."""

    def __init__(self, off: int) -> None:
        self.off = off
        self.sent: int | None = None
        """What the board has (as the gateway last sent it, or seeded)."""
        self._wants: dict[int, int] = {}
        self._last: int | None = None

    def want(self, node: int, value: int) -> int:
        """Node ``node`` asks for ``value``; the value the edge is to have."""
        if value != self.off and self._wants.get(node) != value:
            self._last = node
        self._wants[node] = value
        on = [n for n, v in self._wants.items() if v != self.off]
        if not on:
            return self.off
        return self._wants[self._last if self._last in on else on[-1]]


__all__ = ["IDLE_S", "OBJECT_FIELDS", "JointDrive", "SharedCommand", "Source", "drive_config"]
