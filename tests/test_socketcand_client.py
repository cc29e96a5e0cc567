"""SocketcandBus against fake servers that misbehave, and against ``ucom fleet serve``.

The client runs in a thread with a deadline of its own (:func:`within`), so a client that
waits forever fails its test instead of hanging the suite.  Fake servers are scripts on a
thread of their own; a test hands them what to send through queues and events.
"""

from __future__ import annotations

import contextlib
import functools
import queue
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

import can
import pytest

from tests.test_socketcand import served
from ucom_tools.transport.socketcand import (
    MAX_ELEMENT,
    PINGS,
    ElementSplitter,
    SocketcandBus,
)
from ucom_tools.transport.socketcand_frames import parse_frame, send_element

T = TypeVar("T")
LOCAL = "127.0.0.1"


def within(seconds: float, action: Callable[[], T]) -> T:
    """``action()`` on a thread of its own; the test fails if it takes over ``seconds``."""
    outcome: queue.Queue[tuple[bool, Any]] = queue.Queue()

    def run() -> None:
        try:
            outcome.put((True, action()))
        except BaseException as err:
            outcome.put((False, err))

    threading.Thread(target=run, name="client under test", daemon=True).start()
    try:
        ok, value = outcome.get(timeout=seconds)
    except queue.Empty:
        pytest.fail(f"the client did not finish within {seconds} s")
    if not ok:
        raise value
    return value


def timed(seconds: float, action: Callable[[], object]) -> tuple[BaseException | None, float]:
    """Run ``action`` within ``seconds``; the error it raised (or None) and how long it took."""
    start = time.monotonic()
    try:
        within(seconds, action)
    except Exception as err:
        return err, time.monotonic() - start
    return None, time.monotonic() - start


class Peer:
    """The server's end of one accepted connection, as a script uses it."""

    def __init__(self, conn: socket.socket) -> None:
        conn.settimeout(5)
        self.conn = conn
        self._heard = b""

    def say(self, text: str) -> None:
        self.conn.sendall(text.encode("ascii"))

    def hear(self, text: str) -> None:
        """Read exactly ``text`` from the client."""
        want = text.encode("ascii")
        while len(self._heard) < len(want):
            chunk = self.conn.recv(4096)
            assert chunk, f"the client closed; heard {self._heard!r}"
            self._heard += chunk
        got, self._heard = self._heard[:len(want)], self._heard[len(want):]
        assert got == want

    def greet(self, channel: str = "CAN0", after_rawmode: str = "< ok >",
              tail: str = "", *, echoes: bool = True, first_echo_after: float = 0.0) -> None:
        """The server's side of a handshake that succeeds, with the client's round trips
        (its ``< echo >`` pings) answered, unless not ``echoes``, the first one after
        ``first_echo_after`` seconds; ``tail`` comes with the last answer."""
        self.say("< hi >")
        self.hear(f"< open {channel} >")
        self.say("< ok >")
        self.hear("< rawmode >")
        self.say(after_rawmode)
        for i in range(PINGS if echoes else 0):
            self.hear("< echo >")
            if i == 0 and first_echo_after:
                time.sleep(first_echo_after)  # the scenario: a server slow to switch
            self.say("< echo >" + (tail if i == PINGS - 1 else ""))

    def wait_closed(self) -> None:
        """Read (and drop) everything until the client closes the connection."""
        with contextlib.suppress(OSError):
            while self.conn.recv(4096):
                pass

    def close(self, *, reset: bool = False) -> None:
        if reset:  # RST instead of FIN
            self.conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        else:
            with contextlib.suppress(OSError):
                self.conn.shutdown(socket.SHUT_RDWR)
        self.conn.close()


