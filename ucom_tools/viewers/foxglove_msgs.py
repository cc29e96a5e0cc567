"""What ``--foxglove`` serves (:mod:`.foxglove`): the channels, schemas and messages of
an MCAP recording of the run (:mod:`ucom_tools.trace.mcapfile`,
:mod:`ucom_tools.trace.mcap_record`; ``ucom(1)``, MCAP RECORDINGS), built here from
the loop's snapshots and frames as they come, so that a layout made for a recording
shows the robot live and the other way round.  Nothing here imports foxglove-sdk.

Topics: each board's values (``/<Prefix>/values``, ``ucom.Values.<Prefix>``: ``time``,
``valid`` and each edge's value under its robot-wide name made a message-path field:
``Right_Eye_Joint_Sensor``), ``/joints`` (``foxglove.JointStates``), each bus's frames
(``/<bus>/frames``, ``ucom.CanFrame``), ``/events`` (``foxglove.Log``), and what a client
may publish: ``/set`` (``ucom.Set``, a write).

Time: every log time is the frames' bus time mapped once to the wall clock
(:class:`WallClock`, :func:`~ucom_tools.trace.mcapfile.wall_offset`): values, joints and
frames share one time base, as in a recording.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final

from ucom_tools.errors import InputError
from ucom_tools.net.encode import Conv, conv_of, write
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.remote.image import PartImage
from ucom_tools.ops.remote.publish import LoopSnapshot
from ucom_tools.protocol.traffic import SinkEntry
from ucom_tools.trace import mcapfile
from ucom_tools.trace.mcap_record import Board, joints_of, layout, values_schema
from ucom_tools.trace.mcapfile import (
    EVENTS_TOPIC,
    FRAME_SCHEMA,
    JOINTS_SCHEMA,
    JOINTS_TOPIC,
    LOG_LEVELS,
    LOG_SCHEMA,
    frames_topic,
    wall_offset,
)
from ucom_tools.wire import mca

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey

DEFAULT_HOST: Final = "127.0.0.1"
DEFAULT_PORT: Final = 8765
DEFAULT_ADDRESS: Final = f"{DEFAULT_HOST}:{DEFAULT_PORT}"
SET_TOPIC: Final = "/set"
"""Where a client publishes a write (``{"name": NAME, "value": NUMBER}``)."""

LOG_INFO, LOG_WARNING, LOG_ERROR = (LOG_LEVELS[k] for k in ("info", "warning", "error"))
"""``foxglove.Log`` levels."""

SET_SCHEMA: Final[dict[str, Any]] = {
    "title": "ucom.Set", "type": "object",
    "description": "Set a CI or PAR edge by its robot-wide name: publish it on /set "
                   "(the run needs --allow-writes); the server's /set carries each write "
                   "it applied",
    "properties": {"name": {"type": "string"}, "value": {"type": "number"}},
    "required": ["name", "value"]}


def parse_address(text: str, key: str = "foxglove") -> tuple[str, int]:
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
        now); only the first call counts (a bus time base within a second of the wall
        clock is taken as the wall clock, as a recording does)."""
        if self.offset is None:
            wall = time.time() - (0.0 if taken is None else time.monotonic() - taken)
            self.offset = wall_offset(stamp, wall)

    def ns(self, stamp: float) -> int:
        """Nanoseconds since the Unix epoch of bus time ``stamp``."""
        return round((stamp + (self.offset or 0.0)) * 1e9)


def now_ns() -> int:
    """Now, in nanoseconds since the Unix epoch (an event of the server's own)."""
    return time.time_ns()


def time_json(ns: int) -> str:
    return mcapfile.stamp_json(ns)


frame_json: Callable[[SinkEntry], bytes] = mcapfile.entry_json
"""One frame as its ``/<bus>/frames`` message (:data:`FRAME_SCHEMA`): a recording's."""


def log_json(ns: int, level: int, message: str, name: str = "ucom") -> str:
    """A ``foxglove.Log`` message."""
    return (f'{{"timestamp":{time_json(ns)},"level":{level},"message":{json.dumps(message)},'
            f'"name":{json.dumps(name)},"file":"","line":0}}')


