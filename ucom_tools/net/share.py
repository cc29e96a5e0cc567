"""A running robot on the network: :func:`share` puts a :class:`~ucom_tools.ops.remote.
RemotePart` on Zenoh (``man/ucom-network.7``), as MCA2's mcabrowser reached every edge of
a running program.

What goes out, all under ``ucom/<robot>``: the structure (a queryable: buses, boards,
programs, every edge with its kind, names, unit, range and encoding); each board's values
batched once per publishing period (``<bus>/<board>/values``, also a queryable for the
latest); an edge's own key (``<bus>/<board>/edge/<unique name>``) only while someone
subscribes to it (Zenoh's matching status); the run's events; a liveliness token for the
robot and one per running board.  What comes in: writes (``set``) and a stop (``stop``),
refused unless ``allow_writes``; an allowed write is checked and applied exactly as a
local one (:meth:`RemotePart.set`), on the loop's thread, and answered.

Off the loop's critical path: the share reads the run through the loop's hand-over
(:class:`~ucom_tools.ops.remote.publish.LoopHandover`: every publishing period the
loop's thread takes a snapshot, references and small dict copies, and rings the
publishing thread's queue), never the loop's live structures; the loop's thread only
applies the writes the network queued and asks for the boards' Status reports; it never
waits for the network.  Encoding (from parts prepared once, :mod:`.encode`: the
publishing thread holds the GIL the loop needs as briefly as it can) and every Zenoh
call happen on the publishing thread (or on Zenoh's own threads, for the queries).

One robot, one loop: where the robot's liveliness token is already on the network (or a
ucom robot of that name listens on the endpoint) :func:`share` refuses (BusError),
unless ``force`` (:mod:`ucom_tools.net.one_loop`).
"""

from __future__ import annotations

import contextlib
import getpass
import os
import queue
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import zenoh

from ucom_tools.errors import BusTaken, FrameError, UcomError
from ucom_tools.net import keys, one_loop
from ucom_tools.net.encode import BoardEncoder, encoders
from ucom_tools.net.keys import check_rate
from ucom_tools.net.session import check_endpoint
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.remote import RemotePart
from ucom_tools.ops.remote.faults import BoardFault
from ucom_tools.ops.remote.feed import LocalRun
from ucom_tools.ops.remote.image import PartImage
from ucom_tools.ops.remote.publish import Doorbell, LoopSnapshot
from ucom_tools.ops.remote.report import WriteEvent
from ucom_tools.ops.remote.requests import Applied
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.ids import Direction, IdType

if TYPE_CHECKING:
    from ucom_tools.config.topology import BoardKey

JSON = zenoh.Encoding.APPLICATION_JSON
RESEND_S = 1.0
"""A board's sample that did not change (no new frame, nothing set) is put again only
after this long; its latest is always in the ``values`` queryable."""
CLOSE_S = 2.0
"""How long closing waits for the publishing thread."""
CLEAR_OF_DEADLINE_S = 0.0003
"""The publishing thread does not start a board's sample this close before the loop's
next deadline: it waits until the loop has sent that cycle (:data:`AFTER_DEADLINE_S`),
so that the GIL is free when the loop wakes."""
AFTER_DEADLINE_S = 0.00015


def status_doc(report: m.StatusReport, t: float) -> dict[str, Any]:
    """A board's Status report as its ``status`` sample (``man/ucom-network.7``): the
    LEDs as the board shows them (B.2.3: red, a CAN error; yellow, an overrun; green
    blinks while the program runs)."""
    leds = report.leds
    return {"t": round(t, 6), "state": report.state.name,
            "leds": {"red": "on" if leds & 1 else "off",
                     "yellow": "on" if leds & 2 else "off",
                     "green": "blink" if leds & 8 else "on" if leds & 4 else "off"},
            "tec": report.tec, "rec": report.rec, "overruns": report.overruns}


def fault_doc(fault: BoardFault, t: float) -> dict[str, Any]:
    """A board lost or rejoined as an event (``man/ucom-network.7``): ``t`` on the
    values' time base, ``time`` seconds since the exchange started (as ``--json``'s
    faults)."""
    return {"kind": "fault", "t": round(t, 6), "time": fault.time, "bus": fault.bus,
            "board": fault.board, "where": fault.where, "event": fault.event,
            "seen": fault.seen, "answered": fault.answered}