class FakeServer:
    """A one-connection server on 127.0.0.1 running ``script`` on a thread."""

    def __init__(self, script: Callable[[Peer], None], *, rcvbuf: int | None = None) -> None:
        self.listener = socket.socket()
        if rcvbuf is not None:  # before listen(): accepted sockets inherit it
            self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.listener.bind((LOCAL, 0))
        self.listener.listen(1)
        self.listener.settimeout(5)
        self.port: int = self.listener.getsockname()[1]
        self.script = script
        self.finished = threading.Event()
        self.failures: list[BaseException] = []
        self.peer: Peer | None = None
        self.thread = threading.Thread(target=self._run, name="fake socketcand", daemon=True)

    def _run(self) -> None:
        try:
            conn, _ = self.listener.accept()
            self.peer = Peer(conn)
            self.script(self.peer)
        except BaseException as err:
            self.failures.append(err)
        finally:
            self.finished.set()

    def __enter__(self) -> FakeServer:
        self.thread.start()
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        with contextlib.suppress(OSError):
            self.listener.shutdown(socket.SHUT_RDWR)  # wakes accept()
        self.listener.close()
        if self.peer is not None:
            self.peer.close()
        self.thread.join(5)
        assert not self.thread.is_alive(), "the fake server did not stop"
        if exc_type is None and self.failures:
            raise self.failures[0]


def greet_then_wait(peer: Peer) -> None:
    peer.greet()
    peer.wait_closed()


# ------------------------------------------------------------------ connecting
def test_refused_port_fails_at_once() -> None:
    with socket.socket() as placeholder:  # bound but not listening: connections are refused
        placeholder.bind((LOCAL, 0))
        port = placeholder.getsockname()[1]
        err, took = timed(5, lambda: SocketcandBus("CAN0", LOCAL, port))
    assert isinstance(err, can.CanInitializationError)
    assert str(err).startswith(f"cannot connect to socketcand {LOCAL}:{port}: ")
    assert "refused" in str(err).lower()
    assert took < 0.5


@pytest.mark.skipif(sys.platform != "linux", reason="relies on Linux dropping SYNs to a full "
                                                    "accept queue")
def test_connect_timeout_bounds_a_server_that_never_accepts() -> None:
    with socket.socket() as listener, socket.socket() as first:
        listener.bind((LOCAL, 0))
        listener.listen(0)  # one connection fills the accept queue; later SYNs are dropped
        port = listener.getsockname()[1]
        first.connect((LOCAL, port))
        err, took = timed(5, lambda: SocketcandBus("CAN0", LOCAL, port, connect_timeout=0.3))
    assert isinstance(err, can.CanInitializationError)
    assert str(err) == f"cannot connect to socketcand {LOCAL}:{port}: no connection within 0.3 s"
    assert 0.25 < took < 1.3


def test_the_round_trip_leaves_out_the_first_echo_and_is_unknown_without_echoes() -> None:
    """The first echo may wait for the server's switch to raw mode (fleet serve: 20 ms):
    it does not count, the later ones do; a server that answers no echo leaves the round
    trip unknown, so the network margin is the fixed one (ucom-protocol.7, TIMEOUTS)."""
    from ucom_tools.ops.robot import TRANSPORT_MARGIN, network_margin
    late = 0.06  # within the wait for an echo (PING_WAIT_S)

    def slow_first(peer: Peer) -> None:
        peer.greet(first_echo_after=late)
        peer.wait_closed()

    def no_echo(peer: Peer) -> None:
        peer.greet(echoes=False)
        peer.wait_closed()

    with FakeServer(slow_first) as server:
        bus = within(5, lambda: SocketcandBus("CAN0", LOCAL, server.port))
        try:
            assert bus.round_trip_s is not None and bus.round_trip_s < late / 3
        finally:
            bus.shutdown()
    with FakeServer(no_echo) as server:
        bus = within(5, lambda: SocketcandBus("CAN0", LOCAL, server.port))
        try:
            assert bus.round_trip_s is None
            assert network_margin(bus.round_trip_s) == TRANSPORT_MARGIN["socketcand"]
        finally:
            bus.shutdown()


