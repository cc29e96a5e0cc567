"""``ucom fleet serve`` against hostile socketcand clients: none of them stops the bus.

An in-process :class:`FleetServer` on 127.0.0.1 serves a real-time fleet.  Hostile
clients are raw sockets; after each hostile act a well-behaved client still enumerates
the init chain (Init Request BEGIN, the first board's Init Ack ``0C1``, END).  Every wait
has a deadline: socket timeouts for data, ``join(timeout)`` for threads, a condition on
the server's log records for what only the server sees.  No test may leave a traceback
on the server (log records, uncaught thread exceptions, stderr).
"""

from __future__ import annotations

import contextlib
import logging
import re
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator

import can
import pytest

from ucom_tools.virtual.fleet import Fleet
from ucom_tools.virtual.serve.socketcand import FleetServer
from ucom_tools.wire.socketcand import (
    MAX_ELEMENT,
    ElementError,
    ElementSplitter,
    ElementTooLong,
    parse_send,
)

DEADLINE_S = 5.0
INIT_BEGIN = "< send 280 2 01 00 >"
INIT_END = "< send 280 2 03 00 >"
FILLER = b"< send 7C0 0 >"
"""A frame every board ignores (function 31 is unassigned; broadcast, so no error)."""


# ---------------------------------------------------------------------- watching the server
class ServerLog(logging.Handler):
    """Collects the records of the ``ucom`` loggers; tests wait for them by content."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []
        self.expected: list[logging.LogRecord] = []
        self.changed = threading.Condition()

    def emit(self, record: logging.LogRecord) -> None:
        with self.changed:
            self.records.append(record)
            self.changed.notify_all()

    def find(self, text: str) -> logging.LogRecord | None:
        with self.changed:
            return next((r for r in self.records if text in r.getMessage()), None)

    def matching(self, text: str) -> list[logging.LogRecord]:
        with self.changed:
            return [r for r in self.records if text in r.getMessage()]

    def wait_for(self, text: str, timeout: float = DEADLINE_S,
                 count: int = 1) -> logging.LogRecord:
        """The first record containing ``text``, once ``count`` such records exist."""
        with self.changed:
            found = self.changed.wait_for(lambda: len(self.matching(text)) >= count, timeout)
            assert found, (f"not {count} server log records containing {text!r} in "
                           f"{timeout} s; got {[r.getMessage() for r in self.records]}")
            return self.matching(text)[0]

    def wait_gone(self, client: str) -> logging.LogRecord:
        """The record saying that ``client`` has gone (the server is done with it)."""
        with self.changed:
            found = self.changed.wait_for(lambda: self._gone(client), DEADLINE_S)
        assert found is not None, f"the server kept client {client}"
        return found

    def _gone(self, client: str) -> logging.LogRecord | None:
        return next((r for r in self.records
                     if r.getMessage().startswith((f"client {client} left",
                                                   f"dropped client {client}:"))), None)

    def tracebacks(self) -> list[str]:
        with self.changed:
            return [f"{r.name}: {r.getMessage()}" for r in self.records
                    if (r.exc_info or r.levelno >= logging.ERROR) and r not in self.expected]


@pytest.fixture(autouse=True)
def server_log(monkeypatch: pytest.MonkeyPatch,
               capsys: pytest.CaptureFixture[str]) -> Iterator[ServerLog]:
    watch = ServerLog()
    logger = logging.getLogger("ucom")
    level = logger.level
    logger.addHandler(watch)
    logger.setLevel(logging.DEBUG)
    thread_errors: list[threading.ExceptHookArgs] = []
    monkeypatch.setattr(threading, "excepthook", thread_errors.append)
    try:
        yield watch
    finally:
        logger.removeHandler(watch)
        logger.setLevel(level)
    assert not [f"{e.thread.name if e.thread else '?'}: {e.exc_type.__name__}: {e.exc_value}"
                for e in thread_errors]
    assert not watch.tracebacks()
    assert "Traceback" not in capsys.readouterr().err


@pytest.fixture
def serve() -> Iterator[Callable[..., FleetServer]]:
    """Start servers on a free loopback port, each with its own real-time fleet."""
    started: list[tuple[FleetServer, Fleet, threading.Thread]] = []

    def start(topology: str = "rosi", **options: int) -> FleetServer:
        fleet = Fleet.load(topology, realtime=True)
        try:
            server = FleetServer(fleet, "127.0.0.1", 0, **options)
        except BaseException:
            fleet.close()
            raise
        thread = threading.Thread(target=server.serve_forever, args=(0.05,), name="test-serve",
                                  daemon=True)
        thread.start()
        started.append((server, fleet, thread))
        return server

    yield start
    for server, fleet, thread in started:
        server.shutdown()
        server.server_close()
        thread.join(DEADLINE_S)
        fleet.close()
        assert not thread.is_alive()
    for t in threading.enumerate():
        if t.name.startswith("ucom-serve"):
            t.join(DEADLINE_S)
            assert not t.is_alive(), f"{t.name} still runs after the server closed"


# ---------------------------------------------------------------------- a raw client
class Client:
    """A socketcand client on a raw socket; every read has a deadline."""

    def __init__(self, address: tuple[str, int], *, rcvbuf: int | None = None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        if rcvbuf is not None:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(DEADLINE_S)
        self.sock.connect(address)
        self.pending = b""

    @property
    def name(self) -> str:
        host, port = self.sock.getsockname()[:2]
        return f"{host}:{port}"

    def send(self, data: str | bytes) -> None:
        self.sock.settimeout(DEADLINE_S)
        self.sock.sendall(data.encode("ascii") if isinstance(data, str) else data)

    def element(self, timeout: float = DEADLINE_S) -> str:
        """The next element the server sent."""
        deadline = time.monotonic() + timeout
        while True:
            start = self.pending.find(b"<")
            end = self.pending.find(b">", start + 1)
            if start >= 0 and end >= 0:
                element, self.pending = self.pending[start:end + 1], self.pending[end + 1:]
                return element.decode("ascii")
            chunk = self._receive(deadline)
            if not chunk:
                raise AssertionError(f"server closed the connection; pending {self.pending!r}")
            self.pending += chunk

    def reply(self) -> str:
        """The next element that is not a frame."""
        while (element := self.element()).startswith("< frame "):
            pass
        return element

    def frame(self, ident: str) -> list[str]:
        """The words of the next frame with identifier ``ident``."""
        while True:
            element = self.element()
            words = element[1:-1].split()
            if words[0] == "frame" and words[1] == ident:
                return words

    def until(self, reply: str) -> list[str]:
        """The elements before the next ``reply``."""
        elements = []
        while (element := self.element()) != reply:
            elements.append(element)
        return elements

    def handshake(self, bus: str = "CAN0") -> None:
        assert self.element() == "< hi >"
        self.send(f"< open {bus} >")
        assert self.reply() == "< ok >"
        self.send("< rawmode >")
        assert self.reply() == "< ok >"

    def read_until_closed(self, timeout: float = DEADLINE_S) -> bytes:
        """Everything until the server closes the connection (EOF or reset)."""
        deadline = time.monotonic() + timeout
        data = self.pending
        while True:
            try:
                chunk = self._receive(deadline)
            except ConnectionResetError:
                return data
            if not chunk:
                return data
            data += chunk

    def _receive(self, deadline: float) -> bytes:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise AssertionError(f"nothing from the server before the deadline; "
                                 f"pending {self.pending[-200:]!r}")
        self.sock.settimeout(remaining)
        try:
            return self.sock.recv(65536)
        except TimeoutError:
            raise AssertionError("nothing from the server before the deadline") from None

    def reset(self) -> None:
        """Close abruptly: the server gets a TCP reset instead of an orderly end."""
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        self.sock.close()

    def close(self) -> None:
        self.sock.close()


def enumerate_first_board(client: Client) -> None:
    """Init Request BEGIN; the first board answers Init Ack (function 3, seq ID 1)."""
    client.send(INIT_BEGIN)
    words = client.frame("0C1")
    assert len(words) == 4, words
    assert float(words[2]) > 0
    assert re.fullmatch(r"[0-9A-F]{16}", words[3]), words
    client.send(INIT_END)


def assert_bus_works(server: FleetServer, bus: str = "CAN0") -> None:
    """A well-behaved client opens ``bus`` and enumerates its first board."""
    with contextlib.closing(Client(server.address)) as client:
        client.handshake(bus)
        enumerate_first_board(client)


def send_filler(client: Client, frames: int = 100) -> None:
    """Send frames every board ignores, and wait until the server has queued them all
    for the bus (``< echo >`` answers in order), so they do not pile up unread."""
    client.send(FILLER * frames + b"< echo >")
    client.until("< echo >")


def flood(client: Client, stop: threading.Event) -> None:
    """Keep the bus busy until ``stop`` (every read and send has a deadline)."""
    deadline = time.monotonic() + 3 * DEADLINE_S
    while not stop.is_set() and time.monotonic() < deadline:
        send_filler(client)


# ---------------------------------------------------------------------- malformed input
def test_negative_identifier_gets_an_error_and_the_bus_goes_on(
        serve: Callable[..., FleetServer]) -> None:
    server = serve()
    with contextlib.closing(Client(server.address)) as hostile:
        hostile.handshake()
        hostile.send("< send -1 1 00 >")
        assert hostile.reply().startswith("< error ")
        hostile.send("< echo >")
        assert hostile.reply() == "< echo >"
        assert_bus_works(server)
        enumerate_first_board(hostile)  # the hostile client itself is still served


@pytest.mark.parametrize("element", [
    b"< send -1 1 00 >",
    b"< send 280 9 0 0 0 0 0 0 0 0 0 >",        # DLC over 8
    b"< send 280 A 0 0 0 0 0 0 0 0 0 0 >",      # DLC over 8, in hex
    b"< send 280 02 01 00 >",                   # DLC of two digits
    b"< send 800 1 00 >",                       # identifier over 7FF
    b"< send 0280 2 01 00 >",                   # four digits
    b"< send 20000000 0 >",                     # extended identifier over 1FFFFFFF
    b"< send 000000280 0 >",                    # nine digits
    b"< send 0x80 1 00 >",                      # not plain hex
    b"< send 280 2 01 >",                       # fewer data bytes than the DLC
    b"< send 280 1 01 00 >",                    # more data bytes than the DLC
    b"< send 280 2 0g 00 >",                    # bad hex
    b"< send 280 2 100 00 >",                   # three digits for a byte
    b"< send 280 2 +1 00 >",
    b"< send 280 2 \xff\xfe 00 >",              # non-ASCII
    b"< send 280 >",
    b"< send >",
    b"< \xc3\xa9cho >",
    b"< bogus >",
    b"< >",
    b"< open CAN0 >",                           # a second open
    b"< open >",
    b"< rawmode >",                             # raw mode again
    b"< rawmode now >",
])
def test_malformed_element_gets_an_error_and_the_client_stays(
        serve: Callable[..., FleetServer], element: bytes) -> None:
    server = serve()
    with contextlib.closing(Client(server.address)) as hostile:
        hostile.handshake()
        hostile.send(element)
        assert hostile.reply().startswith("< error ")
        hostile.send("< echo >")
        assert hostile.reply() == "< echo >"
        enumerate_first_board(hostile)
        assert_bus_works(server)
        # each frame reaches the hostile client once (a second rawmode must not attach twice)
        hostile.send("< echo >")
        acks = [e for e in hostile.until("< echo >") if e.startswith("< frame 0C1 ")]
        assert len(acks) == 1, acks


@pytest.mark.parametrize("element", ["< rawmode >", "< send 280 2 01 00 >", "< bogus >",
                                     "< open CAN9 >", "< open CAN0 CAN1 >"])
def test_commands_before_a_bus_is_open_get_an_error(
        serve: Callable[..., FleetServer], element: str) -> None:
    server = serve()
    with contextlib.closing(Client(server.address)) as client:
        assert client.element() == "< hi >"
        client.send(element)
        assert client.reply().startswith("< error ")
        client.send("< open CAN0 >")
        assert client.reply() == "< ok >"
        client.send("< rawmode >")
        assert client.reply() == "< ok >"
        enumerate_first_board(client)


def test_unpadded_data_bytes_are_accepted(serve: Callable[..., FleetServer]) -> None:
    server = serve()
    with contextlib.closing(Client(server.address)) as client:
        client.handshake()
        client.send("< send 280 2 1 0 >")  # python-can's spelling of BEGIN
        assert client.frame("0C1")[1] == "0C1"
        client.send("< send 280 2 3 0 >")


def test_endless_element_closes_only_that_client(
        serve: Callable[..., FleetServer], server_log: ServerLog) -> None:
    server = serve()
    hostile = Client(server.address)
    errors: list[BaseException] = []

    def send_100_mb() -> None:
        chunk = b"A" * (1 << 20)
        try:
            hostile.send(b"< send ")
            for _ in range(100):
                hostile.send(chunk)
        except OSError:
            return  # the server closed the connection: expected
        errors.append(AssertionError("the server took 100 MB without '>'"))

    sender = threading.Thread(target=send_100_mb, daemon=True)
    sender.start()
    try:
        received = hostile.read_until_closed()
        assert b"< error element too long >" in received
        sender.join(DEADLINE_S)
        assert not sender.is_alive()
        assert not errors
        assert "element longer than 4096" in server_log.wait_gone(hostile.name).getMessage()
        assert_bus_works(server)
    finally:
        hostile.close()
        sender.join(DEADLINE_S)


def test_element_limit_counts_brackets_and_holds_no_more() -> None:
    splitter = ElementSplitter(limit=16)
    splitter.feed(b"junk< send 1 0 >tail<")
    assert splitter.next() == b" send 1 0 "
    assert splitter.next() is None
    splitter.feed(b"x" * 15)
    with pytest.raises(ElementTooLong):
        splitter.next()
    exact = ElementSplitter(limit=MAX_ELEMENT)
    exact.feed(b"<" + b" " * (MAX_ELEMENT - 2) + b">")
    assert exact.next() == b" " * (MAX_ELEMENT - 2)


@pytest.mark.parametrize(("words", "expected"), [
    (["280", "2", "1", "0"], (0x280, b"\x01\x00")),
    (["7FF", "8", "ff", "0", "1", "2", "3", "4", "5", "a"],
     (0x7FF, bytes([0xFF, 0, 1, 2, 3, 4, 5, 0xA]))),
    (["0", "0"], (0, b"")),
])
def test_send_parsing(words: list[str], expected: tuple[int, bytes]) -> None:
    assert parse_send(words) == expected


@pytest.mark.parametrize("words", [["-1", "1", "00"], ["1_0", "0"], ["١", "0"],
                                   ["280", "²"], ["280", "1", " 1"]])
def test_send_parsing_is_strict(words: list[str]) -> None:
    with pytest.raises(ElementError):
        parse_send(words)


# ---------------------------------------------------------------------- slow and lost clients
def test_client_that_stops_reading_is_dropped_and_the_bus_goes_on(
        serve: Callable[..., FleetServer], server_log: ServerLog) -> None:
    server = serve(max_queued_frames=200)
    stuck = Client(server.address, rcvbuf=4096)
    busy = Client(server.address)
    try:
        stuck.handshake()
        busy.handshake()
        # small kernel buffers on both ends (loopback would grow them to megabytes), so
        # that the server's queue for the stuck client fills within a second
        (conn,) = [c for c in server.connections() if c.peer == stuck.name]
        conn.sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
        deadline = time.monotonic() + 3 * DEADLINE_S
        while not server_log.find(f"dropped client {stuck.name}"):
            assert time.monotonic() < deadline, "the client that stopped reading was kept"
            send_filler(busy)  # the bus carries these while the stuck client waits
        assert server_log.find(f"dropped client {stuck.name}: stopped reading")
        stuck.read_until_closed()
        enumerate_first_board(busy)
        assert_bus_works(server)
    finally:
        stuck.close()
        busy.close()


def test_connections_are_limited(serve: Callable[..., FleetServer],
                                 server_log: ServerLog) -> None:
    server = serve()
    assert server.max_clients == 16
    clients = [Client(server.address) for _ in range(16)]
    try:
        for c in clients:
            assert c.element() == "< hi >"
        with contextlib.closing(Client(server.address)) as extra:
            assert extra.read_until_closed() == b"< error too many clients (16) >"
        # one leaves: its place is free again once the server has cleaned it up
        gone = clients.pop()
        name = gone.name
        gone.close()
        server_log.wait_gone(name)
        clients.append(Client(server.address))
        clients[-1].handshake()
        enumerate_first_board(clients[-1])
    finally:
        for c in clients:
            c.close()


def test_accepted_connections_have_tcp_nodelay(serve: Callable[..., FleetServer]) -> None:
    server = serve()
    with contextlib.closing(Client(server.address)) as client:
        assert client.element() == "< hi >"
        (conn,) = server.connections()
        assert conn.sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) != 0


@pytest.mark.parametrize("moment", ["before hi", "mid element", "after rawmode"])
@pytest.mark.parametrize("how", ["close", "reset"])
def test_client_closing_abruptly_leaves_no_trace(
        serve: Callable[..., FleetServer], server_log: ServerLog, moment: str,
        how: str) -> None:
    server = serve()
    client = Client(server.address)
    name = client.name
    if moment == "mid element":
        assert client.element() == "< hi >"
        client.send("< open CAN0 >< rawmode >< send 280 2 0")
        assert client.reply() == "< ok >"
    elif moment == "after rawmode":
        client.handshake()
    getattr(client, how)()
    assert server_log.wait_gone(name).levelno == logging.INFO
    assert not server.connections()
    assert_bus_works(server)


def test_client_closing_while_frames_are_delivered(
        serve: Callable[..., FleetServer], server_log: ServerLog) -> None:
    server = serve()
    busy = Client(server.address)
    stop = threading.Event()
    flooder = threading.Thread(target=flood, args=(busy, stop), daemon=True)
    try:
        busy.handshake()
        flooder.start()
        for how in ["reset", "close"] * 5:
            reader = Client(server.address)
            reader.handshake()
            reader.frame("7C0")  # frames are flowing to it
            name = reader.name
            getattr(reader, how)()
            server_log.wait_gone(name)
        stop.set()
        flooder.join(DEADLINE_S)
        assert not flooder.is_alive()
        enumerate_first_board(busy)
        assert_bus_works(server)
    finally:
        stop.set()
        busy.close()
        flooder.join(DEADLINE_S)


@pytest.mark.parametrize("how", ["close", "reset"])
def test_client_closing_while_waiting_for_the_bus_is_cleaned_up(
        serve: Callable[..., FleetServer], server_log: ServerLog, how: str) -> None:
    server = serve()
    client = Client(server.address)
    client.handshake()
    server.fleet.close()  # the bus stands still: the client's transmit queue stays full
    client.send(FILLER * 40)  # 32 fit in its transmit queue, the server waits with the 33rd
    name = client.name
    getattr(client, how)()
    assert server_log.wait_gone(name).getMessage() == (
        f"client {name} left: disconnected while waiting for the bus")
    assert not server.connections()


def test_one_client_waiting_for_room_does_not_hold_up_another(
        serve: Callable[..., FleetServer]) -> None:
    server = serve("armar3")
    with contextlib.closing(Client(server.address)) as pusher:
        pusher.handshake("CAN0")
        stop = threading.Event()
        flooder = threading.Thread(target=flood, args=(pusher, stop), daemon=True)
        flooder.start()
        try:
            assert_bus_works(server, "CAN0")  # same bus as the pusher
            assert_bus_works(server, "CAN1")
        finally:
            stop.set()
            flooder.join(DEADLINE_S)
        assert not flooder.is_alive()


# ---------------------------------------------------------------------- the bus thread
def test_bus_thread_survives_failing_nodes_and_callbacks(
        serve: Callable[..., FleetServer], server_log: ServerLog) -> None:
    server = serve()
    sim = server.fleet.buses["CAN0"]

    class FailingNode:
        def on_frame(self, arbitration_id: int, data: bytes, t_end: float) -> None:
            raise RuntimeError("node failed")

    def failing_callback(t: float) -> None:
        raise RuntimeError("callback failed")

    with sim.changed:
        sim.at(sim.now, failing_callback)
        sim.changed.notify_all()
    server_log.wait_for("the bus goes on")
    with contextlib.closing(Client(server.address)) as client:
        client.handshake()
        node = FailingNode()
        sim.attach(node)
        client.send("< send 7C0 0 >")
        server_log.wait_for("the bus goes on", count=2)
        sim.detach(node)
        enumerate_first_board(client)
    failures = server_log.matching("the bus goes on")
    assert [(r.name, str(r.exc_info[1]) if r.exc_info else None) for r in failures] == [
        ("ucom.bus", "callback failed"), ("ucom.bus", "node failed")]
    server_log.expected.extend(failures)


# ---------------------------------------------------------------------- python-can
def test_python_can_client_connects_while_traffic_flows(
        serve: Callable[..., FleetServer]) -> None:
    """python-can reads each ``< ok >`` with one recv(): frames must not be glued to it."""
    server = serve()
    host, port = server.address
    with contextlib.closing(Client(server.address)) as busy:
        busy.handshake()
        stop = threading.Event()
        flooder = threading.Thread(target=flood, args=(busy, stop), daemon=True)
        flooder.start()
        try:
            for _ in range(5):
                bus = can.Bus(interface="socketcand", host=host, port=port, channel="CAN0")
                try:
                    msg = bus.recv(DEADLINE_S)
                    assert msg is not None and msg.arbitration_id == 0x7C0
                finally:
                    bus.shutdown()
        finally:
            stop.set()
            flooder.join(DEADLINE_S)
        assert not flooder.is_alive()
    bus = can.Bus(interface="socketcand", host=host, port=port, channel="CAN0")
    try:
        bus.send(can.Message(arbitration_id=0x280, data=[1, 0], is_extended_id=False))
        deadline = time.monotonic() + DEADLINE_S
        while (msg := bus.recv(max(0.0, deadline - time.monotonic()))) is not None:
            if msg.arbitration_id == 0x0C1:
                break
        assert msg is not None and len(msg.data) == 8
        bus.send(can.Message(arbitration_id=0x280, data=[3, 0], is_extended_id=False))
    finally:
        bus.shutdown()
