"""The Foxglove WebSocket server of a run (``remote run --foxglove``, ``browse
--foxglove``): foxglove-sdk's server, in a :class:`foxglove.Context` of its own (another
sink of the SDK in this process, an MCAP recording, sees none of its channels), fed by
:mod:`.foxglove_feed` from the snapshots and frames a run hands over.

What it costs and what it avoids (``/work``'s measurements, ``man/ucom.1``, FOXGLOVE):

- nothing is encoded for a channel no client subscribes to: every message is built only
  after its channel's :meth:`has_sinks <foxglove.Channel.has_sinks>` said someone listens
  (the SDK encodes whatever it is given, listened to or not); :attr:`FoxgloveServer.
  encoded` counts what was;
- the SDK's server never sets TCP_NODELAY (Nagle's algorithm held small messages back
  13-24 ms at p99): its sockets are this process's file descriptors, so when a client
  subscribes, :func:`nodelay` (on a thread of the server's, never the SDK's callback)
  finds the connected sockets of the server's port and sets
  the option on them (Linux's ``/proc/self/fd``; elsewhere it says it could not);
- the server speaks only the subprotocol ``foxglove.sdk.v1`` (Lichtblick releases before
  late 2025 cannot connect).

Writes: a client's ``/set`` messages (``{"name": NAME, "value": NUMBER}``; the app's
Publish panel, schema ``ucom.Set``) and its parameter writes (the Parameters panel lists
the CI and PAR edges by robot-wide name) are taken only with ``allow_writes`` and then
checked and applied as a local ``--set`` (:attr:`FoxgloveServer.writer`); without it
each is refused and said so on ``/events`` and in the client's status bar.  The
server's own ``/set`` channel (advertised with the schema ``ucom.Set``, so that the
Publish panel finds it) carries each write it applied.  A write the loop refused is on
``/events`` once, as the loop reports it (the feed's events), not again by the server.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import socket
import stat
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from ucom_tools.errors import BusError
from ucom_tools.net.keys import number
from ucom_tools.ops.remote.requests import Applied
from ucom_tools.viewers import foxglove_msgs as fm

if TYPE_CHECKING:
    from foxglove import Parameter
    from foxglove.websocket import (
        ChannelView,
        Client,
        ClientChannel,
        PlaybackControlRequest,
        PlaybackState,
    )

Writer = Callable[[str, object, str], Applied]
"""Apply a write (name, value, origin): what came of it."""
Reader = Callable[[list[str] | None], dict[str, Any]]
"""The current values of the CI and PAR edges named (None: all of them), by name."""


def nodelay(port: int) -> int:
    """Set TCP_NODELAY on every connected TCP socket of this process whose local port is
    ``port`` (the server's clients): how many it set (0 where none or no ``/proc``)."""
    try:
        fds = os.listdir("/proc/self/fd")
    except OSError:
        return 0
    done = 0
    for name in fds:
        try:
            fd = int(name)
            if not stat.S_ISSOCK(os.fstat(fd).st_mode):
                continue
            s = socket.socket(fileno=os.dup(fd))  # the same socket: its options are shared
        except (OSError, ValueError):
            continue  # closed meanwhile, or not a socket
        with s:
            try:
                if (s.type != socket.SOCK_STREAM
                        or s.family not in (socket.AF_INET, socket.AF_INET6)
                        or s.getsockname()[1] != port):
                    continue
                s.getpeername()  # connected: a client's, not the listening socket
                if not s.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY):
                    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    done += 1
            except OSError:
                continue
    return done