@pytest.mark.parametrize(("answers", "what"), [
    ((), "the connection"),
    (("< hi >",), "< open CAN0 >"),
    (("< hi >", "< ok >"), "< rawmode >"),
])
def test_silent_server_fails_the_handshake_at_its_deadline(answers: tuple[str, ...],
                                                           what: str) -> None:
    commands = ["< open CAN0 >", "< rawmode >"]

    def script(peer: Peer) -> None:
        for i, answer in enumerate(answers):
            if i:
                peer.hear(commands[i - 1])
            peer.say(answer)
        peer.wait_closed()

    with FakeServer(script) as server:
        err, took = timed(5, lambda: SocketcandBus("CAN0", LOCAL, server.port,
                                                   handshake_timeout=0.3))
        assert isinstance(err, can.CanInitializationError)
        assert str(err) == f"socketcand {LOCAL}:{server.port} did not answer {what} within 0.3 s"
        assert 0.25 < took < 1.3
        assert server.finished.wait(2), "the client did not close its socket"


def test_refused_channel_names_it_and_quotes_the_server() -> None:
    def script(peer: Peer) -> None:
        peer.say("< hi >")
        peer.hear("< open CAN7 >")
        peer.say("< error no such bus >")
        peer.wait_closed()

    with FakeServer(script) as server:
        err, _ = timed(5, lambda: SocketcandBus("CAN7", LOCAL, server.port))
        assert isinstance(err, can.CanInitializationError)
        assert str(err) == (f"socketcand {LOCAL}:{server.port} refused to open channel CAN7: "
                            "< error no such bus >")
        assert server.finished.wait(2), "the client did not close its socket"


def test_socket_has_tcp_nodelay_and_channel_info() -> None:
    with FakeServer(greet_then_wait) as server:
        bus = within(5, lambda: SocketcandBus("CAN0", LOCAL, server.port))
        try:
            assert bus._sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) != 0
            assert bus.channel_info == f"socketcand {LOCAL}:{server.port} CAN0"
        finally:
            bus.shutdown()


# ------------------------------------------------------------------ receiving
def test_frames_split_and_glued_are_decoded_in_order() -> None:
    pieces: queue.Queue[str | None] = queue.Queue()

    def script(peer: Peer) -> None:
        # the handshake's last answer arrives together with half a frame
        peer.greet(tail="< frame 0C1 1700000000.000001 01")
        while (piece := pieces.get(timeout=5)) is not None:
            peer.say(piece)
        peer.wait_closed()

    def frame(msg: can.Message | None) -> tuple[int, bool, bytes, bool, object, bool]:
        """The frame; for its stamp whether it is on this machine's clock, no later than
        now (the client translates the server's stamps: tests/test_time_base.py)."""
        assert msg is not None
        return (msg.arbitration_id, msg.is_extended_id, bytes(msg.data),
                msg.timestamp <= time.time(), msg.channel, msg.is_rx)

    with FakeServer(script) as server:
        bus = within(5, lambda: SocketcandBus("CAN0", LOCAL, server.port))
        try:
            assert within(5, lambda: bus.recv(0.1)) is None  # half a frame is no frame
            pieces.put("0203 >< frame 12345678 1700000000.500000 >< error bus o")
            pieces.put("ff >< frame 12 1.0 00 >< fr")  # 2-digit identifier: ignored
            assert within(5, lambda: frame(bus.recv(2))) == (
                0x0C1, False, b"\x01\x02\x03", True,
                "CAN0", True)
            assert within(5, lambda: frame(bus.recv(2))) == (
                0x12345678, True, b"", True, "CAN0", True)
            assert within(5, lambda: bus.recv(0.1)) is None  # "< fr" waits for its end
            pieces.put("ame 7FF 1700000001.000002 0011223344556677 >< echo >")
            pieces.put("< frame 123 1700000002.250000 a b0 C >")  # bytes separated by blanks
            assert within(5, lambda: frame(bus.recv(2))) == (
                0x7FF, False, bytes.fromhex("0011223344556677"),
                True, "CAN0", True)
            assert list(bus.server_errors) == ["bus off"]  # sent before that frame's end
            assert within(5, lambda: frame(bus.recv(2))) == (
                0x123, False, b"\x0a\xb0\x0c", True, "CAN0", True)
            assert within(5, lambda: bus.recv(0.1)) is None
        finally:
            pieces.put(None)
            bus.shutdown()


