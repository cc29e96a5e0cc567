"""Extended (29-bit) frames on a served fleet, and python-can's socketcand client.

python-can's own client, ``can.Bus(interface="socketcand")``, against ``fleet serve`` on
127.0.0.1 (in this process, and with the buses in processes of their own): an extended
frame goes onto the bus, the boards ignore it, every other client of the bus gets it with
its 29-bit identifier, and every answer of an init and GetInfo exchange that follows
arrives - no exception in python-can's ``recv``.  Frames the server refuses are answered
in a form python-can's client survives.  On the simulated bus an extended frame takes the
extended format's bit count and loses arbitration against a standard frame with the same
base ID.  And ``--processes``: auto is capped at the cores, N above the buses refused.

Every wait has a deadline (python-can's ``recv`` timeouts, joins with timeouts); nothing
sleeps to synchronise.
"""

from __future__ import annotations

import contextlib
import logging
import os
import selectors
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator

import can
import pytest
from can.interfaces.socketcand.socketcand import convert_ascii_message_to_can_message
from click.testing import CliRunner
from hypothesis import given
from hypothesis import strategies as st

from tests import canref
from ucom_tools.cli import fleet as fleet_cli
from ucom_tools.cli.main import cli
from ucom_tools.config import topology as topo
from ucom_tools.ops.robot import transport_margin
from ucom_tools.protocol.bootloader import BootloaderClient
from ucom_tools.protocol.link import Link
from ucom_tools.transport.socketcand import SocketcandBus
from ucom_tools.virtual.bus.simbus import SimBus
from ucom_tools.virtual.canbus import VirtualUcomBus
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.virtual.serve import multiserve
from ucom_tools.virtual.serve.multiserve import MultiServer, auto_processes, usable_cores
from ucom_tools.virtual.serve.outbox import encode_line, encode_lines
from ucom_tools.virtual.serve.socketcand import FleetServer
from ucom_tools.wire import canbits
from ucom_tools.wire.ids import seq
from ucom_tools.wire.socketcand import (
    CAN_EFF_FLAG,
    ElementError,
    error_element,
    frame_element,
    parse_send,
)

DEADLINE_S = 10.0
LOCAL = "127.0.0.1"
ARMAR3 = topo.load("armar3")
EXTENDED_ID = 0x1ABCDEF0
MARK = 0x7C0
"""A standard frame every board ignores (function 31, broadcast)."""
PYTHON_CAN_LOG = "can.interfaces.socketcand.socketcand"


# ---------------------------------------------------------------------- served fleets
@pytest.fixture
def one_process() -> Iterator[tuple[tuple[str, int], Fleet]]:
    """ARMAR-III served from this process (``--processes 1``): its address and fleet."""
    fleet = Fleet.load("armar3", realtime=True)
    server = FleetServer(fleet, LOCAL, 0)
    thread = threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True,
                              name="test-serve-extended")
    thread.start()
    try:
        yield server.address, fleet
    finally:
        server.shutdown()
        server.server_close()
        thread.join(DEADLINE_S)
        fleet.close()
        assert not thread.is_alive()


@contextlib.contextmanager
def per_bus_processes() -> Iterator[tuple[str, int]]:
    """ARMAR-III with its buses in two processes of their own (``--processes 2``)."""
    with MultiServer(ARMAR3, LOCAL, 0, processes=2) as server:
        server.start(timeout=60.0)
        yield server.address


def python_can(address: tuple[str, int], channel: str = "CAN0") -> can.BusABC:
    host, port = address
    return can.Bus(interface="socketcand", host=host, port=port, channel=channel)


def recv_until(bus: can.BusABC, wanted: Callable[[can.Message], bool],
               timeout: float = DEADLINE_S) -> list[can.Message]:
    """Every message ``bus`` receives up to and including the first ``wanted`` one."""
    deadline = time.monotonic() + timeout
    got: list[can.Message] = []
    while True:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            pytest.fail(f"no wanted frame within {timeout} s; got {got}")
        msg = bus.recv(remaining)
        if msg is None:
            continue
        got.append(msg)
        if wanted(msg):
            return got


