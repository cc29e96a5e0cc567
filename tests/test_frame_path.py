"""The run time's per-frame paths, fast and plain, give the same frames.

The socketcand client reads runs of frame elements in the usual form in one go
(:meth:`ElementSplitter.plain_data`, :meth:`SocketcandBus._take_buffered`), sends a
standard data frame without a ``can.Message`` (``send_data``), and the dispatcher hands a
batch of frames over at once (``dispatch_all``, ``send_data``): each must do exactly what
the element-by-element path, python-can's constructor and ``dispatch``/``send`` do.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import random
import socket
import threading
from collections.abc import Iterator
from typing import Any

import can
import pytest

from tests.helpers import assert_send_data_refuses_as_send
from ucom_tools.protocol import frames
from ucom_tools.protocol.dispatch import Dispatcher
from ucom_tools.transport import socketcand as client
from ucom_tools.transport.socketcand import PINGS, SocketcandBus
from ucom_tools.transport.socketcand_frames import send_bytes
from ucom_tools.wire.socketcand import (
    ElementSplitter,
    ElementTooLong,
    plain_frame,
    seconds_of,
)

ATTRIBUTES = ("timestamp", "arbitration_id", "is_extended_id", "is_remote_frame",
              "is_error_frame", "channel", "dlc", "data", "is_fd", "is_rx", "bitrate_switch",
              "error_state_indicator")


def attributes(msg: can.Message) -> tuple[Any, ...]:
    return tuple(getattr(msg, a) for a in ATTRIBUTES)


def _greet(listener: socket.socket, out: list[socket.socket]) -> None:
    """A server's side of the handshake (``< hi >``, open, rawmode, echoes)."""
    conn, _ = listener.accept()
    conn.settimeout(5)
    conn.sendall(b"< hi >")
    heard = b""
    for answer in (b"< ok >", b"< ok >", *[b"< echo >"] * PINGS):
        while b">" not in heard:
            heard += conn.recv(4096)
        heard = heard.split(b">", 1)[1]
        conn.sendall(answer)
    out.append(conn)


@contextlib.contextmanager
def offline_bus(channel: str = "CAN0") -> Iterator[SocketcandBus]:
    """A SocketcandBus whose receiving state is set by the test (the elements are fed to
    its splitter, nothing is read from its socket): connected through the handshake, as
    the class (compiled, its instances built only by its constructor) wants it."""
    listener = socket.create_server(("127.0.0.1", 0))
    conns: list[socket.socket] = []
    greeter = threading.Thread(target=_greet, args=(listener, conns), daemon=True)
    greeter.start()
    bus = SocketcandBus(channel, "127.0.0.1", listener.getsockname()[1])
    greeter.join(5)
    listener.close()
    bus._where = "test:0"
    bus._splitter = ElementSplitter(on_skip=client._skipped)
    bus._arrival = 0.0
    bus.clock_offset = math.inf
    bus._pending = collections.deque()
    bus.server_errors = collections.deque(maxlen=client.SERVER_ERRORS_KEPT)
    try:
        yield bus
    finally:
        bus.shutdown()
        for conn in conns:
            conn.close()


def element(rng: random.Random, stamp: float) -> bytes:
    """One element of a stream a client may get: mostly frames as socketcand writes them,
    and every odd form and error around them."""
    kind = rng.random()
    data = bytes(rng.randrange(256) for _ in range(rng.randrange(9)))
    if kind < 0.6:
        ident = rng.randrange(0x800)
        return b"< frame %03X %.6f %s >" % (ident, stamp, data.hex().upper().encode())
    if kind < 0.7:
        ident = rng.randrange(0x20000000)
        return b"< frame %08X %.6f %s >" % (ident, stamp, data.hex().encode())  # lower case
    odd = [
        b"< frame %03X %.6f %s>" % (rng.randrange(0x800), stamp, data.hex().encode()),
        b"< frame %03X %.6f %s >" % (rng.randrange(0x800), stamp, data.hex(" ").encode()),
        b"< frame %03X %d.%s %s >" % (rng.randrange(0x800), int(stamp), b"1" * 17,
                                       data.hex().encode()),  # a long fraction
        b"< frame 800 %.6f 00 >" % stamp,  # out of range
        b"< frame 20000000 %.6f 00 >" % stamp,
        b"< frame 12 %.6f 00 >" % stamp,  # two digits
        b"< frame 123 %.6f 123 >" % stamp,  # odd data
        b"< frame 123 %.6f %s >" % (stamp, b"00" * 9),  # nine bytes
        b"< frame 123 %d 00 >" % int(stamp),  # no fraction
        b"< frame 123 %.6f  >" % stamp,  # DLC 0
        b"<  frame 123 %.6f 00 >" % stamp,
        b"< error some text >",
        b"< echo >",
        b"junk",
        b"\n",
        b"< frame 123 unfinished ",
        b"< hi >",
    ]
    return rng.choice(odd)