def test_server_closing_the_connection_breaks_recv_and_send() -> None:
    def script(peer: Peer) -> None:
        peer.greet()
        peer.say("< frame 0C1 1.000000 01 >")
        peer.close()

    with FakeServer(script) as server:
        bus = within(5, lambda: SocketcandBus("CAN0", LOCAL, server.port))
        closed = f"socketcand {LOCAL}:{server.port} closed the connection"
        msg = within(5, lambda: bus.recv(2))  # what came before the end is delivered
        assert msg is not None and msg.arbitration_id == 0x0C1
        for action in (lambda: bus.recv(2), lambda: bus.recv(0),
                       lambda: bus.send(can.Message(arbitration_id=0x280, data=b"\x01\x00",
                                                    is_extended_id=False))):
            err, took = timed(5, action)
            assert isinstance(err, can.CanOperationError)
            assert str(err) == closed
            assert took < 1
        bus.shutdown()
        bus.shutdown()  # idempotent, also after the server vanished
        with pytest.raises(can.CanOperationError, match="is shut down"):
            bus.recv(0)


def test_connection_reset_breaks_recv_and_send() -> None:
    def script(peer: Peer) -> None:
        peer.greet()
        peer.close(reset=True)

    with FakeServer(script) as server:
        bus = within(5, lambda: SocketcandBus("CAN0", LOCAL, server.port))
        try:
            err, _ = timed(5, lambda: bus.recv(2))
            assert isinstance(err, can.CanOperationError)
            assert str(err).startswith(f"socketcand {LOCAL}:{server.port} connection lost: ")
            assert "reset" in str(err).lower()
            with pytest.raises(can.CanOperationError, match="connection lost"):
                bus.send(can.Message(arbitration_id=0x280, data=b"", is_extended_id=False))
        finally:
            bus.shutdown()


def test_overlong_element_is_a_protocol_error() -> None:
    def script(peer: Peer) -> None:
        peer.greet()
        peer.say("< frame " + "0" * MAX_ELEMENT)
        peer.wait_closed()

    with FakeServer(script) as server:
        bus = within(5, lambda: SocketcandBus("CAN0", LOCAL, server.port))
        try:
            err, _ = timed(5, lambda: bus.recv(2))
            assert isinstance(err, can.CanOperationError)
            assert str(err) == (f"socketcand {LOCAL}:{server.port} protocol error: "
                                f"an element is longer than {MAX_ELEMENT} bytes")
            with pytest.raises(can.CanOperationError, match="protocol error"):
                bus.recv(0)
        finally:
            bus.shutdown()


# ------------------------------------------------------------------ sending
def test_send_writes_elements_byte_exact_and_returns_own_messages() -> None:
    heard = threading.Event()

    def script(peer: Peer) -> None:
        peer.greet()
        peer.hear("< send 280 2 01 00 >")
        peer.hear("< send 1ABCDEF0 0 >")
        peer.hear("< send 7FF 8 00 01 02 03 04 05 06 FF >")
        heard.set()
        peer.wait_closed()

    with FakeServer(script) as server:
        bus = within(5, lambda: SocketcandBus("CAN0", LOCAL, server.port,
                                              receive_own_messages=True))
        try:
            sent = [can.Message(arbitration_id=0x280, data=b"\x01\x00", is_extended_id=False),
                    can.Message(arbitration_id=0x1ABCDEF0, data=b"", is_extended_id=True),
                    can.Message(arbitration_id=0x7FF, data=b"\0\1\2\3\4\5\6\xff",
                                is_extended_id=False)]
            for refused in (can.Message(arbitration_id=0x280, is_remote_frame=True, dlc=2,
                                        is_extended_id=False),
                            can.Message(arbitration_id=0x280, is_error_frame=True),
                            can.Message(arbitration_id=0x280, data=bytes(12), is_fd=True,
                                        is_extended_id=False),
                            can.Message(arbitration_id=0x800, is_extended_id=False)):
                with pytest.raises(can.CanOperationError, match="cannot send"):
                    bus.send(refused)
            for msg in sent:  # the refusals left the connection usable
                within(5, functools.partial(bus.send, msg))
            assert heard.wait(5)
            own = [within(5, lambda: bus.recv(1)) for _ in sent]
            assert [(m.arbitration_id, m.is_extended_id, bytes(m.data), m.is_rx, m.channel)
                    for m in own if m is not None] == [
                (s.arbitration_id, s.is_extended_id, bytes(s.data), False, "CAN0")
                for s in sent]
        finally:
            bus.shutdown()