def attached(sender: can.BusABC, receiver: can.BusABC) -> None:
    """Both are on the bus: ``sender`` sends marks until ``receiver`` hears one (a client
    is attached 20 ms after its rawmode ``< ok >``, and before it reads its next element,
    so a mark heard means both are)."""
    deadline = time.monotonic() + DEADLINE_S
    while time.monotonic() < deadline:
        sender.send(can.Message(arbitration_id=MARK, data=b"\x01", is_extended_id=False))
        msg = receiver.recv(0.2)
        while msg is not None:
            if msg.arbitration_id == MARK and not msg.is_extended_id:
                return
            msg = receiver.recv(0.05)
    pytest.fail("the mark never arrived")


def is_extended(ident: int) -> Callable[[can.Message], bool]:
    return lambda msg: bool(msg.is_extended_id) and msg.arbitration_id == ident


def exchange(bus: can.BusABC, channel: str = "CAN0") -> None:
    """Init and GetInfo of every board of ``channel`` over ``bus``: every answer came.
    Over the network with the margin ucom itself gives a socketcand bus (a served fleet on
    a loaded machine answers later than the wire alone says: without it a step is asked
    again, and the test would be about that)."""
    margin = 0.0 if isinstance(bus, VirtualUcomBus) else transport_margin("socketcand")
    client = BootloaderClient(Link(bus, channel, margin=margin))
    boards = len(ARMAR3.bus(channel).boards)
    result = client.init_chain()
    assert [a.seq_id for a in result.acks] == list(range(1, boards + 1))
    for n in range(1, boards + 1):
        assert client.info(seq(n)).seq_id == n


def extended_frame_goes_round(address: tuple[str, int]) -> None:
    """python-can sends an extended frame; our client and a second python-can client get
    it with its 29-bit identifier; python-can's client then runs an init and GetInfo
    exchange, and gets one in turn from our client."""
    sender = python_can(address)
    ours = SocketcandBus("CAN0", *address)
    other = python_can(address)
    try:
        attached(ours, sender)
        attached(other, sender)
        sender.send(can.Message(arbitration_id=EXTENDED_ID, data=b"\x01\x02\x03",
                                is_extended_id=True))
        for receiver in (ours, other):
            msg = recv_until(receiver, is_extended(EXTENDED_ID))[-1]
            assert bytes(msg.data) == b"\x01\x02\x03"
        exchange(sender)
        ours.send(can.Message(arbitration_id=0x00000001, data=b"\xAA", is_extended_id=True))
        msg = recv_until(sender, is_extended(0x00000001))[-1]
        assert bytes(msg.data) == b"\xAA"
        assert not ours.server_errors
    finally:
        for bus in (sender, ours, other):
            bus.shutdown()


# ---------------------------------------------------------------------- python-can, served
def test_python_can_sends_an_extended_frame_and_every_answer_arrives(
        one_process: tuple[tuple[str, int], Fleet]) -> None:
    address, fleet = one_process
    extended_frame_goes_round(address)
    stats = fleet.buses["CAN0"].stats
    assert stats.extended == 2  # both went over the simulated bus
    assert all(b.can_errors == 0 for b in fleet.boards["CAN0"])


def test_extended_frames_go_round_with_a_process_per_bus() -> None:
    with per_bus_processes() as address:
        extended_frame_goes_round(address)


def test_extended_frame_before_init_loses_no_init_ack_with_a_process_per_bus() -> None:
    """The issue's case on another bus of the per-bus serve: extended frame, then Init
    BEGIN as raw frames; python-can's recv raises nothing and the Init Ack comes."""
    with per_bus_processes() as address:
        bus = python_can(address, "CAN3")
        try:
            bus.send(can.Message(arbitration_id=0x0A000000, data=b"\x01\x00",
                                 is_extended_id=True))  # base ID 0x280: Init Request
            bus.send(can.Message(arbitration_id=0x280, data=b"\x01\x00", is_extended_id=False))
            ack = recv_until(bus, lambda m: m.arbitration_id == 0x0C1)[-1]
            assert not ack.is_extended_id and len(ack.data) == 8
            bus.send(can.Message(arbitration_id=0x280, data=b"\x03\x00",
                                 is_extended_id=False))
        finally:
            bus.shutdown()