def stream(seed: int, n: int = 400) -> bytes:
    rng = random.Random(seed)
    stamp = 1_796_173_614.798991
    out = []
    for _ in range(n):
        stamp += rng.random() * 1e-3
        out.append(element(rng, stamp))
    return b"".join(out)


def chunks(data: bytes, seed: int) -> list[bytes]:
    rng = random.Random(seed)
    out, pos = [], 0
    while pos < len(data):
        n = rng.choice([1, 7, 40, 200, 4000])
        out.append(data[pos:pos + n])
        pos += n
    return out


def take_element_by_element(bus: SocketcandBus) -> None:
    """The client's receiving loop before the runs of frames were read at once."""
    while (element := bus._pop_element()) is not None:
        bus._take(element)


@pytest.mark.parametrize("seed", range(6))
def test_runs_of_frames_are_read_as_one_element_at_a_time_would(
        seed: int, caplog: pytest.LogCaptureFixture) -> None:
    data = stream(seed)
    results = []
    for take in (take_element_by_element, SocketcandBus._take_buffered):
        with offline_bus() as bus:
            caplog.clear()
            with caplog.at_level(logging.DEBUG, logger="ucom_tools.transport.socketcand"):
                for k, chunk in enumerate(chunks(data, seed)):
                    bus._arrival = 1_796_173_615.0 + k * 1e-4
                    bus._splitter.feed(chunk)
                    take(bus)
            results.append(([attributes(bus.message_of(m) if isinstance(m, tuple) else m)
                              for m in bus._pending], bus.clock_offset,
                             list(bus.server_errors),
                             [r.getMessage() for r in caplog.records]))
    assert results[0] == results[1]
    frames_read = results[0][0]
    assert len(frames_read) > 200  # the stream was mostly frames


def test_a_frame_run_is_not_taken_past_a_short_splitter_limit() -> None:
    """A splitter whose limit an element of the usual form may exceed leaves every element
    to next(), which enforces the limit."""
    splitter = ElementSplitter(limit=20)
    splitter.feed(b"< frame 123 1.000000 0011 >")
    assert splitter.plain_data(0.0, math.inf) == ([], math.inf)
    with pytest.raises(ElementTooLong):
        splitter.next()


def test_plain_data_is_plain_frame() -> None:
    rng = random.Random(1)
    for _ in range(2000):
        text = element(rng, rng.random() * 2e9)
        splitter = ElementSplitter()
        splitter.feed(text)
        frames, _ = splitter.plain_data(1e12, 0.0)  # the offset stays 0: stamps as sent
        if frames:
            assert len(frames) == 1
            ident, data, stamp = frames[0]
            assert (ident, stamp, data) == plain_frame(text[1:-1])


def test_seconds_of_is_float() -> None:
    rng = random.Random(2)
    cases = [(b"0", b"0"), (b"1", b"5"), (b"9007199254", b"740993"), (b"99999999999", b"999999"),
             (b"1796173614", b"798991"), (b"1", b"1" * 16), (b"0" * 30, b"1")]
    for _ in range(20000):
        cases.append((b"%d" % rng.randrange(10 ** rng.randrange(1, 12)),
                      b"%0*d" % ((w := rng.randrange(1, 10)), rng.randrange(10 ** w))))
    for seconds, fraction in cases:
        assert seconds_of(seconds, fraction) == float(seconds + b"." + fraction)