def test_send_to_a_server_that_stops_reading_fails_within_send_timeout() -> None:
    release = threading.Event()

    def script(peer: Peer) -> None:
        peer.greet()
        release.wait(30)  # reads nothing more

    with FakeServer(script, rcvbuf=4096) as server:
        bus = within(5, lambda: SocketcandBus("CAN0", LOCAL, server.port, send_timeout=0.3))
        bus._sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
        msg = can.Message(arbitration_id=0x123, data=bytes(8), is_extended_id=False)

        def flood() -> tuple[int, float, can.CanOperationError]:
            for count in range(1_000_000):
                start = time.monotonic()
                try:
                    bus.send(msg)
                except can.CanOperationError as err:
                    return count, time.monotonic() - start, err
            raise AssertionError("the server took a million frames")

        try:
            count, took, err = within(30, flood)
            assert count > 0
            assert str(err) == f"socketcand {LOCAL}:{server.port} took no data for 0.3 s"
            assert 0.29 < took < 1.0
            # send(timeout=...) overrides send_timeout; if the frame that timed out was
            # written in part, the connection is unusable and says so at once
            err2, took2 = timed(5, lambda: bus.send(msg, timeout=0.1))
            assert isinstance(err2, can.CanOperationError)
            assert ("took no data for 0.1 s" in str(err2)) or ("is unusable" in str(err2))
            assert took2 < 0.8
        finally:
            release.set()
            bus.shutdown()


class _TakesFiveBytes:
    """Stands in for the client's socket: the first write takes 5 bytes, later ones none."""

    def __init__(self, real: socket.socket) -> None:
        self.real = real
        self.taken = 0

    def send(self, data: bytes) -> int:
        if self.taken:
            raise BlockingIOError
        self.taken = self.real.send(bytes(data[:5]))
        return self.taken

    def __getattr__(self, name: str) -> Any:
        return getattr(self.real, name)


def test_send_that_times_out_after_a_partial_write_breaks_the_connection() -> None:
    with FakeServer(greet_then_wait) as server:
        bus = within(5, lambda: SocketcandBus("CAN0", LOCAL, server.port, send_timeout=0.2))
        bus._sock = _TakesFiveBytes(bus._sock)  # type: ignore[assignment]
        msg = can.Message(arbitration_id=0x280, data=b"\x01\x00", is_extended_id=False)
        try:
            err, took = timed(5, lambda: bus.send(msg))
            assert isinstance(err, can.CanOperationError)
            assert str(err) == f"socketcand {LOCAL}:{server.port} took no data for 0.2 s"
            assert 0.19 < took < 0.9
            broken = (f"socketcand {LOCAL}:{server.port} is unusable: a send timed out after "
                      "writing 5 of the 20 bytes of < send 280 2 01 00 >")
            for action in (lambda: bus.send(msg), lambda: bus.recv(0)):
                err, took = timed(5, action)
                assert isinstance(err, can.CanOperationError)
                assert str(err) == broken
                assert took < 0.5
        finally:
            bus.shutdown()


# ------------------------------------------------------------------ codec
def test_splitter_and_codec_edges() -> None:
    splitter = ElementSplitter(limit=20)
    splitter.feed(b" junk < hi >\n<ok>< fra< frame")
    assert [splitter.next(), splitter.next(), splitter.next()] == [b" hi ", b"ok", None]
    splitter.feed(b" 123 1.5 >")
    assert splitter.next() == b" frame 123 1.5 "  # "< fra" was cut off by the next "<"
    splitter.feed(b"<" + b"x" * 20)
    with pytest.raises(ValueError, match="longer than 20 bytes"):
        splitter.next()
    for bad in (["frame", "12345", "1.0"], ["frame", "800", "1.0"], ["frame", "123", "1e3"],
                ["frame", "123", "1.0", "0g"], ["frame", "123", "1.0", "123"],
                ["frame", "123", "1.0", "00" * 9], ["frame", "123"]):
        with pytest.raises(ValueError):
            parse_frame(bad, "CAN0")
    assert send_element(can.Message(arbitration_id=0x5, data=b"\x0a",
                                    is_extended_id=False)) == "< send 005 1 0A >"