class FoxgloveServer:
    """One Foxglove WebSocket server (see the module docstring), listening on ``host``:
    ``port`` once constructed (BusError where it cannot: the address is in use, the
    host is not this machine's)."""

    def __init__(self, host: str, port: int, *, name: str, allow_writes: bool) -> None:
        import foxglove
        from foxglove.websocket import Capability

        self.host, self.allow_writes = host, allow_writes
        self.context = foxglove.Context()
        self.channels: dict[str, Any] = {}
        self.encoded: dict[str, int] = {}
        """Topic -> messages encoded and logged (only while a client subscribed)."""
        self.refused = 0
        """Writes from clients refused (no ``allow_writes``, or the loop refused them)."""
        self.applied = 0
        self.nodelay_sockets = 0
        self.writer: Writer | None = None
        self.reader: Reader | None = None
        self.clock = fm.WallClock()
        self._client_topics: dict[tuple[int, int], str] = {}
        self._lock = threading.Lock()
        self._closing = False
        self._nodelay_wanted = threading.Event()
        try:
            self.server = foxglove.start_server(
                name=name, host=host, port=port, context=self.context,
                capabilities=[Capability.ClientPublish, Capability.Parameters],
                supported_encodings=["json"], server_listener=_Listener(self))
        except RuntimeError as err:
            why = str(err).removeprefix("FoxgloveError: ")
            raise BusError(f"the Foxglove server on {address_text(host, port)}: cannot "
                           f"serve there: {why}") from None
        self.port = self.server.port
        threading.Thread(target=self._nodelay_run, name="ucom-foxglove-nodelay",
                         daemon=True).start()
        self.events = self.channel(fm.EVENTS_TOPIC, fm.LOG_SCHEMA)
        self.sets = self.channel(fm.SET_TOPIC, fm.SET_SCHEMA)
        self._log = _ToEvents(self)  # the SDK's own warnings: on /events, not the terminal
        sdk_log = logging.getLogger("foxglove")
        sdk_log.addHandler(self._log)
        sdk_log.propagate = False

    @property
    def url(self) -> str:
        return f"ws://{address_text(self.host, self.port)}"

    def channel(self, topic: str, schema: dict[str, Any]) -> Any:
        """A JSON channel of this server (advertised to clients at once)."""
        import foxglove

        ch = self.channels[topic] = foxglove.Channel(topic, schema=schema,
                                                     context=self.context)
        self.encoded.setdefault(topic, 0)
        return ch

    def send(self, ch: Any, ns: int, text: str | bytes) -> None:
        """Log ``text`` on ``ch`` at ``ns`` (the caller asked :meth:`wants` first)."""
        ch.log(text.encode() if isinstance(text, str) else text, log_time=ns)
        self.encoded[ch.topic()] += 1

    @staticmethod
    def wants(ch: Any) -> bool:
        """Does a client subscribe to ``ch``? (Nothing is built for it otherwise.)"""
        return bool(ch.has_sinks())

    def note(self, level: int, text: str, ns: int | None = None) -> None:
        """An event of this server's own on ``/events`` (a write refused ...)."""
        if self.wants(self.events):
            self.send(self.events, ns if ns is not None else fm.now_ns(),
                      fm.log_json(ns if ns is not None else fm.now_ns(), level, text))

    # ------------------------------------------------------------------ writes
    def write(self, client: int, name: object, value: object) -> Applied:
        """A client's write, refused without ``allow_writes`` (said on ``/events`` and to
        the client), else checked and applied as a local ``--set``."""
        origin = f"foxglove client {client} on {socket.gethostname()}:{self.port}"
        # is the answer on /events already? (the loop reports every write it was asked,
        # applied or refused, among its events; a robot shared on the network publishes
        # them)
        reported = False
        if not isinstance(name, str) or isinstance(value, bool) \
                or not isinstance(value, int | float | str):
            applied = Applied("refused", 'not a write: expected {"name": NAME, "value": '
                              f"NUMBER}}, got name {name!r}, value {value!r}")
        elif not self.allow_writes or self.writer is None:
            applied = Applied("forbidden", f"set {name} = {value} from {origin} refused: "
                              "this run takes no writes from Foxglove (run it with "
                              "--allow-writes)")
        else:
            applied = self.writer(name, value, origin)
            reported = applied.event is not None or applied.error == "refused"
        if applied.ok:
            self.applied += 1
            if self.wants(self.sets):
                ns = fm.now_ns()
                self.send(self.sets, ns, json.dumps(
                    {"name": applied.name or name,
                     "value": number(applied.value) if applied.value is not None
                     else value}, separators=(",", ":")))
            return applied
        self.refused += 1
        if not reported:
            self.note(fm.LOG_WARNING, applied.message)
        with contextlib.suppress(Exception):
            from foxglove import StatusLevel

            self.server.publish_status(applied.message, StatusLevel.Warning)
        return applied

    def client_topic(self, client: int, channel: int, topic: str | None) -> str | None:
        with self._lock:
            if topic is None:
                return self._client_topics.pop((client, channel), None)
            self._client_topics[(client, channel)] = topic
            return topic

    def on_subscribed(self) -> None:
        """A client subscribed (the SDK's thread): its socket gets TCP_NODELAY on a thread
        of this server's, not here: the SDK takes the next subscription only when this
        returns, and a scan of this process's sockets waits for the GIL at every step
        while the feed's thread computes (a client's later subscriptions came seconds
        late in a busy CI run)."""
        self._nodelay_wanted.set()

    def _nodelay_run(self) -> None:
        while True:
            self._nodelay_wanted.wait()
            if self._closing:
                return
            self._nodelay_wanted.clear()
            n = nodelay(self.port)
            with self._lock:
                self.nodelay_sockets += n

    # ------------------------------------------------------------------ the end
    def close(self) -> None:
        self._closing = True
        self._nodelay_wanted.set()
        with contextlib.suppress(Exception):
            self.server.stop()
        logging.getLogger("foxglove").removeHandler(self._log)

    def stats(self) -> dict[str, Any]:
        """For ``remote run --json``: where, and what was encoded per topic."""
        return {"url": self.url, "allow_writes": self.allow_writes,
                "encoded": {t: n for t, n in self.encoded.items() if n},
                "encoded_total": sum(self.encoded.values()),
                "writes_applied": self.applied, "writes_refused": self.refused,
                "nodelay_sockets": self.nodelay_sockets}


