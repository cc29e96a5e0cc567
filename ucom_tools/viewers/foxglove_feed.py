"""What feeds a :class:`~.foxglove.FoxgloveServer`: a run's consumers' process
(:class:`RunFoxglove`, ``remote run --foxglove``: the loop's snapshots and every bus's
frames, from :class:`~ucom_tools.ops.remote.mirror.Mirror`) or a browser's Zenoh
session (:class:`BrowseFoxglove`, ``browse --foxglove``: the boards' ``values`` samples
and the events; the frames stay on the robot's host).

:class:`RunFoxglove` works on a thread of its own: the mirror's reader only queues a
batch of frames for a bus some client subscribes to (a dictionary look-up and a call
to the SDK otherwise), so that what a client asks for never slows the hand-over the
recording depends on; the thread builds the messages (only of subscribed channels)
and hands them to the SDK.  A client that cannot keep up loses the oldest frames
(:data:`FRAME_BACKLOG`, counted), never the run.  Between two batches it pauses now and
then (:class:`~ucom_tools.courtesy.Courtesy`): the pipe's reader, which brings the
values, does not wait for the GIL behind the frames.
"""

from __future__ import annotations

import contextlib
import json
import queue
import threading
import time
from collections import deque
from concurrent.futures import TimeoutError as FutureTimeout
from typing import TYPE_CHECKING, Any, Final

from ucom_tools.courtesy import Courtesy
from ucom_tools.errors import BusError, InputError, UcomError
from ucom_tools.net.keys import number
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.remote.image import PartImage
from ucom_tools.ops.remote.mirror import Mirror
from ucom_tools.ops.remote.publish import Doorbell, LoopSnapshot
from ucom_tools.ops.remote.requests import Applied
from ucom_tools.protocol.traffic import SinkEntry
from ucom_tools.viewers import foxglove_msgs as fm
from ucom_tools.viewers.foxglove import FoxgloveServer
from ucom_tools.wire import mca

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey

WRITE_S: Final = 2.0
"""How long a client's write waits for the loop's answer."""
FRAME_BACKLOG: Final = 2000
"""Batches of frames (about 10 ms each) waiting for the thread; beyond, the oldest go."""
CLOSE_S: Final = 2.0
_FRAMES: Final = "frames"
"""The queue's token for 'frames are waiting'."""
WRITABLE = (mca.Kind.CI, mca.Kind.PAR)


