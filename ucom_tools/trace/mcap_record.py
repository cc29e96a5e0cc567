"""Recording a run as one MCAP file (``ucom remote run --record run.mcap``): every frame
of every bus, the values by robot-wide name per board at the loop's rate (or
``--record-rate``), the joints as ``foxglove.JointStates``, the run's events as
``foxglove.Log``, the robot's structure as a metadata record (``ucom(1)``, MCAP
RECORDINGS; the channels and the writer: :mod:`ucom_tools.trace.mcapfile`).

:class:`McapRecorder` runs in the consumers' process of ``remote run``
(:mod:`ucom_tools.cli.consumers`) and reads what the loop hands over there (a
:class:`RunSource`, the :class:`~ucom_tools.ops.remote.mirror.Mirror`): the sinks it adds
only queue what comes (the pipe's reader must keep up); a thread of its own encodes and
writes every :data:`WRITE_EVERY_S`, up to the latest snapshot, so that the faults and
events a snapshot brings are placed in time among the values before they are written;
it pauses now and then (:class:`~ucom_tools.courtesy.Courtesy`), so that the process's
other threads (the pipe's reader, the Foxglove feed) are not kept waiting for the GIL.

One time base: every time is the frames' (a frame's stamp, a value's frame, a
snapshot's ``stamp``, an event's time via ``on_stamps``), mapped once to the wall clock
(:func:`~ucom_tools.trace.mcapfile.wall_offset`, at the first snapshot) for the log
times; the messages keep the bus time in their ``time`` field.

The values: each board's last value of each edge (from the loop's value changes, every
SO value with its frame's time; an edge that no change brought by the first snapshot,
a target never written, from that snapshot) sampled on a grid of ``1 / rate`` seconds
of bus time:
at each sample time every board gets a message ``{"time", "valid", <key>: value ...}``
(keys: :func:`value_key`; ``valid`` false while its board is lost, its values then the
last it sent).  A change reported behind a sample time already written (another bus's
frame of the same cycle) goes into the next sample.  At the end each board gets one more
with the last snapshot's values: what ``--json`` prints.
"""

from __future__ import annotations

import json
import re
import threading
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

from ucom_tools import __version__
from ucom_tools.courtesy import Courtesy
from ucom_tools.errors import InputError, WriteError
from ucom_tools.fileio import reason
from ucom_tools.trace.logs import LogError, not_kept
from ucom_tools.trace.mcapfile import (
    EVENTS_TOPIC,
    FRAME_SCHEMA,
    JOINTS_SCHEMA,
    JOINTS_TOPIC,
    LOG_LEVELS,
    LOG_SCHEMA,
    ROBOT_METADATA,
    McapFile,
    entry_json,
    frames_topic,
    stamp_json,
    wall_offset,
)

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey

WRITE_EVERY_S = 0.05
"""How often the recorder's thread writes what came."""
VALUES_SCHEMA_PREFIX = "ucom.Values."
"""A board's values schema is named this and its topic's name (``ucom.Values.Eyes``)."""
RESERVED = ("time", "valid")
"""The fields of a board's values message that are not edges."""


class RunSource(Protocol):
    """What the recorder reads (:class:`~ucom_tools.ops.remote.mirror.Mirror`)."""

    image: Any
    frame_sinks: list[Any]
    change_sinks: list[Any]
    snapshot_sinks: list[Any]

    def final(self) -> Any: ...


def value_key(name: str) -> str:
    """A robot-wide name as a field of a values message that a Foxglove message path can
    name (letters, digits, ``_``): ``Right Eye Joint Sensor`` -> ``Right_Eye_Joint_Sensor``."""
    return re.sub(r"[^A-Za-z0-9_]+", "_", name).strip("_") or "_"