@pytest.mark.parametrize("refused", [
    can.Message(arbitration_id=MARK, is_remote_frame=True, dlc=4, is_extended_id=False),
    can.Message(arbitration_id=MARK, is_fd=True, data=bytes(12), is_extended_id=False),
    can.Message(arbitration_id=MARK, dlc=8, data=b"\x01\x02", is_extended_id=False),
], ids=["remote-with-dlc", "can-fd", "dlc-above-data"])
def test_python_can_survives_a_refused_frame(
        one_process: tuple[tuple[str, int], Fleet], refused: can.Message,
        caplog: pytest.LogCaptureFixture) -> None:
    """The server refuses what python-can sends for these (``< send 7C0 4  >``, DLC C,
    DLC 8 with two bytes); its ``< error ...>`` reaches python-can, which logs it and
    goes on: the init and GetInfo exchange after it gets every answer."""
    address, _ = one_process
    caplog.set_level(logging.WARNING, logger=PYTHON_CAN_LOG)
    bus = python_can(address)
    try:
        bus.send(refused)
        exchange(bus)
    finally:
        bus.shutdown()
    skipped = [r.getMessage() for r in caplog.records if r.name == PYTHON_CAN_LOG]
    assert any("< error " in text for text in skipped), skipped


def test_error_replies_in_raw_mode_are_no_error_frames_to_python_can() -> None:
    text = "DLC 9 above 8"
    assert error_element(text) == "< error DLC 9 above 8 >"
    # the form python-can takes for an error frame, and fails on
    with pytest.raises(ValueError):
        convert_ascii_message_to_can_message(error_element(text))
    assert convert_ascii_message_to_can_message(error_element(text, raw=True)) is None


def test_a_raw_client_gets_error_replies_in_the_raw_mode_form(
        one_process: tuple[tuple[str, int], Fleet]) -> None:
    address, _ = one_process
    with contextlib.closing(RawClient(address)) as client:
        assert client.element() == "< hi >"
        client.send("< bogus >")
        assert client.element() == "< error unsupported command bogus >"  # not raw yet
        client.send("< open CAN0 >< rawmode >")
        assert client.element() == "< ok >"
        assert client.element() == "< ok >"
        client.send("< send 7C0 9 0 0 0 0 0 0 0 0 0 >< send 1234 0 >< rawmode >< echo >")
        replies = [e for e in client.until("< echo >") if not e.startswith("< frame ")]
        assert replies == ["< error DLC 9 above 8>",
                           "< error bad identifier 1234: 1-3 hex digits (11 bit) or 8 "
                           "(29 bit)>",
                           "< error already in raw mode>"]


class RawClient:
    """A socketcand client on a plain socket; every read has a deadline."""

    def __init__(self, address: tuple[str, int]) -> None:
        self.sock = socket.create_connection(address, timeout=DEADLINE_S)
        self.pending = b""

    def send(self, text: str) -> None:
        self.sock.sendall(text.encode("ascii"))

    def element(self) -> str:
        """The next element (none of the server's answers here has a ``>`` inside)."""
        while True:
            start = self.pending.find(b"<")
            end = self.pending.find(b">", start + 1)
            if start >= 0 and end >= 0:
                element, self.pending = self.pending[start:end + 1], self.pending[end + 1:]
                return element.decode("ascii")
            chunk = self.sock.recv(65536)  # the socket's timeout is the deadline
            assert chunk, f"the server closed the connection; pending {self.pending!r}"
            self.pending += chunk

    def until(self, reply: str) -> list[str]:
        elements = []
        while (element := self.element()) != reply:
            elements.append(element)
        return elements

    def close(self) -> None:
        self.sock.close()


