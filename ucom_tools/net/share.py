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

Off the loop's critical path: the loop's thread only takes a snapshot every few cycles
(:meth:`RemotePart.snapshot`: references and small dict copies) and hands it to the
publishing thread through a queue, and applies the writes the network queued; it never
waits for the network.  Encoding (from parts prepared once, :mod:`.encode`: the
publishing thread holds the GIL the loop needs as briefly as it can) and every Zenoh
call happen on the publishing thread (or on Zenoh's own threads, for the queries).

One robot, one loop: where the robot's liveliness token is already on the network (or a
ucom robot of that name listens on the endpoint) :func:`share` refuses (BusError),
unless ``force``.
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
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import zenoh

from ucom_tools.errors import BusError, FrameError, InputError, UcomError
from ucom_tools.net import keys
from ucom_tools.net.encode import BoardEncoder, encoders
from ucom_tools.net.session import address_in_use, check_endpoint, config, open_session
from ucom_tools.ops.edges import EdgeRef
from ucom_tools.ops.remote import RawSnapshot, RemotePart, RemoteStop, WriteEvent
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import ReportChannel
from ucom_tools.wire.ids import Direction, Function, IdType, seq

JSON = zenoh.Encoding.APPLICATION_JSON
PROBE_S = 1.0
"""How long a new share looks for the robot's liveliness token elsewhere on the network."""
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
STATUS_PERIOD_S = 1.0
"""Each running board is asked for its Status report (state, LEDs, CAN error counters,
overruns) once in this long, the boards one after the other (ARMAR-III: a Report Request
every 91 ms, 0.1 % of a bus's capacity)."""


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


def _is_status(msg: can.Message) -> bool:
    return not msg.is_extended_id and msg.arbitration_id >> 6 == Function.REPORT_0


def origin() -> str:
    """Who this process is, for the robot's events: ``user@host pid N``."""
    try:
        user = getpass.getuser()
    except (KeyError, OSError):
        user = "?"
    return f"{user}@{socket.gethostname()} pid {os.getpid()}"


@dataclass
class _Request:
    """A write (or stop) from the network, queued for the loop's thread."""

    query: zenoh.Query
    name: str
    value: Any
    origin: str
    stop: bool = False


@dataclass
class _Answer:
    """What the loop's thread made of a request, for the publishing thread to send."""

    query: zenoh.Query
    ok: bool
    doc: dict[str, Any]
    event: WriteEvent


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
    s = RobotShare(part, endpoint=endpoint, config_file=config_file,
                   allow_writes=allow_writes, publish_hz=publish_hz, force=force)
    part.share = s
    part.each_cycle.append(s.on_cycle)
    if part.report is not None:
        s.declare()  # the names are known: declared now, not while the loop runs
    return s


