"""What ``--foxglove`` serves (:mod:`.foxglove`), as JSON text built from parts prepared
once: the topics, their JSON schemas (documented here and in ``man/ucom.1``, FOXGLOVE),
the messages, the clock they are stamped with and the robot's joints.  Nothing here
imports foxglove-sdk.

Topics (every message JSON, its schema inline in the server's advertisement):

- ``/<bus>/<board>/values`` (``ucom.BoardValues``): a board's values by robot-wide name
  (``Right Eye Joint Sensor``, ``Eyes/AD Channel 6``), with ``timestamp``, ``t`` (the
  bus time), ``valid`` (false while the board is lost: its last values);
- ``/joints`` (``foxglove.JointStates``): each joint (an axis whose Target its board's tree
  names, :mod:`ucom_tools.gateway.joints`) with its joint sensor as ``position`` and its
  velocity as ``velocity``, in the tree's units (counts, not radians);
- ``/<bus>/frames`` (``ucom.CanFrame``): every frame of the bus, one message each: ``id``,
  ``extended``, ``remote``, ``error``, ``direction`` (``rx`` from the boards, ``tx`` sent
  by the PC), ``dlc``, ``data`` (base64: Foxglove shows bytes), ``bus_time`` (seconds on
  the bus's time base, as ``--record``'s log has it) and ``timestamp``;
- ``/events`` (``foxglove.Log``): the run's events (boards' Errors, boards lost and
  rejoined, writes and stops, writes refused), for the Log panel.

Time: every ``timestamp`` (and each message's log time) is the frames' bus time mapped
once to the wall clock (:class:`WallClock`): values and frames share one time base.
The precision a JavaScript number keeps of epoch nanoseconds is too little; ``sec`` and
``nsec`` are apart for that reason.
"""

from __future__ import annotations

import binascii
import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final

from ucom_tools.errors import InputError
from ucom_tools.net.encode import Conv, conv_of, write
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.remote_image import PartImage
from ucom_tools.ops.remote_publish import LoopSnapshot
from ucom_tools.protocol.dispatch import ERROR, EXTENDED, REMOTE, SENT, SinkEntry
from ucom_tools.wire import mca

DEFAULT_HOST: Final = "127.0.0.1"
DEFAULT_PORT: Final = 8765
DEFAULT_ADDRESS: Final = f"{DEFAULT_HOST}:{DEFAULT_PORT}"
JOINTS_TOPIC: Final = "/joints"
EVENTS_TOPIC: Final = "/events"
SET_TOPIC: Final = "/set"
"""Where a client publishes a write (``{"name": NAME, "value": NUMBER}``)."""

LOG_INFO, LOG_WARNING, LOG_ERROR = 2, 3, 4
"""``foxglove.Log`` levels."""