# ---------------------------------------------------------------------- the server's parsing
def test_send_takes_eight_hex_digits_as_an_extended_identifier() -> None:
    assert parse_send(["1ABCDEF0", "2", "1", "F1"]) == (0x1ABCDEF0 | CAN_EFF_FLAG, b"\x01\xf1")
    assert parse_send(["00000280", "0"]) == (0x280 | CAN_EFF_FLAG, b"")
    assert parse_send(["280", "0"]) == (0x280, b"")
    for ident in ("20000000", "0280", "1234567", "000000280"):
        with pytest.raises(ElementError):
            parse_send([ident, "0"])
    assert encode_line((0x1ABCDEF0 | CAN_EFF_FLAG, b"\x01", 0.0), 1700000000.0) == \
        b"< frame 1ABCDEF0 1700000000.000000 01 >"
    assert encode_line((0x0C1, b"", 0.0), 1700000000.0) == \
        b"< frame 0C1 1700000000.000000  >"


@given(epoch=st.one_of(st.floats(0.0, 4e9), st.floats(-1e6, 1e6),
                      st.integers(2**30, 2**33).map(float)),
       t_end=st.one_of(st.floats(0.0, 1e11), st.integers(0, 10**10).map(float)),
       ident=st.one_of(st.integers(0, 0x7FF), st.integers(0, 0x1FFFFFFF).map(
           lambda i: i | CAN_EFF_FLAG)),
       data=st.binary(max_size=8))
def test_a_frame_is_written_as_percent_formatting_writes_it(
        epoch: float, t_end: float, ident: int, data: bytes) -> None:
    """The server puts a frame element together from pieces (no float formatting): the
    same bytes as socketcand's format, ``%.6f`` of the time included."""
    assert encode_line((ident, data, t_end), epoch) == frame_element(
        ident, epoch + t_end / 1e6, data)


def test_a_time_half_way_between_two_microseconds_is_rounded_as_percent_formatting_does(
        ) -> None:
    # k / 2**22 s with k * 15625 = 32768 (mod 65536): exactly half a microsecond over
    for whole in (2**30, 1_765_000_000, 2**31 - 1, 2**31, 2**40 + 3):
        for step in range(64):
            seconds = whole + step / 64 + 1 / 128
            assert encode_line((0x0C1, b"", 0.0), seconds) == frame_element(
                0x0C1, seconds, b"")
    assert encode_line((0x0C1, b"\x01", 0.0), 2**30 + 1 / 128) == \
        b"< frame 0C1 1073741824.007812 01 >"  # half to even, as %.6f
    assert encode_line((0x0C1, b"", 999_999.6), 1_765_000_000.0) == \
        b"< frame 0C1 1765000001.000000  >"  # rounded up into the next second
    lines = [b"< ok >", (0x123, b"\xab", 5.0), (0x1ABCDEF0 | CAN_EFF_FLAG, b"", 7.5)]
    assert encode_lines(lines, 1.7e9) == b"".join(encode_line(x, 1.7e9) for x in lines)


# ---------------------------------------------------------------------- the simulated bus
Seen = tuple[int, bool, bytes, float]
"""A frame a node got: identifier, extended, data, end time."""


class Recorder:
    """A node that takes standard frames only (as the boards' acceptance filter)."""

    def __init__(self) -> None:
        self.seen: list[Seen] = []

    def on_frame(self, arbitration_id: int, data: bytes, t_end: float) -> None:
        self.seen.append((arbitration_id, False, data, t_end))


class ExtendedRecorder(Recorder):
    """A node that takes both formats."""

    def on_extended_frame(self, arbitration_id: int, data: bytes, t_end: float) -> None:
        self.seen.append((arbitration_id, True, data, t_end))


def _reference_extended_bits(arb: int, data: bytes) -> int:
    """An extended data frame bit by bit (tests/canref.py)."""
    return canref.extended(arb, data)


@given(st.integers(0, canbits.MAX_EXTENDED_ID), st.binary(max_size=8))
def test_extended_frame_bits_match_bit_by_bit_reference(arb: int, data: bytes) -> None:
    bits = canbits.frame_bits(arb, data, extended=True)
    assert bits == _reference_extended_bits(arb, data)
    assert canbits.unstuffed_bits(len(data), extended=True) <= bits
    assert bits <= canbits.worst_frame_bits(len(data), extended=True)