def origin() -> str:
    """Who this process is, for the robot's events: ``user@host pid N``."""
    try:
        user = getpass.getuser()
    except (KeyError, OSError):
        user = "?"
    return f"{user}@{socket.gethostname()} pid {os.getpid()}"


@dataclass
class _Answer:
    """What the loop's thread made of a request, for the publishing thread to send."""

    query: zenoh.Query
    ok: bool
    doc: dict[str, Any]
    event: WriteEvent | None


def open_shared(robot: str, *, zenoh: str | None = None,
                zenoh_config: str | Path | None = None, allow_writes: bool = False,
                publish_hz: float = 100.0, start: bool = True, force: bool = False,
                **open_args: Any) -> RemotePart:
    """:meth:`RemotePart.open` of ``robot`` (the same ``open_args``), shared on Zenoh
    before it starts: listening on ``zenoh`` (an endpoint, ``"tcp/127.0.0.1:7447"``)
    and/or by ``zenoh_config`` (a Zenoh JSON5 file), values at ``publish_hz``, writes
    only with ``allow_writes``; refused (BusError) where the robot already runs on that
    network, unless ``force``."""
    part = RemotePart.open(robot, start=False, force=force, **open_args)
    try:
        s = share(part, endpoint=zenoh, config_file=zenoh_config, allow_writes=allow_writes,
                  publish_hz=publish_hz, force=force)
        if start:  # the names known before the start: declared while nothing runs
            part.claim(force=force)
            part.check()
            s.declare()
            part.start(force=force)
    except BaseException:
        part.close()
        raise
    return part


def share(part: RemotePart, *, endpoint: str | None = None,
          config_file: str | Path | None = None, allow_writes: bool = False,
          publish_hz: float = 100.0, force: bool = False) -> RobotShare:
    """Share ``part`` on Zenoh: listen on ``endpoint`` (default ``tcp/127.0.0.1:7447``,
    unless ``config_file`` names the endpoints), values at ``publish_hz`` (1 .. the loop's
    rate).  Call it before :meth:`RemotePart.start` (or open the part with
    :func:`open_shared`); it may also share a running part.  The part closes the share."""
    assert part.robot.topology is not None
    loop_hz = 1.0 / part.period_s
    check_rate(publish_hz, loop_hz)
    run = LocalRun(part, publish_hz)
    try:
        s = RobotShare(run, keys.robot_id(part.robot.topology.source,
                                          part.robot.topology.name), loop_hz,
                       endpoint=endpoint, config_file=config_file,
                       allow_writes=allow_writes, publish_hz=publish_hz, force=force)
    except BaseException:
        run.close()
        raise
    s.owns_source = True
    part.share = s
    if part.report is not None:
        s.declare()  # the names are known: declared now, not while the loop runs
    return s


class RunSource(Protocol):
    """What a share reads and asks of the run: in the loop's own process its
    :class:`~ucom_tools.ops.remote.feed.LocalRun`, in the consumers' process of ``ucom
    remote run`` its :class:`~ucom_tools.ops.remote.mirror.Mirror`."""

    @property
    def image(self) -> PartImage | None: ...

    @property
    def latest(self) -> LoopSnapshot | None: ...

    def subscribe(self, rate_hz: float | None = None, into: Any = None) -> Doorbell: ...

    def next_deadline(self) -> float | None: ...

    def final(self) -> LoopSnapshot | None: ...

    def write(self, name: str, value: object, origin: str, *,
              network: bool = True) -> Future[Applied]: ...

    def stop(self, origin: str) -> Future[Applied]: ...

    def poll_status(self, boards: list[BoardKey]) -> None: ...

    @property
    def status_sinks(self) -> list[Callable[[str, int, bytes, float], None]]: ...

    def close(self) -> None: ...