# ------------------------------------------------------------------ the served fleet
def test_init_request_to_the_served_fleet_is_acknowledged() -> None:
    with served("rosi") as port:
        bus = within(10, lambda: SocketcandBus("CAN0", LOCAL, port))
        try:
            def begin_and_wait_for_ack() -> can.Message | None:
                bus.send(can.Message(arbitration_id=0x280, data=b"\x01\x00",
                                     is_extended_id=False))
                deadline = time.monotonic() + 2
                while (left := deadline - time.monotonic()) > 0:
                    msg = bus.recv(left)
                    if msg is not None and msg.arbitration_id == 0x0C1:
                        return msg
                return None

            ack = within(5, begin_and_wait_for_ack)
            assert ack is not None, "no Init Ack within 2 s"
            assert (ack.is_extended_id, ack.dlc, ack.channel, ack.is_rx) == (False, 8, "CAN0",
                                                                             True)
            within(5, lambda: bus.send(can.Message(arbitration_id=0x280, data=b"\x03\x00",
                                                   is_extended_id=False)))
        finally:
            bus.shutdown()


class _CountedSends:
    """The bus's socket, counting the writes (each a system call)."""

    def __init__(self, sock: socket.socket) -> None:
        self._sock = sock
        self.sends = 0

    def send(self, data: Any) -> int:
        self.sends += 1
        return self._sock.send(data)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._sock, name)


def test_held_frames_go_out_in_one_write_and_dropped_ones_not_at_all() -> None:
    heard = threading.Event()

    def script(peer: Peer) -> None:
        peer.greet()
        peer.hear("< send 701 0 >")  # another thread's frame, written while held
        peer.hear("< send 280 1 01 >< send 281 1 02 >< send 282 1 03 >")
        peer.hear("< send 290 0 >")  # the dropped batch never came
        heard.set()
        peer.wait_closed()

    with FakeServer(script) as server:
        bus = within(5, lambda: SocketcandBus("CAN0", LOCAL, server.port))
        counted = _CountedSends(bus._sock)
        bus._sock = counted  # type: ignore[assignment]
        try:
            bus.hold()
            for k in range(3):
                bus.send(can.Message(arbitration_id=0x280 + k, data=bytes([k + 1]),
                                     is_extended_id=False))
            assert counted.sends == 0
            other = threading.Thread(target=bus.send, args=(can.Message(
                arbitration_id=0x701, data=b"", is_extended_id=False),))
            other.start()
            other.join(5)
            assert counted.sends == 1
            bus.release()
            assert counted.sends == 2  # three frames, one write
            with pytest.raises(RuntimeError), bus.batch():
                bus.send(can.Message(arbitration_id=0x28F, data=b"", is_extended_id=False))
                raise RuntimeError("the cycle failed")
            bus.send(can.Message(arbitration_id=0x290, data=b"", is_extended_id=False))
            assert counted.sends == 3
            assert heard.wait(5)
        finally:
            bus.shutdown()


def test_fileno_is_the_connection_a_select_loop_can_wait_on() -> None:
    import select

    def script(peer: Peer) -> None:
        peer.greet()
        peer.say("< frame 123 1.000000 AB >")
        peer.wait_closed()

    with FakeServer(script) as server:
        bus = within(5, lambda: SocketcandBus("CAN0", LOCAL, server.port))
        try:
            assert select.select([bus.fileno()], [], [], 5)[0] == [bus.fileno()]
            msg = bus.recv(1)
            assert msg is not None and msg.arbitration_id == 0x123
        finally:
            bus.shutdown()