@pytest.mark.parametrize("alone", [True, False], ids=["idle-bus", "queued"])
def test_an_extended_frame_takes_the_extended_bit_count(alone: bool) -> None:
    bus = SimBus("CAN0", 500_000)
    rx, standard_only = ExtendedRecorder(), Recorder()
    bus.attach(rx)
    bus.attach(standard_only)
    data = b"\x00" * 8
    bits = canbits.frame_bits(EXTENDED_ID, data, extended=True)
    assert bits == _reference_extended_bits(EXTENDED_ID, data)
    assert bits >= canbits.unstuffed_bits(8, extended=True) == 131
    if alone:
        assert bus.send_alone(object(), 10.0, EXTENDED_ID, data, extended=True) == \
            10.0 + bits * 2.0
    else:
        bus.send(object(), 10.0, EXTENDED_ID, data, extended=True)
        bus.run_until(1e6)
    assert rx.seen == [(EXTENDED_ID, True, data, 10.0 + bits * 2.0)]  # 2 us/bit at 500k
    assert standard_only.seen == []
    s = bus.stats
    assert (s.frames, s.extended, s.bits, s.busy_us, s.payload_bits) == (
        1, 1, bits, bits * 2.0, 64)
    assert not s.by_function  # an extended frame has no function


def test_a_standard_frame_wins_against_an_extended_one_with_the_same_base_id() -> None:
    bus = SimBus("CAN0", 1_000_000)
    rx = ExtendedRecorder()
    bus.attach(rx)
    same_base = 0x280 << 18  # base ID 0x280, extension 0
    bus.send(object(), 0.0, same_base, b"\x01", extended=True)
    bus.send(object(), 0.0, 0x280, b"\x01")
    bus.send(object(), 0.0, 0x27F << 18 | 0x3FFFF, b"", extended=True)  # lower base ID
    bus.send(object(), 0.0, 0x281, b"")
    bus.send(object(), 0.0, same_base | 1, b"", extended=True)
    bus.run_until(1e6)
    assert [(ident, extended) for ident, extended, _, _ in rx.seen] == [
        (0x27F << 18 | 0x3FFFF, True), (0x280, False), (same_base, True),
        (same_base | 1, True), (0x281, False)]
    assert bus.stats.clashes == 0  # no two frames had the same arbitration field
    t = 0.0  # back to back, each for its own format's bit count at 1 us per bit
    for ident, extended, data, t_end in rx.seen:
        t += canbits.frame_bits(ident, data, extended=extended)
        assert t_end == t


def test_the_same_extended_identifier_from_two_nodes_is_a_clash() -> None:
    bus = SimBus("CAN0", 1_000_000)
    bus.send(object(), 0.0, EXTENDED_ID, b"\x01", extended=True)
    bus.send(object(), 0.0, EXTENDED_ID, b"\x02", extended=True)
    bus.send(object(), 0.0, EXTENDED_ID >> 18, b"\x03")  # its base ID as a standard one
    bus.run_until(1e6)
    assert bus.stats.clashes == 1


def test_an_identifier_above_29_bits_is_refused_by_the_bus() -> None:
    bus = SimBus("CAN0", 1_000_000)
    with pytest.raises(ValueError, match="29 bits"):
        bus.send(object(), 0.0, 0x20000000, b"", extended=True)


# ---------------------------------------------------------------------- boards, in process
def test_boards_ignore_extended_frames_and_other_hosts_get_them() -> None:
    fleet = Fleet.load("armar3")
    a, b = VirtualUcomBus("CAN0", fleet=fleet), VirtualUcomBus("CAN0", fleet=fleet)
    try:
        link = Link(a, "CAN0")
        # base ID 0x280 with Init BEGIN's data: an Init Request, were it a standard frame
        a.send(can.Message(arbitration_id=0x0A000000, data=b"\x01\x00", is_extended_id=True))
        assert link.drain(0.05) == []
        assert [board.seq_id for board in fleet.boards["CAN0"]] == [0, 0, 0]
        got = b.recv(0.01)
        assert got is not None and got.is_extended_id
        assert (got.arbitration_id, bytes(got.data)) == (0x0A000000, b"\x01\x00")
        assert b.recv(0.01) is None
        exchange(a)
        assert all(board.can_errors == 0 for board in fleet.boards["CAN0"])
    finally:
        a.shutdown()
        b.shutdown()