class RobotShare:
    """One robot's run time on Zenoh (see the module docstring)."""

    def __init__(self, part: RemotePart, *, endpoint: str | None = None,
                 config_file: str | Path | None = None, allow_writes: bool = False,
                 publish_hz: float = 100.0, force: bool = False) -> None:
        assert part.robot.topology is not None
        loop_hz = 1.0 / part.period_s
        if not 0 < publish_hz <= loop_hz * 1.0001:
            raise InputError(f"the publishing rate must be more than 0 and at most the loop's "
                             f"rate ({loop_hz:g} Hz), not {publish_hz:g}", key="--publish-rate")
        self.part = part
        self.robot = keys.robot_id(part.robot.topology.source, part.robot.topology.name)
        """The robot's chunk of the keys (``armar3``)."""
        self.allow_writes = allow_writes
        self.publish_hz = loop_hz / max(1, round(loop_hz / publish_hz))
        self._every = max(1, round(loop_hz / publish_hz))
        self._countdown = 1
        if endpoint is None and config_file is None:
            endpoint = keys.DEFAULT_ENDPOINT
        self.endpoint = check_endpoint(endpoint) if endpoint is not None else None
        self.joined: str | None = None
        """The endpoint this share connected to instead of listening (``force``: another
        loop of the robot listens there)."""
        self.started = time.time()
        self.session = self._open(config_file, force)
        self.where = self.endpoint or str(config_file)
        try:
            if not force:
                other = self._other(self.session)
                if other is not None:
                    raise BusError(self._refusal(other))
            self._requests: queue.SimpleQueue[_Request] = queue.SimpleQueue()
            self._out: queue.SimpleQueue[RawSnapshot | _Answer] = queue.SimpleQueue()
            self._matched: set[str] = set()
            self._latest: dict[str, bytes] = {}
            self._edge_latest: dict[str, bytes] = {}
            self._put_at: dict[str, float] = {}
            self._encoders: dict[tuple[str, int], BoardEncoder] | None = None
            self._declared = False
            self._lock = threading.Lock()
            self._closing = threading.Event()
            self._board_tokens: dict[tuple[str, int], zenoh.LivelinessToken] = {}
            self._edge_pubs: dict[EdgeRef, tuple[str, zenoh.Publisher]] = {}
            self._edge_by_key: dict[str, tuple[EdgeRef, zenoh.Publisher]] = {}
            self._listeners: list[Any] = []
            self._board_pubs: dict[tuple[str, int], tuple[str, zenoh.Publisher]] = {}
            self._structure: bytes | None = None
            self._status_frames: deque[tuple[str, int, bytes, float]] = deque()
            """The Status report frames the loop's thread saw (bus, identifier, data,
            time), for the publishing thread to decode."""
            self._status_pubs: dict[tuple[str, int], zenoh.Publisher] = {}
            self._status_subs: list[tuple[Any, Any]] = []
            self._polled: list[tuple[str, int]] = []
            self._poll_at = 0
            self._poll_every = 1
            self._events_seen = 0
            self._writes_seen = 0
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

    # ------------------------------------------------------------------ opening
    def _open(self, config_file: str | Path | None, force: bool) -> zenoh.Session:
        listen = [self.endpoint] if self.endpoint is not None else None
        try:
            return open_session(config(listen=listen, file=config_file),
                                self.endpoint or str(config_file))
        except BusError as err:
            if self.endpoint is None or not address_in_use(err):
                raise
            other = self._probe(self.endpoint, config_file)
            if other is None:
                raise BusError(f"cannot listen on {self.endpoint}: the address is in use "
                               "(and no ucom robot of that name answers there)") from None
            if not force:
                raise BusError(self._refusal(other)) from None
            self.joined = self.endpoint  # --force: join that network as a peer
            return open_session(config(listen=[], connect=[self.endpoint], file=config_file,
                                       connect_timeout_s=PROBE_S), self.endpoint)

    def _probe(self, endpoint: str, config_file: str | Path | None) -> dict[str, Any] | None:
        """The structure of this robot's loop that listens on ``endpoint``, if one does."""
        try:
            s = open_session(config(listen=[], connect=[endpoint], file=config_file,
                                    connect_timeout_s=PROBE_S), endpoint)
        except BusError:
            return None
        try:
            return self._other(s)
        finally:
            s.close()

    def _other(self, s: zenoh.Session) -> dict[str, Any] | None:
        """Another loop of this robot reachable from session ``s``: its structure (or an
        empty one where it does not answer), None where there is none."""
        if not s.info.peers_zid() and not s.info.routers_zid():
            return None
        deadline = time.monotonic() + PROBE_S
        found = False
        while not found and time.monotonic() < deadline:
            found = any(r.ok is not None for r in s.liveliness().get(
                keys.robot_key(self.robot, "alive"), timeout=PROBE_S))
            if not found:
                time.sleep(0.05)  # the peer's declarations may still be on their way
        if not found:
            return None
        for r in s.get(keys.robot_key(self.robot, "structure"), timeout=PROBE_S):
            if r.ok is not None:
                try:
                    return keys.loads(r.ok.payload.to_bytes())
                except ValueError:
                    pass
        return {}

    def _refusal(self, other: dict[str, Any]) -> str:
        who = ", ".join(f"{k} {other[k]}" for k in ("host", "pid", "listen") if other.get(k))
        since = other.get("started")
        when = f", since {time.strftime('%H:%M:%S', time.localtime(since))}" \
            if isinstance(since, int | float) else ""
        return (f"robot {self.robot!r} already runs its loop on this Zenoh network"
                f"{' (' + who + when + ')' if who or when else ''}, reached on "
                f"{self.endpoint or 'the configured endpoints'}: one robot, one loop; stop "
                "that one first (or --force)")

    # ------------------------------------------------------------------ declarations
    def declare(self) -> None:
        """Build the structure and declare what needs the edges' names (the part has been
        checked): the robot's liveliness token, a publisher per board and per edge, and
        the edges' matching listeners.  Done by :func:`share` where the part is checked
        already, else by the publishing thread."""
        with self._lock:
            if self._declared:
                return
            part, s = self.part, self.session
            self._structure = keys.dumps(self._structure_doc())
            for ref in part.names:
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
            self._polled = sorted(self._board_pubs)
            self._poll_every = max(1, round(STATUS_PERIOD_S / part.period_s
                                            / max(1, len(self._polled))))
            for name, h in part.robot.buses.items():
                d = h.link.dispatcher
                self._status_subs.append((d, d.subscribe(
                    _is_status, "zenoh status", on_frame=self._status_taker(name))))
            self._token = s.liveliness().declare_token(keys.robot_key(self.robot, "alive"))
            self._declared = True

    def _status_taker(self, bus: str) -> Callable[[can.Message], None]:
        frames = self._status_frames

        def take(msg: can.Message) -> None:  # the loop's thread: keep it, decode later
            frames.append((bus, msg.arbitration_id, bytes(msg.data), msg.timestamp))
        return take

    def _matching(self, key: str) -> Callable[[zenoh.MatchingStatus], None]:
        def changed(status: zenoh.MatchingStatus) -> None:
            if status.matching:
                self._edge_latest.pop(key, None)  # a new subscriber: the next value goes
                self._matched.add(key)
            else:
                self._matched.discard(key)
        return changed

    def _structure_doc(self) -> dict[str, Any]:
        part = self.part
        checks = {(b.bus, b.board): b for b in (part.report.boards if part.report else ())}
        buses: dict[str, dict[str, Any]] = {}
        boards: dict[tuple[str, int], dict[str, Any]] = {}
        for name, h in part.robot.buses.items():
            buses[name] = {"name": name, "bitrate": h.link.bitrate, "boards": []}
        for ref in part.names:
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
                "robot_name": part.names.name_of(ref), "kind": ref.kind.name,
                "unit": spec.unit, "min": keys.number(ref.value(spec.minimum)),
                "max": keys.number(ref.value(spec.maximum)), "range": ref.describe_range(),
                "encoding": {"width": spec.width, "signed": spec.signed,
                             "exponent": spec.exponent, "raw_min": spec.minimum,
                             "raw_max": spec.maximum},
                "cyclic": part.cyclic(ref), "writable": ref.kind is not mca.Kind.SO,
                "key": keys.edge_key(self.robot, ref.bus, ref.board, ref.unique)})
        assert part.robot.topology is not None
        return {"robot": self.robot, "name": part.robot.topology.name,
                "host": socket.gethostname(), "pid": os.getpid(),
                "listen": self.endpoint if self.joined is None else None,
                "started": round(self.started, 3), "rate_hz": round(1 / part.period_s, 3),
                "publish_hz": round(self.publish_hz, 3), "allow_writes": self.allow_writes,
                "virtual_time": part.virtual, "zid": str(self.session.zid()),
                "buses": [b for b in buses.values() if b["boards"]]}

    # ------------------------------------------------------------------ the loop's side
    def on_cycle(self) -> None:
        """The loop's thread, every cycle: apply what the network queued, and every
        publishing period hand a snapshot over.  Never waits."""
        if not self._requests.empty():
            self._apply()
        self._countdown -= 1
        if self._countdown <= 0:
            self._countdown = self._every
            self._out.put(self.part.snapshot())
        if self._polled:
            self._poll_at -= 1
            if self._poll_at <= 0:
                self._poll_at = self._poll_every
                self._ask_status()

    def _ask_status(self) -> None:
        """One running board's Status report asked for (round robin; a failed send is
        the bus's business: the loop notices it itself)."""
        bus, board = self._polled[0]
        self._polled.append(self._polled.pop(0))
        if self._state != "running" or (bus, board) not in self._board_tokens:
            return
        h = self.part.robot.buses.get(bus)
        if h is None:
            return
        with contextlib.suppress(UcomError):
            h.link.send(m.ReportRequest(ReportChannel.STATUS), seq(board))

    def _apply(self) -> None:
        part = self.part
        while True:
            try:
                r = self._requests.get_nowait()
            except queue.Empty:
                return
            t = round(part._clock() - part.stats.started_clock, 4)
            if r.stop:
                event = WriteEvent(t, "", "stop", r.origin, "done")
                part.writes.append(event)
                self._out.put(_Answer(r.query, True, {"ok": True, "done": "stopping"},
                                      event))
                raise RemoteStop(r.origin)
            try:
                ref = part.set(r.name, r.value)
            except InputError as err:
                result, ok = err.reason, False
                doc: dict[str, Any] = {"ok": False, "error": "refused", "message": err.reason}
            except UcomError as err:  # a PAR write the board did not acknowledge
                result, ok = str(err), False
                doc = {"ok": False, "error": "failed", "message": str(err)}
            else:
                result, ok = "done", True
                doc = {"ok": True, "done": "set", "name": part.names.name_of(ref),
                       "value": keys.number(part[part.names.name_of(ref)]),
                       "range": ref.describe_range(), "unit": ref.spec.unit}
            event = WriteEvent(t, r.name, str(r.value), r.origin, result)
            part.writes.append(event)
            self._out.put(_Answer(r.query, ok, doc, event))

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
        if self._closing.is_set() or not self.part.running:
            query.reply_err(keys.dumps({"ok": False, "error": "stopped",
                                        "message": "the loop is not running"}),
                            encoding=JSON)
            return
        try:
            doc = keys.loads(query.payload.to_bytes() if query.payload is not None else b"{}")
            who = str(doc.get("origin") or "unknown")
            if stop:
                self._requests.put(_Request(query, "", None, who, stop=True))
                return
            name, value = doc.get("name"), doc.get("value")
            if not isinstance(name, str) or isinstance(value, bool) \
                    or not isinstance(value, int | float | str):
                raise ValueError('expected {"v": 1, "name": NAME, "value": NUMBER}')
        except ValueError as err:
            query.reply_err(keys.dumps({"ok": False, "error": "refused",
                                        "message": f"not a write: {err}"}), encoding=JSON)
            return
        self._requests.put(_Request(query, name, value, who))

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
                    self._publish_events()
                    continue
                latest: RawSnapshot | None = None
                while True:  # behind: answer everything, publish only the latest values
                    if isinstance(item, RawSnapshot):
                        latest = item
                    else:
                        self._answer(item)
                    try:
                        item = self._out.get_nowait()
                    except queue.Empty:
                        break
                if latest is not None:
                    self._publish(latest)
                self._publish_events()
        except BaseException as err:  # the share ends; the loop goes on
            self.error = err

    def _answer(self, a: _Answer) -> None:
        payload = keys.dumps(a.doc)
        if a.ok:
            a.query.reply(a.query.key_expr, payload, encoding=JSON)
        else:
            a.query.reply_err(payload, encoding=JSON)
        a.query.drop()

    def _publish(self, snap: RawSnapshot) -> None:
        if not self._declared:
            self.declare()
        part = self.part
        if self._state == "starting" and part.running:
            self._state = "running"
            for board in self._board_pubs:
                self._board_tokens[board] = self.session.liveliness().declare_token(
                    keys.board_key(self.robot, *board, what="board_alive"))
            self._event({"kind": "state", "state": "running", "t": snap.clock})
        if self._encoders is None:  # once: the boards are configured now
            self._encoders = encoders(part, self.robot)
        now = time.monotonic()
        for board, (k, pub) in self._board_pubs.items():
            self._clear_of_the_loop()
            payload = self._encoders[board].sample(snap)
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
            edge = self._encoders[(ref.bus, ref.board)].edge_sample(ref, snap)
            if edge is None or (edge == self._edge_latest.get(k)
                                and now - self._put_at.get(k, 0.0) < RESEND_S):
                continue
            self._edge_latest[k] = edge
            self._put_at[k] = now
            pub.put(edge)
            self.published += 1

    def _clear_of_the_loop(self) -> None:
        """Wait out the loop's next deadline when it is about to come (real buses)."""
        deadline = self.part.next_deadline
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

    def _publish_events(self) -> None:
        part = self.part
        while self._events_seen < len(part.events):
            e = part.events[self._events_seen]
            self._events_seen += 1
            self._event({"kind": "board", "t": e.time, "bus": e.bus, "board": e.board,
                         "where": e.where, "error": e.code.name, "text": e.text,
                         "stopped_motors": e.stopped_motors})
            if e.stopped_motors:  # stopped until started again: not alive
                token = self._board_tokens.pop((e.bus, e.board), None)
                if token is not None:
                    token.undeclare()
        while self._writes_seen < len(part.writes):
            w = part.writes[self._writes_seen]
            self._writes_seen += 1
            self._event({"kind": "stop" if w.value == "stop" and not w.name else "write",
                         "t": w.time, "name": w.name, "value": w.value, "origin": w.origin,
                         "result": w.result})

    # ------------------------------------------------------------------ the end
    def close(self) -> None:
        """Stop publishing, answer what is still queued, say the robot stopped, and close
        the session (its liveliness tokens go with it)."""
        if self._closing.is_set():
            return
        self._closing.set()
        self._thread.join(CLOSE_S)
        for d, sub in self._status_subs:
            d.unsubscribe(sub)
        try:
            while True:
                try:
                    item = self._out.get_nowait()
                except queue.Empty:
                    break
                if isinstance(item, _Answer):
                    self._answer(item)
            while True:
                try:
                    r = self._requests.get_nowait()
                except queue.Empty:
                    break
                r.query.reply_err(keys.dumps({"ok": False, "error": "stopped",
                                              "message": "the loop stopped"}), encoding=JSON)
                r.query.drop()
            self._publish_events()
            self._event({"kind": "state", "state": "stopped",
                         "t": round(self.part._clock(), 6)})
        except (zenoh.ZError, UcomError):
            pass
        finally:
            self.session.close()

    def stats(self) -> dict[str, Any]:
        """For ``remote run --json``: where, how often, how much."""
        return {"endpoint": self.endpoint, "joined": self.joined,
                "publish_hz": round(self.publish_hz, 3), "allow_writes": self.allow_writes,
                "published": self.published, "writes": len(self.part.writes),
                "error": None if self.error is None else str(self.error)}