# ---------------------------------------------------------------------- values
class BoardValues:
    """A board's values message (``{"time", "valid", <key>: value ...}``, as a recording
    has it) from a snapshot: only its maps are unpacked (:meth:`PartImage.raw_so`)."""

    def __init__(self, image: PartImage, board: Board) -> None:
        self.bus, self.board = board.bus, board.board
        self.topic = board.topic
        self.schema = values_schema(board)
        keys = {r: f'"{k}":' for k, r in zip(board.keys, board.edges, strict=True)}
        refs: list[EdgeRef] = list(board.edges)
        self._so = [(r, keys[r], conv_of(r)[0]) for r in refs if r.kind is mca.Kind.SO]
        self._ci = [((r.board, r.index), keys[r], conv_of(r)[0]) for r in refs
                    if r.kind is mca.Kind.CI]
        self._par = [(r, keys[r], conv_of(r)[0]) for r in refs if r.kind is mca.Kind.PAR]
        self._wanted = frozenset(r for r, _, _ in self._so)
        self._maps = [m.number for m in image.so_maps(self.bus) if m.board == self.board]

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
        valid = "false" if snap.stale(self.bus, self.board) else "true"
        return clock.ns(t), (f'{{"time":{t!r},"valid":{valid}'
                             + "".join("," + p for p in parts) + "}")


@dataclass(frozen=True)
class JointRefs:
    """A joint (an axis whose Target its board's tree names) and its edges."""

    name: str
    position: EdgeRef
    velocity: EdgeRef | None


def find_joints(boards: Sequence[Board]) -> list[JointRefs]:
    """The robot's joints, named as a recording names them
    (:func:`~ucom_tools.trace.mcap_record.joints_of`, after ``ucom gateway``)."""
    return [JointRefs(j.name, j.position[0].edges[j.position[1]],
                      None if j.velocity is None else j.velocity[0].edges[j.velocity[1]])
            for j in joints_of(list(boards))]


class JointStates:
    """The ``/joints`` message (``foxglove.JointStates``) from a snapshot."""

    def __init__(self, joints: Sequence[JointRefs]) -> None:
        def edge(ref: EdgeRef | None, field: str) -> tuple[EdgeRef, str, Conv] | None:
            if ref is None or ref.kind is not mca.Kind.SO:
                return None  # a joint's sensor and velocity are SO (what the board sends)
            return ref, f',"{field}":', conv_of(ref)[0]

        self._joints = [('{"name":' + json.dumps(j.name), edge(j.position, "position"),
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


def joint_states_of(latest: dict[tuple[BoardKey, str], Any],
                    joints: Sequence[JointRefs], ns: int) -> str:
    """The ``/joints`` message of the latest values of the joints' boards, by (bus and
    board, unique name) (``browse``: from the boards' samples)."""
    items = []
    for j in joints:
        doc: dict[str, Any] = {"name": j.name}
        for field, ref in (("position", j.position), ("velocity", j.velocity)):
            got = None if ref is None else latest.get(((ref.bus, ref.board), ref.unique))
            if got is not None:
                doc[field] = got
        items.append(json.dumps(doc, separators=(",", ":")))
    return f'{{"timestamp":{time_json(ns)},"joints":[{",".join(items)}]}}'


# ---------------------------------------------------------------------- events
class EventLines:
    """The run's events that came since the last snapshot, as (bus time, level, name,
    text): the boards' Errors, the writes and stops from outside, the boards lost and
    rejoined (in the words, levels and names of a recording's ``/events``: a board's
    placement, or ``writes``)."""

    def __init__(self) -> None:
        self._events = self._writes = self._faults = 0

    def of(self, snap: LoopSnapshot) -> list[tuple[float, int, str, str]]:
        out: list[tuple[float, int, str, str]] = []
        for e in snap.newer(snap.events, snap.events_total, self._events):
            out.append((snap.on_stamps(e.time), LOG_ERROR if e.stopped_motors
                        else LOG_WARNING, e.where, f"{e.where}: {e.code.name}: {e.text}"
                        + ("; its watchdog stopped its motors" if e.stopped_motors else "")))
        for w in snap.newer(snap.writes, snap.writes_total, self._writes):
            what = "stop" if not w.name else f"set {w.name} = {w.value}"
            out.append((snap.on_stamps(w.time), LOG_INFO if w.done else LOG_WARNING,
                        "writes", f"{what} from {w.origin}: {w.result}"))
        for f in snap.newer(snap.faults, snap.faults_total, self._faults):
            out.append((snap.on_stamps(f.time), LOG_WARNING if f.event == "lost"
                        else LOG_INFO, f.where, f.describe()))
        self._events, self._writes = snap.events_total, snap.writes_total
        self._faults = snap.faults_total
        return sorted(out, key=lambda e: e[0])


__all__ = ["DEFAULT_ADDRESS", "EVENTS_TOPIC", "FRAME_SCHEMA", "JOINTS_SCHEMA", "JOINTS_TOPIC",
           "LOG_SCHEMA", "SET_SCHEMA", "SET_TOPIC", "BoardValues", "EventLines",
           "JointRefs", "JointStates", "WallClock", "find_joints", "frame_json",
           "frames_topic", "joint_states_of", "layout", "log_json", "now_ns",
           "parse_address", "values_schema"]