class RunFoxglove:
    """``remote run --foxglove``'s server in the consumers' process (module docstring)."""

    def __init__(self, mirror: Mirror, host: str, port: int, *, robot: str,
                 allow_writes: bool, rate_hz: float) -> None:
        self.server = FoxgloveServer(host, port, name=f"ucom {robot}",
                                     allow_writes=allow_writes)
        self.mirror = mirror
        self.frames_dropped = 0
        self.frames_received = 0
        """Frames the loop handed over: only while a client watches a bus's frames."""
        self._frames_watched = False
        self.error: BaseException | None = None
        self._image: PartImage | None = None
        self._boards: list[tuple[fm.BoardValues, Any]] = []
        self._joints: tuple[fm.JointStates, Any] | None = None
        self._frame_channels: dict[str, Any] = {}
        self._frames: deque[tuple[str, list[SinkEntry]]] = deque()
        self._frames_rung = False
        self._last: dict[str, str] = {}
        self._lines = fm.EventLines()
        self._running = False
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._bell = mirror.subscribe(rate_hz, into=self._queue)
        self._closing = threading.Event()
        self._courtesy = Courtesy()
        self.server.writer = self._write
        self.server.reader = self._read
        mirror.frame_sinks.append(self._take_frames)
        self._thread = threading.Thread(target=self._run, name="ucom-foxglove", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ the mirror's thread
    def _take_frames(self, bus: str, entries: list[SinkEntry]) -> None:
        """A batch of a bus's frames: kept only where a client subscribes to the bus."""
        ch = self._frame_channels.get(bus)
        self.frames_received += len(entries)
        if ch is None or not ch.has_sinks():
            return
        if len(self._frames) >= FRAME_BACKLOG:
            self.frames_dropped += len(self._frames.popleft()[1])
        self._frames.append((bus, entries))
        if not self._frames_rung:
            self._frames_rung = True
            self._queue.put(_FRAMES)

    # ------------------------------------------------------------------ this one's thread
    def _run(self) -> None:
        try:
            while not self._closing.is_set():
                try:
                    item = self._queue.get(timeout=0.05)
                except queue.Empty:
                    continue
                self._take(item)
                self._send_frames()
                self._ask_frames()
        except BaseException as err:  # the server ends; the run goes on
            self.error = err

    def _take(self, item: object) -> None:
        """``item`` and whatever else is queued: the latest snapshot's values sent (behind,
        only the latest; the frames' token needs nothing, :meth:`_send_frames` follows)."""
        snap: LoopSnapshot | None = None
        while True:
            if isinstance(item, Doorbell):
                snap = item.answer()
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
        if snap is not None:
            self._snapshot(snap)

    def _ask_frames(self) -> None:
        """The loop hands the frames over only while a client watches a bus's frames
        (25,000 a second of ARMAR-III through the pipe, for nobody otherwise)."""
        watched = any(ch.has_sinks() for ch in self._frame_channels.values())
        if watched != self._frames_watched:
            self._frames_watched = watched
            self.mirror.frames(watched)

    def _declare(self, image: PartImage, snap: LoopSnapshot) -> None:
        """The channels, once the boards run (their names known)."""
        s = self.server
        s.clock.anchor(snap.stamp, snap.taken)
        boards = fm.layout(image.refs)
        for b in boards:
            enc = fm.BoardValues(image, b)
            self._boards.append((enc, s.channel(enc.topic, enc.schema)))
        joints = fm.find_joints(boards)
        if joints:
            self._joints = (fm.JointStates(joints),
                            s.channel(fm.JOINTS_TOPIC, fm.JOINTS_SCHEMA))
        self._frame_channels = {bus: s.channel(fm.frames_topic(bus), fm.FRAME_SCHEMA)
                                for bus in image.bitrates}
        self._image = image

    def _snapshot(self, snap: LoopSnapshot) -> None:
        image = self._image
        if image is None:
            if self.mirror.image is None:
                return
            self._declare(self.mirror.image, snap)
            image = self._image
            assert image is not None
        s = self.server
        if snap.running and not self._running:
            self._running = True
            s.note(fm.LOG_INFO, f"the loop runs: {image.name}, "
                   f"{1 / image.period_s:g} Hz", s.clock.ns(snap.stamp))
        lines = self._lines.of(snap)
        if lines and s.wants(s.events):
            for t, level, name, text in lines:
                ns = s.clock.ns(t)
                s.send(s.events, ns, fm.log_json(ns, level, text, name))
        sources: list[tuple[Any, Any]] = list(self._boards)
        if self._joints is not None:
            sources.append(self._joints)
        for enc, ch in sources:
            if not s.wants(ch):
                continue
            ns, text = enc.message(image, snap, s.clock)
            topic = ch.topic()
            if text != self._last.get(topic):  # nothing new: not again
                self._last[topic] = text
                s.send(ch, ns, text)

    def _send_frames(self) -> None:
        """Every queued batch of frames; a snapshot that comes meanwhile is sent between
        two batches, so that the values never wait behind a backlog of frames."""
        s, frames, waiting = self.server, self._frames, self._queue
        self._frames_rung = False
        while frames:
            self._frames_rung = False  # before the pop: a batch after it rings again
            bus, entries = frames.popleft()
            ch = self._frame_channels[bus]
            for entry in entries:
                s.send(ch, s.clock.ns(entry[2]), fm.frame_json(entry))
            self._courtesy()
            if not waiting.empty():
                with contextlib.suppress(queue.Empty):
                    self._take(waiting.get_nowait())

    # ------------------------------------------------------------------ writes (SDK threads)
    def _write(self, name: str, value: object, origin: str) -> Applied:
        try:
            return self.mirror.write(name, value, origin).result(timeout=WRITE_S)
        except FutureTimeout:
            return Applied("failed", f"set {name}: the loop did not answer within "
                           f"{WRITE_S:g} s")

    def _read(self, names: list[str] | None) -> dict[str, Any]:
        image, snap = self._image, self.mirror.latest
        if image is None or snap is None:
            return {}
        return current_values(image, snap, names)

    # ------------------------------------------------------------------ the end
    def close(self) -> None:
        """Stop the thread, say how the run ended on ``/events``, stop the server."""
        self._closing.set()
        self._thread.join(CLOSE_S)
        with contextlib.suppress(ValueError):
            self.mirror.frame_sinks.remove(self._take_frames)
        self._bell.close()
        final = self.mirror.final()
        s = self.server
        if final is not None and self._image is not None and s.wants(s.events):
            for t, level, name, text in self._lines.of(final):
                ns = s.clock.ns(t)
                s.send(s.events, ns, fm.log_json(ns, level, text, name))
            s.note(fm.LOG_INFO, "the loop ended", s.clock.ns(final.stamp))
        s.close()

    def stats(self) -> dict[str, Any]:
        return {**self.server.stats(), "frames_dropped": self.frames_dropped,
                "frames_received": self.frames_received,
                "joints": [] if self._joints is None else self._joints[0].names,
                "error": None if self.error is None else repr(self.error)}


def current_values(image: PartImage, snap: LoopSnapshot, names: list[str] | None,
                   ) -> dict[str, Any]:
    """The CI and PAR values of ``names`` (None: all) by robot-wide name, as numbers."""
    wanted: set[EdgeRef] | None = None
    if names is not None:
        wanted = set()
        for n in names:
            try:
                wanted.add(image.names.resolve(n, kinds=WRITABLE))
            except InputError:
                continue
    out: dict[str, Any] = {}
    for ref, (_, value) in image.decode(snap.values, WRITABLE).items():
        if wanted is None or ref in wanted:
            out[image.names.name_of(ref)] = number(value)
    return out


class BrowseFoxglove:
    """``browse --foxglove``: a robot's values and events from its Zenoh share, served
    (module docstring)."""

    def __init__(self, client: Any, host: str, port: int, *, allow_writes: bool) -> None:
        self.client = client
        s = self.server = FoxgloveServer(host, port, name=f"ucom {client.robot} (browse)",
                                         allow_writes=allow_writes)
        boards = fm.layout(list(client.names))
        self._boards: dict[BoardKey, tuple[Any, dict[str, str]]] = {
            (b.bus, b.board): (s.channel(b.topic, fm.values_schema(b)),
                               {r.unique: k for k, r in zip(b.keys, b.edges, strict=True)})
            for b in boards}
        self._joint_list = fm.find_joints(boards)
        self._joint_boards = {(j.position.bus, j.position.board) for j in self._joint_list}
        self._joints = (s.channel(fm.JOINTS_TOPIC, fm.JOINTS_SCHEMA)
                        if self._joint_list else None)
        self._latest: dict[tuple[BoardKey, str], Any] = {}
        self._joints_period = 1.0 / float(client.structure.get("publish_hz") or 100.0)
        self._joints_t = float("-inf")
        s.writer = self._write
        s.reader = self._read
        self._subs = [client.on_values(self._values), client.on_events(self._event),
                      client.on_alive(self._alive)]

    def _values(self, doc: dict[str, Any]) -> None:
        """A board's sample (Zenoh's thread)."""
        try:
            board = (str(doc["bus"]), int(doc["board"]))
            t, values = float(doc["t"]), dict(doc["values"])
        except (KeyError, TypeError, ValueError):
            return
        got = self._boards.get(board)
        if got is None:
            return
        ch, keys = got
        s = self.server
        s.clock.anchor(t)
        if board in self._joint_boards:
            self._latest.update({(board, u): v for u, v in values.items()})
        ns = s.clock.ns(t)
        if s.wants(ch):
            s.send(ch, ns, json.dumps({
                "time": t, "valid": doc.get("valid", True) is not False,
                **{keys[u]: v for u, v in values.items() if u in keys}},
                separators=(",", ":")))
        if self._joints is not None and board in self._joint_boards \
                and t - self._joints_t >= self._joints_period * 0.9 and s.wants(self._joints):
            self._joints_t = t  # once a publishing period, not once a board
            s.send(self._joints, ns, fm.joint_states_of(self._latest, self._joint_list, ns))

    def _event(self, doc: dict[str, Any]) -> None:
        s = self.server
        if not s.wants(s.events):
            return
        kind = doc.get("kind")
        t = doc.get("t")  # on the values' time base only for a fault
        ns = s.clock.ns(float(t)) if kind == "fault" and isinstance(t, int | float) \
            else fm.now_ns()
        name = "ucom"  # as a recording's /events names them: a board's placement, writes
        if kind == "board":
            level, text = fm.LOG_ERROR if doc.get("stopped_motors") else fm.LOG_WARNING, \
                f"{doc.get('where')}: {doc.get('error')}: {doc.get('text')}"
            name = str(doc.get("where") or name)
        elif kind in ("write", "stop"):
            what = "stop" if kind == "stop" else f"set {doc.get('name')} = {doc.get('value')}"
            level = fm.LOG_INFO if doc.get("result") == "done" else fm.LOG_WARNING
            text = f"{what} from {doc.get('origin')}: {doc.get('result')}"
            name = "writes"
        elif kind == "fault":
            level = fm.LOG_WARNING if doc.get("event") == "lost" else fm.LOG_INFO
            text = f"{doc.get('where')} {doc.get('event')}: {doc.get('seen')}"
            name = str(doc.get("where") or name)
        else:
            level, text = fm.LOG_INFO, f"robot {self.client.robot}: {doc.get('state', kind)}"
        s.send(s.events, ns, fm.log_json(ns, level, text, name))

    def _alive(self, up: bool) -> None:
        self.server.note(fm.LOG_INFO if up else fm.LOG_WARNING,
                         f"robot {self.client.robot} on {self.client.where}: "
                         + ("there" if up else "connection lost"))

    def _write(self, name: str, value: object, origin: str) -> Applied:
        from ucom_tools.net.client import WritesForbidden

        try:
            answer = self.client.write(name, value, timeout=WRITE_S)
        except WritesForbidden as err:
            return Applied("forbidden", str(err))
        except InputError as err:
            return Applied("refused", err.reason)
        except (BusError, UcomError) as err:
            return Applied("failed", str(err))
        return Applied(None, "done", str(answer.get("name", name)), answer.get("value"))

    def _read(self, names: list[str] | None) -> dict[str, Any]:
        wanted = names if names is not None else [
            self.client.names.name_of(r) for r in self.client.names
            if r.kind in WRITABLE]
        got = self.client.read(wanted, timeout=1.0)
        return {n: r.value for n, r in got.items()}

    def close(self) -> None:
        for sub in self._subs:
            sub.close()
        self.server.close()

    def stats(self) -> dict[str, Any]:
        return self.server.stats()


def serve_until(stop: threading.Event, seconds: float | None) -> None:
    """Wait until ``stop`` is set or ``seconds`` passed (None: until ``stop``)."""
    end = None if seconds is None else time.monotonic() + seconds
    while not stop.wait(0.2 if end is None else max(0.0, min(0.2, end - time.monotonic()))):
        if end is not None and time.monotonic() >= end:
            return