# ---------------------------------------------------------------------- --processes
def test_auto_processes_is_capped_at_the_cores(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(multiserve, "usable_cores", lambda: 2)
    assert auto_processes(ARMAR3) == 2
    assert fleet_cli._process_count(ARMAR3, None) == 2
    monkeypatch.setattr(multiserve, "usable_cores", lambda: 64)
    assert auto_processes(ARMAR3) == len(ARMAR3.buses) == 4
    monkeypatch.setattr(multiserve, "usable_cores", lambda: 1)
    assert fleet_cli._process_count(ARMAR3, None) == 1  # then served in this process
    assert fleet_cli._process_count(ARMAR3, 3) == 3     # asked for: as asked


def test_usable_cores_counts_the_affinity_else_the_cpus(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 3, 5}, raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 16)
    assert usable_cores() == 3
    monkeypatch.delattr(os, "sched_getaffinity", raising=False)
    assert usable_cores() == 16
    monkeypatch.setattr(os, "cpu_count", lambda: None)
    assert usable_cores() == 1


@pytest.mark.parametrize(("topology", "asked", "buses"), [
    ("armar3", "5", "4 buses"), ("rosi", "2", "1 bus")])
def test_more_processes_than_buses_is_a_usage_error(topology: str, asked: str,
                                                    buses: str) -> None:
    result = CliRunner().invoke(cli, ["fleet", "serve", topology, "--processes", asked,
                                      "--port", "0"])
    assert result.exit_code == 2, result.output
    text = " ".join(result.output.split())
    assert "--processes" in text and f"which has {buses}" in text, text
    assert "at most one process per bus" in text
    assert "listening on" not in text


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="needs CPU affinity")
@pytest.mark.parametrize(("cores", "banner"), [
    (1, "one process (auto: 1 core)"),
    (2, "2 processes (auto: 2 cores): CAN0, CAN2; CAN1, CAN3")])
def test_auto_serves_from_no_more_processes_than_cores(cores: int, banner: str) -> None:
    """``fleet serve armar3`` (auto) on a server that may run on ``cores`` cores: the
    banner says how the buses were shared out, and the first and the last bus serve."""
    usable = sorted(os.sched_getaffinity(0))
    if len(usable) < cores:
        pytest.skip(f"needs {cores} cores")
    script = ("import os, runpy, sys; os.sched_setaffinity(0, set(map(int, sys.argv[1:"
              f"{cores + 1}]))); sys.argv = ['ucom', *sys.argv[{cores + 1}:]]; "
              "runpy.run_module('ucom_tools', run_name='__main__')")
    proc = subprocess.Popen(
        [sys.executable, "-c", script, *map(str, usable[:cores]), "fleet", "serve",
         "armar3", "--host", LOCAL, "--port", "0"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"))
    errors: list[str] = []
    reader = threading.Thread(target=lambda: errors.extend(proc.stderr or []), daemon=True)
    reader.start()
    try:
        assert proc.stdout is not None
        with selectors.DefaultSelector() as sel:
            sel.register(proc.stdout, selectors.EVENT_READ)
            assert sel.select(timeout=60.0), "the server did not start"
        line = proc.stdout.readline()
        assert line.startswith(f"listening on {LOCAL}:"), line
        port = int(line.rsplit(":", 1)[1])
        for channel in ("CAN0", "CAN3"):
            bus = SocketcandBus(channel, LOCAL, port)
            try:
                exchange(bus, channel)
            finally:
                bus.shutdown()
        deadline = time.monotonic() + DEADLINE_S
        while banner not in " ".join("".join(errors).split()):
            assert time.monotonic() < deadline, "".join(errors)
            reader.join(0.05)  # polling what the server wrote, not synchronisation
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            code = proc.wait(DEADLINE_S)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(DEADLINE_S)
        reader.join(DEADLINE_S)
    assert code == 130, "".join(errors)