_TIME: dict[str, Any] = {
    "type": "object", "title": "time",
    "properties": {"sec": {"type": "integer", "minimum": 0},
                   "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}}

FRAME_SCHEMA: Final[dict[str, Any]] = {
    "title": "ucom.CanFrame", "type": "object",
    "description": "One CAN frame of a UCoM bus as the PC saw it (sent or received)",
    "properties": {
        "timestamp": {**_TIME, "description": "The bus time mapped to the wall clock"},
        "bus_time": {"type": "number", "description": "Seconds on the bus's time base"},
        "bus": {"type": "string"},
        "id": {"type": "integer", "description": "Arbitration identifier"},
        "extended": {"type": "boolean"}, "remote": {"type": "boolean"},
        "error": {"type": "boolean"},
        "direction": {"type": "string", "enum": ["rx", "tx"],
                      "description": "rx: received by the PC; tx: sent by it"},
        "dlc": {"type": "integer", "minimum": 0, "maximum": 8},
        "data": {"type": "string", "contentEncoding": "base64"}}}

VALUES_SCHEMA: Final[dict[str, Any]] = {
    "title": "ucom.BoardValues", "type": "object",
    "description": "A board's edge values by robot-wide name",
    "properties": {
        "timestamp": _TIME, "t": {"type": "number", "description": "Bus time, seconds"},
        "bus": {"type": "string"}, "board": {"type": "integer"},
        "valid": {"type": "boolean", "description": "false: the board is lost"},
        "values": {"type": "object", "additionalProperties": {"type": "number"}}}}

JOINT_STATES_SCHEMA: Final[dict[str, Any]] = {
    "title": "foxglove.JointStates", "type": "object",
    "description": "The state of a set of joints at a given time",
    "properties": {
        "timestamp": _TIME,
        "joints": {"type": "array", "items": {
            "title": "foxglove.JointState", "type": "object",
            "properties": {"name": {"type": "string"}, "position": {"type": "number"},
                           "velocity": {"type": "number"}}}}}}

LOG_SCHEMA: Final[dict[str, Any]] = {
    "title": "foxglove.Log", "type": "object", "description": "A log message",
    "properties": {
        "timestamp": _TIME,
        "level": {"type": "integer", "description": "1 debug, 2 info, 3 warning, 4 error"},
        "message": {"type": "string"}, "name": {"type": "string"},
        "file": {"type": "string"}, "line": {"type": "integer", "minimum": 0}}}

SET_SCHEMA: Final[dict[str, Any]] = {
    "title": "ucom.Set", "type": "object",
    "description": "Set a CI or PAR edge (needs --allow-writes)",
    "properties": {"name": {"type": "string"}, "value": {"type": "number"}},
    "required": ["name", "value"]}


def values_topic(bus: str, board: int) -> str:
    return f"/{bus}/{board}/values"


def frames_topic(bus: str) -> str:
    return f"/{bus}/frames"


def parse_address(text: str, key: str = "--foxglove") -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:8765`` for IPv6) as (host, port); InputError naming
    ``key`` otherwise.  Port 0 takes any free one."""
    host, sep, port = text.rpartition(":")
    bracketed = host.startswith("[") and host.endswith("]")
    if bracketed:
        host = host[1:-1]
    if not sep or not host or not port.isdigit() or int(port) > 65535 or any(
            c.isspace() for c in host) or (":" in host and not bracketed):
        raise InputError(f"{text!r} is not HOST:PORT (a host name or address, a port "
                         f"0..65535; e.g. {DEFAULT_ADDRESS})", key=key)
    return host, int(port)


class WallClock:
    """The frames' bus time mapped once to the wall clock: the first :meth:`anchor` says
    which bus time is now; every time stamp after is that plus the same offset."""

    def __init__(self) -> None:
        self.offset: float | None = None

    def anchor(self, stamp: float, taken: float | None = None) -> None:
        """``stamp`` (bus time) was the moment ``taken`` (``time.monotonic()``; None:
        now); only the first call counts."""
        if self.offset is None:
            wall = time.time() - (0.0 if taken is None else time.monotonic() - taken)
            self.offset = wall - stamp

    def ns(self, stamp: float) -> int:
        """Nanoseconds since the Unix epoch of bus time ``stamp``."""
        return round((stamp + (self.offset or 0.0)) * 1e9)


def now_ns() -> int:
    """Now, in nanoseconds since the Unix epoch (an event of the server's own)."""
    return time.time_ns()


def time_json(ns: int) -> str:
    return f'{{"sec":{ns // 1_000_000_000},"nsec":{ns % 1_000_000_000}}}'


def _name(text: str) -> str:
    return json.dumps(text, ensure_ascii=False)


def frame_json(bus: str, entry: SinkEntry, ns: int) -> str:
    """One frame as its ``/<bus>/frames`` message (``bus``: already JSON text)."""
    ident, data, stamp, flags = entry
    return (f'{{"timestamp":{time_json(ns)},"bus_time":{stamp!r},"bus":{bus},'
            f'"id":{ident},"extended":{"true" if flags & EXTENDED else "false"},'
            f'"remote":{"true" if flags & REMOTE else "false"},'
            f'"error":{"true" if flags & ERROR else "false"},'
            f'"direction":"{"tx" if flags & SENT else "rx"}","dlc":{len(data)},'
            f'"data":"{binascii.b2a_base64(data, newline=False).decode()}"}}')


def log_json(ns: int, level: int, message: str, name: str = "ucom") -> str:
    """A ``foxglove.Log`` message."""
    return (f'{{"timestamp":{time_json(ns)},"level":{level},"message":{_name(message)},'
            f'"name":{_name(name)},"file":"","line":0}}')


# ---------------------------------------------------------------------- values
class BoardValues:
    """A board's ``/<bus>/<board>/values`` message from a snapshot (only its maps are
    unpacked: :meth:`PartImage.raw_so`)."""

    def __init__(self, image: PartImage, bus: str, board: int, refs: Sequence[EdgeRef]
                 ) -> None:
        self.bus, self.board = bus, board
        self.topic = values_topic(bus, board)
        names = image.names
        convs = {r: conv_of(r)[0] for r in refs}
        heads = {r: _name(names.name_of(r)) + ":" for r in refs}
        self._so = [(r, heads[r], convs[r]) for r in refs if r.kind is mca.Kind.SO]
        self._ci = [((board, r.index), heads[r], convs[r]) for r in refs
                    if r.kind is mca.Kind.CI]
        self._par = [(r, heads[r], convs[r]) for r in refs if r.kind is mca.Kind.PAR]
        self._wanted = frozenset(r for r, _, _ in self._so)
        self._maps = [m.number for m in image.so_maps(bus) if m.board == board]
        self._head = f'{{"bus":{_name(bus)},"board":{board},"timestamp":'

    def message(self, image: PartImage, snap: LoopSnapshot, clock: WallClock
                ) -> tuple[int, str]:
        """(log time in ns, the message's JSON)."""
        raw = snap.values
        so = image.raw_so(raw, self._wanted) if self._wanted else {}
        parts = [h + write(c, so[r]) for r, h, c in self._so if r in so]
        ci = raw.ci.get(self.bus, {})
        parts += [h + write(c, ci[k]) for k, h, c in self._ci if k in ci]
        parts += [h + write(c, raw.par[r]) for r, h, c in self._par if r in raw.par]
        stamps = raw.stamps.get(self.bus, {})
        seen = [stamps[n] for n in self._maps if n in stamps]
        t = max(seen) if seen else snap.stamp
        ns = clock.ns(t)
        valid = "false" if snap.stale(self.bus, self.board) else "true"
        return ns, (f'{self._head}{time_json(ns)},"t":{round(t, 6)!r},"valid":{valid},'
                    f'"values":{{{",".join(parts)}}}}}')


@dataclass(frozen=True)
class JointRefs:
    """A joint (an axis whose Target its board's tree names) and its edges."""

    name: str
    target: EdgeRef
    position: EdgeRef | None
    velocity: EdgeRef | None


def find_joints(refs: Sequence[EdgeRef]) -> list[JointRefs]:
    """The robot's joints among ``refs``, named as ``ucom gateway`` names them (the
    Target's robot-wide name without its suffix: "Right Eye"; where several boards have
    a joint of that name, the board's prefix in front: "FL/Alpha"); a board whose
    program is not one whose axes are joints (:data:`~ucom_tools.gateway.joints.MODELS`,
    recognised by its edges' generic names) has none."""
    from ucom_tools.gateway.joints import MODELS, Role

    boards: dict[tuple[str, int], dict[str, EdgeRef]] = {}
    for r in refs:
        boards.setdefault((r.bus, r.board), {})[r.generic] = r
    found: list[tuple[str, JointRefs]] = []
    for by_generic in boards.values():
        for model in MODELS.values():
            for axis in range(model.axes):
                target = by_generic.get(model.generic(Role.TARGET, axis) or "")
                if target is None or target.unique == target.generic:
                    continue  # not this program, or an axis its tree does not name
                name = target.unique
                if name.endswith(model.name_suffix) and len(name) > len(model.name_suffix):
                    name = name[:-len(model.name_suffix)].strip()
                found.append((target.prefix, JointRefs(
                    name, target, by_generic.get(model.generic(Role.JOINT_SENSOR, axis) or ""),
                    by_generic.get(model.generic(Role.VELOCITY, axis) or ""))))
    counts: dict[str, int] = {}
    for _, j in found:
        counts[j.name.casefold()] = counts.get(j.name.casefold(), 0) + 1
    return [j if counts[j.name.casefold()] == 1 else
            JointRefs(f"{prefix}/{j.name}", j.target, j.position, j.velocity)
            for prefix, j in found]


class JointStates:
    """The ``/joints`` message (``foxglove.JointStates``) from a snapshot."""

    def __init__(self, joints: Sequence[JointRefs]) -> None:
        def edge(ref: EdgeRef | None, field: str) -> tuple[EdgeRef, str, Conv] | None:
            if ref is None or ref.kind is not mca.Kind.SO:
                return None  # a joint's sensor and velocity are SO (what the board sends)
            return ref, f',"{field}":', conv_of(ref)[0]

        self._joints = [('{"name":' + _name(j.name), edge(j.position, "position"),
                         edge(j.velocity, "velocity")) for j in joints]
        self._wanted = frozenset(e[0] for _, *es in self._joints for e in es
                                 if e is not None)
        self.names = [j.name for j in joints]

    def message(self, image: PartImage, snap: LoopSnapshot, clock: WallClock
                ) -> tuple[int, str]:
        so = image.raw_so(snap.values, self._wanted)
        items = []
        for head, *edges in self._joints:
            items.append(head + "".join(f + write(c, so[r]) for e in edges if e is not None
                                        for r, f, c in (e,) if r in so) + "}")
        ns = clock.ns(snap.stamp)
        return ns, f'{{"timestamp":{time_json(ns)},"joints":[{",".join(items)}]}}'


def joint_states_of(values: dict[str, Any], joints: Sequence[JointRefs],
                    names: Any, ns: int) -> str:
    """The ``/joints`` message of decoded values by robot-wide name (``browse``)."""
    items = []
    for j in joints:
        doc: dict[str, Any] = {"name": j.name}
        for field, ref in (("position", j.position), ("velocity", j.velocity)):
            if ref is not None and names.name_of(ref) in values:
                doc[field] = values[names.name_of(ref)]
        items.append(json.dumps(doc, ensure_ascii=False, separators=(",", ":")))
    return f'{{"timestamp":{time_json(ns)},"joints":[{",".join(items)}]}}'


# ---------------------------------------------------------------------- events
class EventLines:
    """The run's events that came since the last snapshot, as (bus time, level, text):
    the boards' Errors, the writes and stops from outside, the boards lost and
    rejoined (as ``man/ucom-network.7``'s events, in words)."""

    def __init__(self) -> None:
        self._events = self._writes = self._faults = 0

    def of(self, snap: LoopSnapshot) -> list[tuple[float, int, str]]:
        out: list[tuple[float, int, str]] = []
        for e in snap.newer(snap.events, snap.events_total, self._events):
            out.append((snap.on_stamps(e.time), LOG_ERROR if e.stopped_motors
                        else LOG_WARNING, f"{e.where}: {e.code.name}: {e.text}"))
        for w in snap.newer(snap.writes, snap.writes_total, self._writes):
            what = "stop" if w.value == "stop" and not w.name else f"set {w.name} = {w.value}"
            out.append((snap.on_stamps(w.time), LOG_INFO if w.done else LOG_WARNING,
                        f"{what} from {w.origin}: {w.result}"))
        for f in snap.newer(snap.faults, snap.faults_total, self._faults):
            out.append((snap.on_stamps(f.time), LOG_ERROR if f.event == "lost" else LOG_INFO,
                        f.describe()))
        self._events, self._writes = snap.events_total, snap.writes_total
        self._faults = snap.faults_total
        return sorted(out, key=lambda e: e[0])