class RobotShare:
    """One robot's run time on Zenoh (see the module docstring)."""

    def __init__(self, source: RunSource, robot: str, loop_hz: float, *,
                 endpoint: str | None = None, config_file: str | Path | None = None,
                 allow_writes: bool = False, publish_hz: float = 100.0, force: bool = False,
                 pid: int | None = None) -> None:
        check_rate(publish_hz, loop_hz)
        self.source = source
        self.owns_source = False
        """Closing the share closes its source (a :class:`LocalRun` made for it)."""
        self.robot = robot
        """The robot's chunk of the keys (``armar3``)."""
        self.pid = os.getpid() if pid is None else pid
        """The loop's process (the structure names it)."""
        self.allow_writes = allow_writes
        self.publish_hz = loop_hz / max(1, round(loop_hz / publish_hz))
        if endpoint is None and config_file is None:
            endpoint = keys.DEFAULT_ENDPOINT
        self.endpoint = check_endpoint(endpoint) if endpoint is not None else None
        self.started = time.time()
        self.session, joined = one_loop.open_listening(robot, self.endpoint, config_file,
                                                       force=force)
        self.joined: str | None = joined
        """The endpoint this share connected to instead of listening (``force``: another
        loop of the robot listens there)."""
        self.where = self.endpoint or str(config_file)
        try:
            if not force:
                other = one_loop.other_loop(self.session, robot)
                if other is not None:
                    raise BusTaken(one_loop.refusal(robot, self.endpoint, other))
            self._out: queue.SimpleQueue[Doorbell | _Answer] = queue.SimpleQueue()
            """What the publishing thread does next: the loop's doorbell (a snapshot to
            publish) or an answer to a write."""
            self._bell = source.subscribe(self.publish_hz, into=self._out)
            self._image: PartImage | None = None
            self._matched: set[str] = set()
            self._latest: dict[str, bytes] = {}
            self._edge_latest: dict[str, bytes] = {}
            self._put_at: dict[str, float] = {}
            self._encoders: dict[BoardKey, BoardEncoder] | None = None
            self._declared = False
            self._lock = threading.Lock()
            self._closing = threading.Event()
            self._board_tokens: dict[BoardKey, zenoh.LivelinessToken] = {}
            self._edge_pubs: dict[EdgeRef, tuple[str, zenoh.Publisher]] = {}
            self._edge_by_key: dict[str, tuple[EdgeRef, zenoh.Publisher]] = {}
            self._listeners: list[Any] = []
            self._board_pubs: dict[BoardKey, tuple[str, zenoh.Publisher]] = {}
            self._structure: bytes | None = None
            self._status_frames: deque[tuple[str, int, bytes, float]] = deque()
            """The Status report frames the loop's thread saw (bus, identifier, data,
            time), for the publishing thread to decode."""
            self._status_pubs: dict[BoardKey, zenoh.Publisher] = {}
            self._events_seen = 0
            self._writes_seen = 0
            self._faults_seen = 0
            self._state = "starting"
            self.published = 0
            """Samples put so far (board values and edges)."""
            self.error: BaseException | None = None
            """What stopped the publishing thread, if anything did (the loop goes on)."""
            s = self.session
            self._events = s.declare_publisher(keys.robot_key(self.robot, "events"),
                                               encoding=JSON)
            self._queryables = [
                s.declare_queryable(keys.robot_key(self.robot, "structure"),
                                    self._on_structure),
                s.declare_queryable(keys.robot_key(self.robot, "set"), self._on_set),
                s.declare_queryable(keys.robot_key(self.robot, "stop"), self._on_stop),
                s.declare_queryable(keys.KEYS["values"].format(
                    robot=keys.escape(self.robot), bus="*", board="*"), self._on_values),
            ]
            self._token: zenoh.LivelinessToken | None = None
            self._thread = threading.Thread(target=self._run, name="ucom-zenoh", daemon=True)
            self._thread.start()
        except BaseException:
            self.session.close()
            raise

    # ------------------------------------------------------------------ declarations
    def declare(self) -> None:
        """Build the structure and declare what needs the edges' names (the part has been
        checked): the robot's liveliness token, a publisher per board and per edge, and
        the edges' matching listeners.  Done by :func:`share` where the part is checked
        already, else by the publishing thread."""
        with self._lock:
            if self._declared:
                return
            image, s = self.source.image, self.session
            if image is None:
                return  # not checked yet: the publishing thread declares later
            self._image = image
            self._structure = keys.dumps(self._structure_doc(image))
            for ref in image.refs:
                board = (ref.bus, ref.board)
                if board not in self._board_pubs:
                    k = keys.board_key(self.robot, ref.bus, ref.board)
                    self._board_pubs[board] = (k, s.declare_publisher(k, encoding=JSON))
                    self._status_pubs[board] = s.declare_publisher(
                        keys.board_key(self.robot, ref.bus, ref.board, "status"),
                        encoding=JSON)
                k = keys.edge_key(self.robot, ref.bus, ref.board, ref.unique)
                pub = s.declare_publisher(k, encoding=JSON)
                self._edge_pubs[ref] = (k, pub)
                self._edge_by_key[k] = (ref, pub)
                self._listeners.append(pub.declare_matching_listener(self._matching(k)))
            self.source.status_sinks.append(self._take_status)
            self.source.poll_status(sorted(self._board_pubs))
            self._token = s.liveliness().declare_token(keys.robot_key(self.robot, "alive"))
            self._declared = True

    def _take_status(self, bus: str, ident: int, data: bytes, t: float) -> None:
        """A Status report frame (the loop's thread: kept, decoded later)."""
        self._status_frames.append((bus, ident, data, t))

    def _matching(self, key: str) -> Callable[[zenoh.MatchingStatus], None]:
        def changed(status: zenoh.MatchingStatus) -> None:
            if status.matching:
                self._edge_latest.pop(key, None)  # a new subscriber: the next value goes
                self._matched.add(key)
            else:
                self._matched.discard(key)
        return changed

    def _structure_doc(self, image: PartImage) -> dict[str, Any]:
        report = image.report
        checks = {(b.bus, b.board): b for b in (report.boards if report else ())}
        buses: dict[str, dict[str, Any]] = {}
        boards: dict[BoardKey, dict[str, Any]] = {}
        for name, bitrate in image.bitrates.items():
            buses[name] = {"name": name, "bitrate": bitrate, "boards": []}
        for ref in image.refs:
            b = boards.get((ref.bus, ref.board))
            if b is None:
                c = checks.get((ref.bus, ref.board))
                b = {"board": ref.board, "where": ref.where, "prefix": ref.prefix,
                     "tree": c.tree_file if c else "", "program": c.program if c else "",
                     "key": keys.board_key(self.robot, ref.bus, ref.board).rsplit("/", 1)[0],
                     "edges": []}
                boards[(ref.bus, ref.board)] = b
                buses[ref.bus]["boards"].append(b)
            spec = ref.spec
            b["edges"].append({
                "name": ref.unique, "generic": ref.generic, "qualified": ref.qualified,
                "robot_name": image.names.name_of(ref), "kind": ref.kind.name,
                "unit": spec.unit, "min": keys.number(ref.value(spec.minimum)),
                "max": keys.number(ref.value(spec.maximum)), "range": ref.describe_range(),
                "encoding": {"width": spec.width, "signed": spec.signed,
                             "exponent": spec.exponent, "raw_min": spec.minimum,
                             "raw_max": spec.maximum},
                "cyclic": image.cyclic(ref), "writable": ref.kind is not mca.Kind.SO,
                "key": keys.edge_key(self.robot, ref.bus, ref.board, ref.unique)})
        return {"robot": self.robot, "name": image.name,
                "host": socket.gethostname(), "pid": self.pid,
                "listen": self.endpoint if self.joined is None else None,
                "started": round(self.started, 3), "rate_hz": round(1 / image.period_s, 3),
                "publish_hz": round(self.publish_hz, 3), "allow_writes": self.allow_writes,
                "virtual_time": image.virtual, "zid": str(self.session.zid()),
                "buses": [b for b in buses.values() if b["boards"]]}

    # ------------------------------------------------------------------ queries (Zenoh's threads)
    def _on_structure(self, query: zenoh.Query) -> None:
        if self._structure is None:
            query.reply_err(keys.dumps({"ok": False, "error": "starting",
                                        "message": "the boards are being checked"}),
                            encoding=JSON)
        else:
            query.reply(keys.robot_key(self.robot, "structure"), self._structure,
                        encoding=JSON)

    def _on_values(self, query: zenoh.Query) -> None:
        asked = query.key_expr
        for k, payload in list(self._latest.items()):
            if asked.intersects(zenoh.KeyExpr(k)):
                query.reply(k, payload, encoding=JSON)

    def _request(self, query: zenoh.Query, stop: bool) -> None:
        what = "stop the boards" if stop else "set values"
        if not self.allow_writes:
            query.reply_err(keys.dumps({
                "ok": False, "error": "forbidden",
                "message": f"robot {self.robot!r} does not allow other hosts to {what} (its "
                           "loop runs without --allow-writes)"}), encoding=JSON)
            return
        latest = self.source.latest
        if self._closing.is_set() or (latest is not None and not latest.running):
            query.reply_err(keys.dumps({"ok": False, "error": "stopped",
                                        "message": "the loop is not running"}),
                            encoding=JSON)
            return
        try:
            doc = keys.loads(query.payload.to_bytes() if query.payload is not None else b"{}")
            who = str(doc.get("origin") or "unknown")
            if stop:
                self._ask(query, self.source.stop(who))
                return
            name, value = doc.get("name"), doc.get("value")
            if not isinstance(name, str) or isinstance(value, bool) \
                    or not isinstance(value, int | float | str):
                raise ValueError('expected {"v": 1, "name": NAME, "value": NUMBER}')
        except ValueError as err:
            query.reply_err(keys.dumps({"ok": False, "error": "refused",
                                        "message": f"not a write: {err}"}), encoding=JSON)
            return
        self._ask(query, self.source.write(name, value, who))

    def _ask(self, query: zenoh.Query, future: Future[Applied]) -> None:
        """The answer, once the loop's thread applied the request, to the publishing
        thread (which replies)."""
        def done(f: Future[Applied]) -> None:
            a = f.result()
            if a.ok:
                doc: dict[str, Any] = ({"ok": True, "done": "stopping"}
                                       if a.message == "stopping" else
                                       {"ok": True, "done": "set", "name": a.name,
                                        "value": keys.number(a.value), "range": a.range,
                                        "unit": a.unit})
            else:
                doc = {"ok": False, "error": a.error, "message": a.message}
            self._out.put(_Answer(query, a.ok, doc, a.event))
        future.add_done_callback(done)

    def _on_set(self, query: zenoh.Query) -> None:
        self._request(query, stop=False)

    def _on_stop(self, query: zenoh.Query) -> None:
        self._request(query, stop=True)

    # ------------------------------------------------------------------ the publishing thread
    def _run(self) -> None:
        try:
            while not self._closing.is_set():
                try:
                    item = self._out.get(timeout=0.05)
                except queue.Empty:
                    continue
                latest: LoopSnapshot | None = None
                while True:  # behind: answer everything, publish only the latest values
                    if isinstance(item, Doorbell):
                        latest = item.answer()
                    else:
                        self._answer(item)
                    try:
                        item = self._out.get_nowait()
                    except queue.Empty:
                        break
                if latest is not None:
                    self._publish(latest)
                    self._publish_events(latest)
        except BaseException as err:  # the share ends; the loop goes on
            self.error = err

    def _answer(self, a: _Answer) -> None:
        payload = keys.dumps(a.doc)
        if a.ok:
            a.query.reply(a.query.key_expr, payload, encoding=JSON)
        else:
            a.query.reply_err(payload, encoding=JSON)
        a.query.drop()

    def _publish(self, loop: LoopSnapshot) -> None:
        if not self._declared:
            self.declare()
            if not self._declared:
                return  # not checked yet
        snap = loop.values
        if self._state == "starting" and loop.running:
            self._state = "running"
            for board in self._board_pubs:
                if board not in loop.lost:
                    self._alive(board, True)
            self._event({"kind": "state", "state": "running", "t": snap.clock})
        if self._encoders is None:  # once: the boards are configured now
            assert self._image is not None
            self._encoders = encoders(self._image, self.robot)
        now = time.monotonic()
        for board, (k, pub) in self._board_pubs.items():
            self._clear_of_the_loop()
            lost = loop.lost.get(board)
            payload = self._encoders[board].sample(
                snap, None if lost is None else (loop.on_stamps(lost.since), lost.seen))
            if payload == self._latest.get(k) and now - self._put_at.get(k, 0.0) < RESEND_S:
                continue  # nothing new on this board: its latest stays where it is
            self._latest[k] = payload
            self._put_at[k] = now
            pub.put(payload)
            self.published += 1
        if self._status_frames:
            self._publish_status()
        for k in list(self._matched):  # the edges someone subscribes to (few)
            ref, pub = self._edge_by_key[k]
            edge = self._encoders[(ref.bus, ref.board)].edge_sample(
                ref, snap, (ref.bus, ref.board) not in loop.lost)
            if edge is None or (edge == self._edge_latest.get(k)
                                and now - self._put_at.get(k, 0.0) < RESEND_S):
                continue
            self._edge_latest[k] = edge
            self._put_at[k] = now
            pub.put(edge)
            self.published += 1

    def _alive(self, board: BoardKey, alive: bool) -> None:
        """The board's liveliness token: there while it runs, gone while it is lost or
        stopped."""
        token = self._board_tokens.pop(board, None)
        if token is not None and not alive:
            token.undeclare()
        elif alive:
            self._board_tokens[board] = token or self.session.liveliness().declare_token(
                keys.board_key(self.robot, *board, what="board_alive"))

    def _clear_of_the_loop(self) -> None:
        """Wait out the loop's next deadline when it is about to come (real buses)."""
        deadline = self.source.next_deadline()
        if deadline is not None:
            gap = deadline - time.monotonic()
            if 0.0 < gap < CLEAR_OF_DEADLINE_S:
                time.sleep(gap + AFTER_DEADLINE_S)

    def _publish_status(self) -> None:
        """The Status reports that came, each as its board's ``status`` sample."""
        frames = self._status_frames
        while frames:
            bus, arbitration_id, data, t = frames.popleft()
            try:
                address, msg = m.decode(arbitration_id, data,
                                        sender=Direction.BOARD_TO_HOST)
            except FrameError:
                continue  # malformed: the loop's own decoding counts it
            if address.id_type is not IdType.SEQUENTIAL:
                continue
            pub = self._status_pubs.get((bus, address.number))
            if pub is not None and isinstance(msg, m.StatusReport):
                pub.put(keys.dumps({"robot": self.robot, "bus": bus,
                                    "board": address.number, **status_doc(msg, t)}))
                self.published += 1

    def _event(self, doc: dict[str, Any]) -> None:
        self._events.put(keys.dumps({"robot": self.robot, **doc}))

    def _publish_events(self, snap: LoopSnapshot) -> None:
        """The run's events that came since the last snapshot: the boards' Errors, the
        writes and stops from the network, the boards lost and rejoined."""
        for e in snap.newer(snap.events, snap.events_total, self._events_seen):
            self._event({"kind": "board", "t": e.time, "bus": e.bus, "board": e.board,
                         "where": e.where, "error": e.code.name, "text": e.text,
                         "stopped_motors": e.stopped_motors})
            if e.stopped_motors:  # stopped until started again: not alive
                self._alive((e.bus, e.board), False)
        self._events_seen = snap.events_total
        for w in snap.newer(snap.writes, snap.writes_total, self._writes_seen):
            self._event({"kind": "stop" if w.value == "stop" and not w.name else "write",
                         "t": w.time, "name": w.name, "value": w.value, "origin": w.origin,
                         "result": w.result})
        self._writes_seen = snap.writes_total
        for f in snap.newer(snap.faults, snap.faults_total, self._faults_seen):
            self._event(fault_doc(f, snap.on_stamps(f.time)))
            if self._state == "running" and (f.bus, f.board) in self._board_pubs:
                self._alive((f.bus, f.board), f.event == "rejoined")
        self._faults_seen = snap.faults_total

    # ------------------------------------------------------------------ the end
    def close(self) -> None:
        """Stop publishing, answer what is still queued, say the robot stopped, and close
        the session (its liveliness tokens go with it)."""
        if self._closing.is_set():
            return
        self._closing.set()
        self._thread.join(CLOSE_S)
        with contextlib.suppress(ValueError):
            self.source.status_sinks.remove(self._take_status)
        if self.owns_source:
            self.source.close()  # what is still asked: answered as refused
        try:
            while True:
                try:
                    item = self._out.get_nowait()
                except queue.Empty:
                    break
                if isinstance(item, _Answer):
                    self._answer(item)
            self._bell.close()
            final = self.source.final()
            if final is not None:
                self._publish_events(final)
            self._event({"kind": "state", "state": "stopped",
                         "t": round(final.clock if final is not None else 0.0, 6)})
        except (zenoh.ZError, UcomError):
            pass
        finally:
            self.session.close()

    def stats(self) -> dict[str, Any]:
        """For ``remote run --json``: where, how often, how much."""
        return {"endpoint": self.endpoint, "joined": self.joined,
                "publish_hz": round(self.publish_hz, 3), "allow_writes": self.allow_writes,
                "published": self.published, "writes": self._writes_seen,
                "error": None if self.error is None else str(self.error)}