@pytest.mark.parametrize("fast", [True, False])
def test_data_frame_is_the_constructors_message(fast: bool,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(frames, "FAST", fast)
    for ext, rx, channel in [(False, True, "CAN0"), (True, False, None)]:
        data = bytearray(b"\x01\x02\x03")
        made = frames.data_frame(12.5, 0x123, data, is_extended_id=ext, is_rx=rx,
                                 channel=channel)
        expected = can.Message(timestamp=12.5, arbitration_id=0x123, data=data,
                               is_extended_id=ext, is_rx=rx, channel=channel)
        assert type(made) is can.Message
        assert attributes(made) == attributes(expected)
        assert made.data is data


def test_fast_messages_are_in_use_with_this_python_can() -> None:
    assert frames.FAST, "can.Message's attributes changed: frames.data_frame falls back"


def test_send_data_writes_what_send_writes() -> None:
    rng = random.Random(3)
    with offline_bus() as bus:
        bus.hold()
        for _ in range(3000):
            ident = rng.randrange(0x800)
            data = bytes(rng.randrange(256) for _ in range(rng.randrange(9)))
            bus.send_data(ident, data)
            assert bus._batch is not None
            assert bus._batch[-1] == send_bytes(can.Message(arbitration_id=ident, data=data,
                                                            is_extended_id=False))
        assert_send_data_refuses_as_send(bus)
        bus.release(write=False)


def test_send_data_many_writes_what_send_data_writes() -> None:
    """A cycle's frames in one call are the bytes of each frame's send_data, in order, as
    one piece; with a frame that is not a standard one of at most 8 bytes, none (that
    one refused as send refuses it)."""
    rng = random.Random(5)
    with offline_bus() as bus:
        bus.hold()
        for _ in range(500):
            frames = [(rng.randrange(0x800),
                       bytes(rng.randrange(256) for _ in range(rng.randrange(9))))
                      for _ in range(rng.randrange(1, 12))]
            for ident, data in frames:
                bus.send_data(ident, data)
            assert bus._batch is not None
            one_by_one = b"".join(bus._batch)
            bus._batch.clear()
            bus.send_data_many(frames)
            assert bus._batch == [one_by_one]
            bus._batch.clear()
        for bad in [(0x800, b""), (0x123, bytes(9))]:
            with pytest.raises(can.CanOperationError) as many:
                bus.send_data_many([(0x100, b"\x01"), bad])
            assert bus._batch == []
            with pytest.raises(can.CanOperationError) as one:
                bus.send_data(*bad)
            assert str(many.value) == str(one.value)
        bus.release(write=False)


class _Bus(can.BusABC):
    """A bus that notes what it was given to send, with or without ``send_data`` (and
    ``send_data_many``: ``many``)."""

    def __init__(self, fast: bool, many: bool = False) -> None:
        self.sent: list[tuple[int, bytes]] = []
        self.calls = 0
        if fast:
            self.send_data = lambda ident, data, timeout=None: self.sent.append((ident, data))
        if many:
            def send_data_many(frames: list[tuple[int, bytes]],
                               timeout: float | None = None) -> None:
                self.calls += 1
                self.sent.extend(frames)
            self.send_data_many = send_data_many
        super().__init__(channel="test")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append((msg.arbitration_id, bytes(msg.data)))

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return None, False


def test_dispatcher_send_data_is_send() -> None:
    seen: dict[bool, list[tuple[Any, ...]]] = {True: [], False: []}
    dispatchers = {}
    for fast in (True, False):
        d = Dispatcher(_Bus(fast), "CAN0")
        d.sender.stamp = lambda: 5.0
        d.taps.append(lambda msg, fast=fast: seen[fast].append(attributes(msg)))
        for ident in range(0, 0x800, 7):
            d.send_data(ident, bytes(ident % 9), timeout=1.0)
        dispatchers[fast] = d
    fast_d, plain_d = dispatchers[True], dispatchers[False]
    assert seen[True] == seen[False] and seen[True]
    assert fast_d.bus.sent == plain_d.bus.sent
    assert (fast_d.sent, fast_d.bits) == (plain_d.sent, plain_d.bits)


def test_dispatcher_send_data_many_is_send_data_of_each() -> None:
    """The frames, the taps' messages, the counts and the bits are those of send_data
    frame by frame; a bus without send_data_many gets them so; with one, in one call."""
    frames = [(ident, bytes(ident % 9)) for ident in range(0, 0x800, 7)]
    seen: dict[str, list[tuple[Any, ...]]] = {}
    dispatchers = {}
    for way in ("one by one", "without", "many"):
        d = Dispatcher(_Bus(True, many=way == "many"), "CAN0")
        d.sender.stamp = lambda: 5.0
        seen[way] = []
        d.taps.append(lambda msg, way=way: seen[way].append(attributes(msg)))
        if way == "one by one":
            for ident, data in frames:
                d.send_data(ident, data, timeout=1.0)
        else:
            assert d.batches == (way == "many")
            for k in range(0, len(frames), 10):
                d.send_data_many(frames[k:k + 10], timeout=1.0)
        dispatchers[way] = d
    want = dispatchers["one by one"]
    for way in ("without", "many"):
        d = dispatchers[way]
        assert seen[way] == seen["one by one"] and seen[way]
        assert (d.bus.sent, d.sent, d.bits) == (want.bus.sent, want.sent, want.bits)
    assert dispatchers["many"].bus.calls == -(-len(frames) // 10)


def test_link_send_frames_in_one_call_keeps_the_horizon() -> None:
    """Link.send_frames to a bus that takes a cycle's frames in one call: the frames in
    one call, counted and the wire horizon moved as one by one; a bus that refuses the
    call took none, and the frames then go one by one."""
    from ucom_tools.protocol.link import Link

    frames = [(0x100 + k, bytes(k % 9)) for k in range(12)]
    links = {}
    for many in (False, True):
        link = Link(_Bus(True, many=many), "CAN0", margin=0.01)
        link.clock = lambda: 100.0
        link.send_frames(frames)
        links[many] = link
    one, batch = links[False], links[True]
    assert batch.bus.calls == 1 and batch.bus.sent == one.bus.sent == frames
    assert (batch.frames_sent, batch._horizon) == (one.frames_sent, one._horizon)

    refusing = _Bus(True, many=True)

    def refuse(frames: list[tuple[int, bytes]], timeout: float | None = None) -> None:
        raise can.CanOperationError("no room")
    refusing.send_data_many = refuse
    link = Link(refusing, "CAN0", margin=0.01)
    link.clock = lambda: 100.0
    link.send_frames(frames)
    assert refusing.sent == frames and link.frames_sent == len(frames)
    assert link._horizon == one._horizon


def dispatch_one(d: Dispatcher, msg: can.Message) -> None:
    """Dispatcher.dispatch as it was before dispatch_all: the reference."""
    d.router.received += 1
    if not msg.is_error_frame and not msg.is_remote_frame and not msg.is_extended_id:
        d.traffic.count(msg.arbitration_id, msg.data)
    for tap in d.taps:
        tap(msg)
    subs = d.router.route(msg)
    for sub in subs:
        if sub.on_frame is not None:
            sub.on_frame(msg)
            continue
        sub.queue.append(msg)
    if not subs:
        d.unclaimed[msg.arbitration_id >> 6] += 1


def test_dispatch_all_is_dispatch_frame_by_frame() -> None:
    rng = random.Random(4)
    msgs = []
    for _ in range(3000):
        kind = rng.random()
        msgs.append(can.Message(
            timestamp=rng.random(), arbitration_id=rng.randrange(0x800 if kind < 0.8 else
                                                                 0x20000000),
            data=bytes(rng.randrange(256) for _ in range(rng.randrange(9))),
            is_extended_id=kind >= 0.8, is_remote_frame=0.9 <= kind < 0.95,
            is_error_frame=kind >= 0.95))

    def run(batch: bool) -> tuple[Any, ...]:
        d = Dispatcher(_Bus(False), "CAN0")
        got: list[tuple[str, int]] = []
        tapped: list[int] = []
        d.taps.append(lambda msg: tapped.append(msg.arbitration_id))
        d.subscribe(lambda msg: msg.arbitration_id & 1 == 0, "even",
                    on_frame=lambda msg: got.append(("even", msg.arbitration_id)))
        queued = d.subscribe(lambda msg: msg.arbitration_id % 3 == 0, "threes")
        d.subscribe(lambda msg: bool(msg.is_remote_frame), "remote",
                    on_frame=lambda msg: got.append(("remote", msg.arbitration_id)))
        if batch:
            d.dispatch_all(msgs[:1000])
            for msg in msgs[1000:2000]:
                d.dispatch(msg)
            d.dispatch_all(iter(msgs[2000:]))
        else:
            for msg in msgs:
                dispatch_one(d, msg)
        return (got, tapped, [m.arbitration_id for m in queued.queue], dict(d.unclaimed),
                d.received, d.bits, d.traffic.frames)

    assert run(True) == run(False)