def topic_chunk(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_") or "_"


@dataclass
class Board:
    """One board's values as the recorder keeps them: each edge's last value as text
    and as its field of the message (``"Key":text``, made when the value changes, not
    at each of the 1,000 samples a second), and the fields joined once after a change."""

    bus: str
    board: int
    where: str
    prefix: str
    topic: str
    keys: list[str]
    edges: list[Any]
    texts: list[str | None] = field(default_factory=list)
    valid: bool = True
    channel: Any = None
    fields: list[str | None] = field(default_factory=list)
    body: str | None = None
    """The fields joined (None: to be joined again)."""

    def add(self, key: str, ref: Any) -> None:
        self.keys.append(key)
        self.edges.append(ref)
        self.texts.append(None)
        self.fields.append(None)

    def set(self, i: int, text: str) -> None:
        """Edge ``i``'s value is ``text`` now."""
        if self.texts[i] != text:
            self.texts[i] = text
            self.fields[i] = f'"{self.keys[i]}":{text}'
            self.body = None

    def joined(self) -> str:
        """Its fields joined ('' while no edge has a value)."""
        body = self.body
        if body is None:
            body = self.body = ",".join(f for f in self.fields if f is not None)
        return body

    def message(self, t: float) -> bytes:
        body = self.joined()
        return (f'{{"time":{t!r},"valid":{"true" if self.valid else "false"}'
                + ("," + body if body else "") + "}").encode()


@dataclass(frozen=True)
class JointSlots:
    """A joint: its name and where its position and velocity are kept."""

    name: str
    position: tuple[Board, int]
    velocity: tuple[Board, int] | None


def layout(refs: Iterable[Any]) -> list[Board]:
    """The boards of an image's edges (:attr:`PartImage.refs`), each with its edges'
    keys (unique within the board: a second ``X`` is ``X_2``) and a topic of its own
    (``/<Prefix>/values``, ``/<bus>/<board>/values`` where two boards share a prefix)."""
    by_board: dict[BoardKey, Board] = {}
    for ref in refs:
        b = by_board.get((ref.bus, ref.board))
        if b is None:
            b = by_board[(ref.bus, ref.board)] = Board(ref.bus, ref.board, ref.where,
                                                       ref.prefix, "", [], [])
        key = value_key(ref.unique)
        n, base = 1, key
        while key in b.keys or key in RESERVED:
            n += 1
            key = f"{base}_{n}"
        b.add(key, ref)
    prefixes = [b.prefix for b in by_board.values()]
    for b in by_board.values():
        chunk = topic_chunk(b.prefix) if b.prefix and prefixes.count(b.prefix) == 1 \
            else f"{topic_chunk(b.bus)}/{b.board}"
        b.topic = f"/{chunk}/values"
    return list(by_board.values())


def values_schema(b: Board) -> dict[str, Any]:
    """The JSON Schema of a board's values messages (``ucom.Values.<topic>``; also what
    ``--foxglove`` serves live)."""
    props = {k: {"type": "number", "title": ref.unique,
                 "description": f"{ref.kind.name}"
                                + (f", {ref.spec.unit}" if ref.spec.unit else "")}
             for k, ref in zip(b.keys, b.edges, strict=True)}
    return {"title": VALUES_SCHEMA_PREFIX + b.topic.strip("/").removesuffix(
        "/values").replace("/", "."), "type": "object",
        "description": f"the values of {b.where} by robot-wide name",
        "properties": {"time": {"type": "number", "description": "bus time, s"},
                       "valid": {"type": "boolean",
                                 "description": "false while the board is lost"},
                       **props}}


def joints_of(boards: list[Board]) -> list[JointSlots]:
    """The joints among the boards' edges: an axis whose Target edge the tree names
    (its unique name is not the program's generic one), as ``ucom gateway`` finds them
    (:mod:`ucom_tools.gateway.joints`, by the programs' :mod:`~ucom_tools.edgelists.axes`),
    with its joint sensor as position and its
    velocity edge as velocity."""
    from ucom_tools.edgelists.axes import MODELS, Role

    found: list[tuple[str, Board, JointSlots]] = []
    for b in boards:
        slot = {ref.generic: i for i, ref in enumerate(b.edges)}
        for model in MODELS.values():
            for axis in range(model.axes):
                target = model.generic(Role.TARGET, axis)
                sensor = model.generic(Role.JOINT_SENSOR, axis)
                velocity = model.generic(Role.VELOCITY, axis)
                if target not in slot or sensor not in slot:
                    continue
                unique = b.edges[slot[target]].unique
                if unique == target:
                    continue  # an axis the tree does not use
                name = unique.removesuffix(model.name_suffix).strip() or unique
                found.append((name, b, JointSlots(
                    name, (b, slot[sensor]),
                    (b, slot[velocity]) if velocity in slot else None)))
    names = [n for n, _, _ in found]
    return [JointSlots(f"{b.prefix}/{n}", j.position, j.velocity) if names.count(n) > 1
            else j for n, b, j in found]


def _newer(items: tuple[Any, ...], total: int, seen: int) -> tuple[Any, ...]:
    new = total - seen
    if new <= 0:
        return ()
    return items[-new:] if new < len(items) else items


class McapRecorder:
    """``--record FILE.mcap`` in the consumers' process (see the module docstring).
    InputError (exit 3) when FILE cannot be written; :meth:`attach` to the run's
    source; :meth:`check` raises LogError once writing failed; :meth:`close` commits
    (LogError, and no file, when writing failed), :meth:`discard` keeps nothing."""

    def __init__(self, path: str, *, rate_hz: float | None = None,
                 loop_hz: float = 1000.0, key: str = "record") -> None:
        self.path = path
        self.rate_hz = float(rate_hz or loop_hz)
        self.loop_hz = loop_hz
        self.key = key
        self.file = McapFile(path, key)
        self.frames = 0
        """Frames written so far."""
        self.samples = 0
        """Values messages written so far."""
        self.events = 0
        self._queue: deque[tuple[Any, ...]] = deque()
        self._snapshots = 0
        """Snapshots queued (the thread writes up to the last one queued)."""
        self._offset: float | None = None
        self._source: RunSource | None = None
        self._boards: list[Board] | None = None
        self._slots: dict[Any, tuple[Board, int]] = {}
        self._joints: list[JointSlots] = []
        self._next: float | None = None
        self._timeline: list[tuple[float, BoardKey, bool]] = []
        self._seen = [0, 0, 0]
        self._seeded = False
        self._last_log: dict[str, int] = {}
        self._failure: BaseException | None = None
        self._closed = False
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._courtesy = Courtesy()
        self._thread = threading.Thread(target=self._run, name="ucom-mcap", daemon=True)

    # ------------------------------------------------------------------ the source's side
    def attach(self, source: RunSource) -> None:
        """Read ``source``'s frames, value changes and snapshots from now on."""
        self._source = source
        source.frame_sinks.append(self._on_frames)
        source.change_sinks.append(self._on_change)
        source.snapshot_sinks.append(self._on_snapshot)
        self._thread.start()

    def _on_frames(self, bus: str, entries: list[Any]) -> None:
        self._queue.append(("f", bus, entries))

    def _on_change(self, t: float, ref: Any, value: Any) -> None:
        self._queue.append(("c", t, ref, value))

    def _on_snapshot(self, snap: Any) -> None:
        if self._offset is None:
            self._offset = wall_offset(snap.stamp, time.time() - (time.monotonic()
                                                                  - snap.taken))
        self._queue.append(("s", snap))
        self._snapshots += 1

    # ------------------------------------------------------------------ the thread
    def _run(self) -> None:
        while not self._stopping.wait(WRITE_EVERY_S):
            try:
                with self._lock:
                    self._write_queued(final=False)
            except Exception as err:  # kept: check() ends the run with it
                self._failure = err
                return

    def _write_queued(self, *, final: bool) -> None:
        """Write what was queued up to the last snapshot (everything where ``final``)."""
        if self._failure is not None or self.file.failure is not None:
            self._queue.clear()
            return
        take = len(self._queue) if final else self._last_snapshot()
        if take == 0 or self._offset is None:
            return
        if self._boards is None:
            self._begin()
        batch = [self._queue.popleft() for _ in range(take)]
        for item in batch:  # faults and events first: they are placed by their times
            if item[0] == "s":
                self._snapshot_events(item[1])
        courtesy = self._courtesy
        for item in batch:
            courtesy()
            kind = item[0]
            if kind == "c":
                self._change(item[1], item[2], item[3])
            elif kind == "f":
                self._frames(item[1], item[2])
            else:
                if not self._seeded:
                    self._seed(item[1])
                self._advance(item[1].stamp)
        if self.file.failure is not None:
            raise self.file.failure

    def _seed(self, snap: Any) -> None:
        """Each edge that no value change has brought yet (a target never written, a
        PAR as the tree configured it, a sensor that stands still) as the first
        snapshot has it: in the messages from then on, not from its first change (a
        plot of a target that was never set stayed empty)."""
        self._seeded = True
        self._take_values(snap, missing_only=True)

    def _take_values(self, snap: Any, *, missing_only: bool) -> bool:
        """The snapshot's values into the boards (only where an edge has none yet, with
        ``missing_only``); False where the run's structure is not known."""
        image = self._source.image if self._source is not None else None
        if image is None or self._boards is None:
            return False
        for ref, (_, value) in image.decode(snap.values).items():
            got = self._slots.get(ref)
            if got is not None and not (missing_only and got[0].texts[got[1]] is not None):
                got[0].set(got[1], str(value))
        return True

    def _last_snapshot(self) -> int:
        """How many queued items reach to the last snapshot queued."""
        if not self._snapshots:
            return 0
        for i in range(len(self._queue) - 1, -1, -1):
            if self._queue[i][0] == "s":
                self._snapshots = 0
                return i + 1
        return 0

    def _begin(self) -> None:
        """The boards, joints and channels, once the run's structure is there."""
        assert self._source is not None
        image = self._source.image
        self._boards = layout(image.refs if image is not None else ())
        for b in self._boards:
            b.channel = self.file.channel(b.topic, values_schema(b), {
                "bus": b.bus, "board": str(b.board), "where": b.where, "prefix": b.prefix,
                "edges": json.dumps([[k, r.unique, r.kind.name, r.spec.unit]
                                     for k, r in zip(b.keys, b.edges, strict=True)])})
            for i, ref in enumerate(b.edges):
                self._slots[ref] = (b, i)
        self._joints = joints_of(self._boards)
        self._joint_channel = self.file.channel(JOINTS_TOPIC, JOINTS_SCHEMA) \
            if self._joints else None
        self._events_channel = self.file.channel(EVENTS_TOPIC, LOG_SCHEMA)

    def _ns(self, t: float) -> int:
        assert self._offset is not None
        return round((t + self._offset) * 1e9)

    def _log(self, channel: Any, topic: str, t: float, data: bytes) -> int:
        """Log ``data`` at bus time ``t``, never before the channel's last message."""
        ns = max(self._ns(t), self._last_log.get(topic, 0))
        self._last_log[topic] = ns
        channel.log(data, log_time=ns)
        return ns

    # ------------------------------------------------------------------ frames
    def _frames(self, bus: str, entries: list[Any]) -> None:
        topic = frames_topic(bus)
        ch = self.file.channel(topic, FRAME_SCHEMA, {"bus": bus})
        offset = self._offset
        assert offset is not None
        last = self._last_log.get(topic, 0)
        for entry in entries:
            ns = max(round((entry[2] + offset) * 1e9), last)
            last = ns
            ch.log(entry_json(entry), log_time=ns)
        self._last_log[topic] = last
        self.frames += len(entries)

    # ------------------------------------------------------------------ values
    def _change(self, t: float, ref: Any, value: Any) -> None:
        self._advance(t)
        got = self._slots.get(ref)
        if got is not None:
            got[0].set(got[1], str(value))

    def _advance(self, t: float) -> None:
        """Write every sample due up to bus time ``t``."""
        step = 1.0 / self.rate_hz
        if self._next is None:
            self._next = t
        while self._next <= t:
            self._sample(self._next)
            self._next += step
            self._courtesy()

    def _sample(self, t: float) -> None:
        timeline = self._timeline
        while timeline and timeline[0][0] <= t:
            _, board, valid = timeline.pop(0)
            for b in self._boards or ():
                if (b.bus, b.board) == board:
                    b.valid = valid
        for b in self._boards or ():
            if b.joined():
                self._log(b.channel, b.topic, t, b.message(t))
                self.samples += 1
        if self._joint_channel is not None:
            self._joint_message(t)

    def _joint_message(self, t: float) -> None:
        parts = []
        for j in self._joints:
            b, i = j.position
            position = b.texts[i]
            if position is None:
                continue
            text = f'{{"name":{json.dumps(j.name)},"position":{position}'
            if j.velocity is not None and j.velocity[0].texts[j.velocity[1]] is not None:
                text += f',"velocity":{j.velocity[0].texts[j.velocity[1]]}'
            parts.append(text + "}")
        if parts:
            ns = self._ns(t)
            self._log(self._joint_channel, JOINTS_TOPIC, t,
                      f'{{"timestamp":{stamp_json(ns)},"joints":[{",".join(parts)}]}}'
                      .encode())

    # ------------------------------------------------------------------ events
    def _snapshot_events(self, snap: Any) -> None:
        """The faults, board Errors and writes ``snap`` added: logged, and the faults
        placed on the timeline of the boards' validity."""
        seen = self._seen
        events = _newer(snap.events, snap.events_total, seen[0])
        writes = _newer(snap.writes, snap.writes_total, seen[1])
        faults = _newer(snap.faults, snap.faults_total, seen[2])
        seen[:] = [snap.events_total, snap.writes_total, snap.faults_total]
        out: list[tuple[float, str, str, str]] = []
        for f in faults:
            at = snap.on_stamps(f.time)
            self._timeline.append((at, (f.bus, f.board), f.event != "lost"))
            out.append((at, "warning" if f.event == "lost" else "info", f.where,
                        f.describe()))
        for e in events:
            stopped = getattr(e, "stopped_motors", False)
            out.append((snap.on_stamps(e.time), "error" if stopped else "warning", e.where,
                        f"{e.where}: {getattr(e.code, 'name', e.code)}: {e.text}"
                        + ("; its watchdog stopped its motors" if stopped else "")))
        for w in writes:
            what = "stop" if not w.name else f"set {w.name} = {w.value}"
            out.append((snap.on_stamps(w.time), "info" if w.done else "warning", "writes",
                        f"{what} from {w.origin}: {w.result}"))
        self._timeline.sort(key=lambda x: x[0])
        for at, level, name, text in sorted(out, key=lambda x: x[0]):
            self.event(at, level, name, text)

    def event(self, t: float, level: str, name: str, text: str) -> None:
        """Log one event at bus time ``t`` (``level`` one of :data:`LOG_LEVELS`)."""
        ns = max(self._ns(t), self._last_log.get(EVENTS_TOPIC, 0))
        self._log(self._events_channel, EVENTS_TOPIC, t,
                  (f'{{"timestamp":{stamp_json(ns)},"level":{LOG_LEVELS[level]},'
                   f'"message":{json.dumps(text)},"name":{json.dumps(name)},'
                   '"file":"","line":0}').encode())
        self.events += 1

    # ------------------------------------------------------------------ the end
    def _last_values(self, snap: Any) -> None:
        """The last snapshot's values: one more message per board, what ``--json``
        prints."""
        if not self._take_values(snap, missing_only=False):
            return
        for b in self._boards or ():
            b.valid = not snap.stale(b.bus, b.board)
        t = max(snap.stamp, self._next if self._next is not None else snap.stamp)
        self._timeline.clear()
        self._sample(t)

    def _metadata(self) -> None:
        image = self._source.image if self._source is not None else None
        if image is None or self._boards is None:
            return
        self.file.metadata(ROBOT_METADATA, {
            "robot": image.name, "source": image.source, "virtual": str(image.virtual),
            "ucom_version": __version__, "loop_hz": repr(self.loop_hz),
            "record_hz": repr(self.rate_hz),
            "clock_offset_s": repr(self._offset or 0.0),
            "buses": json.dumps(image.bitrates),
            "boards": json.dumps([
                {"bus": b.bus, "board": b.board, "where": b.where, "prefix": b.prefix,
                 "serial": image.serials.get((b.bus, b.board)), "topic": b.topic,
                 "edges": [{"name": r.unique, "key": k, "kind": r.kind.name,
                            "unit": r.spec.unit, "range": r.spec.describe_range()}
                           for k, r in zip(b.keys, b.edges, strict=True)]}
                for b in self._boards]),
            "joints": json.dumps([{"name": j.name, "position": j.position[0].edges[
                j.position[1]].unique, "velocity": None if j.velocity is None else
                j.velocity[0].edges[j.velocity[1]].unique} for j in self._joints])})

    def check(self) -> None:
        """LogError when writing failed (cheap: the consumers' process asks often)."""
        err = self._failure or self.file.failure
        if err is not None:
            raise LogError(f"{self.path}: {reason(err)}; nothing was kept",
                           path=self.path, key=self.key) from err

    def _stop_thread(self) -> None:
        self._stopping.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join()

    def close(self) -> None:
        """Write the rest, the last values and the structure, and commit (idempotent);
        LogError, and no file, when writing failed."""
        if self._closed:
            return
        self._closed = True
        self._stop_thread()
        try:
            with self._lock:
                self.check()
                self._write_queued(final=True)
                final = self._source.final() if self._source is not None else None
                if final is not None and self._offset is not None:
                    if self._boards is None:
                        self._begin()
                    self._last_values(final)
                self._metadata()
                self.check()
            self.file.commit()
        except WriteError as err:
            self.file.discard()
            raise not_kept(err) from None
        except BaseException as err:
            self.file.discard()
            if isinstance(err, InputError | LogError):
                raise
            raise LogError(f"{self.path}: {reason(err)}; nothing was kept",
                           path=self.path, key=self.key) from err

    def discard(self) -> None:
        """End the recording and keep nothing (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._stop_thread()
        self.file.discard()

    def __repr__(self) -> str:
        return f"McapRecorder({self.path!r}, frames={self.frames}, samples={self.samples})"


__all__ = ["RESERVED", "VALUES_SCHEMA_PREFIX", "Board", "McapRecorder", "RunSource",
           "joints_of", "layout", "topic_chunk", "value_key"]