def address_text(host: str, port: int) -> str:
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


class _Listener:
    """The SDK's callbacks (its threads): subscriptions, a client's channels and
    messages, parameters."""

    def __init__(self, server: FoxgloveServer) -> None:
        self.s = server

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        self.s.on_subscribed()

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        return None

    def on_client_advertise(self, client: Client, channel: ClientChannel) -> None:
        self.s.client_topic(client.id, channel.id, channel.topic)

    def on_client_unadvertise(self, client: Client, client_channel_id: int) -> None:
        self.s.client_topic(client.id, client_channel_id, None)

    def on_message_data(self, client: Client, client_channel_id: int, data: bytes) -> None:
        topic = self.s._client_topics.get((client.id, client_channel_id))
        if topic != fm.SET_TOPIC:
            return  # a topic of no meaning here
        try:
            doc = json.loads(data)
        except ValueError:
            doc = None
        if not isinstance(doc, dict):
            self.s.write(client.id, None, data[:60].decode(errors="replace"))
            return
        self.s.write(client.id, doc.get("name"), doc.get("value"))

    def on_get_parameters(self, client: Client, param_names: list[str],
                          request_id: str | None = None) -> list[Parameter]:
        return _parameters(self.s, param_names or None)

    def on_set_parameters(self, client: Client, parameters: list[Parameter],
                          request_id: str | None = None) -> list[Parameter]:
        done = {}
        for p in parameters:
            applied = self.s.write(client.id, p.name, p.get_value())
            if applied.ok and applied.value is not None:
                done[p.name] = number(applied.value)  # as the loop set it
        return _parameters(self.s, [p.name for p in parameters if p.name not in done],
                           done)

    def on_parameters_subscribe(self, param_names: list[str]) -> None:
        return None

    def on_parameters_unsubscribe(self, param_names: list[str]) -> None:
        return None

    def on_connection_graph_subscribe(self) -> None:
        return None

    def on_connection_graph_unsubscribe(self) -> None:
        return None

    def on_playback_control_request(self, playback_control_request: PlaybackControlRequest
                                    ) -> PlaybackState | None:
        return None


def _parameters(s: FoxgloveServer, names: list[str] | None,
                done: dict[str, Any] | None = None) -> list[Parameter]:
    """The CI and PAR values asked for, as parameters (none before the boards run), and
    those just set (``done``)."""
    from foxglove import Parameter as Param

    values: dict[str, Any] = {}
    if s.reader is not None and (names is None or names):
        try:
            values = s.reader(names)
        except Exception:  # the robot does not answer: no values now
            values = {}
    values.update(done or {})
    return [Param(n, value=v) for n, v in values.items() if v is not None]


class _ToEvents(logging.Handler):
    """The SDK's log (a client that went away without closing, ...) as the server's
    events, at warning and above, and as warnings: what the SDK calls an error is about
    a client's connection ("Connection reset by peer" where a browser tab closed), never
    the robot; never on the terminal a live view owns."""

    def __init__(self, server: FoxgloveServer) -> None:
        super().__init__(logging.WARNING)
        self.server = server

    def emit(self, record: logging.LogRecord) -> None:
        with contextlib.suppress(Exception):
            self.server.note(fm.LOG_WARNING, f"foxglove: {record.getMessage()}")
