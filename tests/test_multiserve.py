"""``ucom fleet serve --processes auto``: every bus of ARMAR-III served from its own process.

The server runs as ``python -m ucom_tools fleet serve`` in a session of its own, on
127.0.0.1 and a free port (the first line on its stdout names it); its stderr is read by
a thread, so what it logs can be waited for.  Clients are the project's socketcand client
(:class:`~ucom_tools.transport.socketcand.SocketcandBus`) and raw sockets.  Every wait
has a deadline; nothing sleeps to synchronise (conditions are polled until a deadline).
"""

from __future__ import annotations

import contextlib
import os
import re
import selectors
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import can
import pytest
from click.testing import CliRunner
from hypothesis import given
from hypothesis import strategies as st

from tests.helpers import image_words, plan_of, program
from ucom_tools.cli.main import cli
from ucom_tools.config import topology as topo
from ucom_tools.protocol.bootloader import BootloaderClient
from ucom_tools.protocol.link import Link
from ucom_tools.transport.socketcand import SocketcandBus
from ucom_tools.virtual.serve.multiserve import bus_groups
from ucom_tools.wire import socketcand as socketcand_wire
from ucom_tools.wire.ids import seq
from ucom_tools.wire.socketcand import ElementError, element_words, parse_send, plain_send

DEADLINE_S = 10.0
"""The longest any one wait may take (starting four processes on a busy machine included)."""
STOP_S = 8.0
"""How soon SIGINT must have stopped the server and every process it started."""
LOCAL = "127.0.0.1"
ARMAR3 = topo.load("armar3")
T = TypeVar("T")


def until(condition: Callable[[], T], timeout: float = DEADLINE_S, what: str = "") -> T:
    """Poll ``condition`` until it returns something true; fail after ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        result = condition()
        if result:
            return result
        if time.monotonic() >= deadline:
            pytest.fail(f"not within {timeout} s: {what or condition}")
        time.sleep(0.02)  # polling interval, not synchronisation


# ---------------------------------------------------------------------- the server
class Server:
    """``ucom -v fleet serve`` in a process group of its own."""

    def __init__(self, *args: str) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ucom_tools", "-v", "fleet", "serve", "armar3",
             "--host", LOCAL, "--port", "0", *args],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
            start_new_session=True)
        self.lines: list[str] = []
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read_stderr, daemon=True)
        self._reader.start()
        assert self.proc.stdout is not None
        with selectors.DefaultSelector() as sel:
            sel.register(self.proc.stdout, selectors.EVENT_READ)
            if not sel.select(timeout=3 * DEADLINE_S):
                self.kill()
                pytest.fail("the server did not start: " + self.stderr())
        line = self.proc.stdout.readline()
        assert line.startswith(f"listening on {LOCAL}:"), (line, self.stderr())
        self.port = int(line.rsplit(":", 1)[1])
        self.address = (LOCAL, self.port)

    def _read_stderr(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            with self._lock:
                self.lines.append(line)

    def stderr(self) -> str:
        with self._lock:
            return "".join(self.lines)

    def bus_pids(self) -> dict[str, int]:
        """The process of each bus, as the server logs them (-v)."""
        pattern = re.compile(r"(CAN\d) is served by process (\d+)")
        return {m[1]: int(m[2]) for m in pattern.finditer(self.stderr())}

    def children(self) -> list[int]:
        """Every process the server started (bus processes and multiprocessing's helper)."""
        if sys.platform != "linux":
            return list(self.bus_pids().values())
        found = []
        for entry in os.listdir("/proc"):
            if entry.isdigit():
                with contextlib.suppress(OSError, IndexError, ValueError):
                    stat = Path(f"/proc/{entry}/stat").read_text()
                    if int(stat.rsplit(")", 1)[1].split()[1]) == self.proc.pid:
                        found.append(int(entry))
        return found

    def interrupt(self) -> None:
        """Ctrl-C as a terminal sends it: SIGINT to every process of the group."""
        os.killpg(self.proc.pid, signal.SIGINT)

    def wait(self, timeout: float = STOP_S) -> int:
        code = self.proc.wait(timeout)
        self._reader.join(DEADLINE_S)
        return code

    def kill(self) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait(DEADLINE_S)


@contextlib.contextmanager
def served(*args: str) -> Iterator[Server]:
    server = Server(*args)
    try:
        yield server
    finally:
        if server.proc.poll() is None:
            server.kill()


def alive(pid: int) -> bool:
    """Is ``pid`` a live process (a zombie is not)?"""
    try:
        import psutil  # type: ignore[import-untyped]
    except ImportError:
        psutil = None
    if psutil is not None:
        try:
            return bool(psutil.Process(pid).status() != psutil.STATUS_ZOMBIE)
        except psutil.NoSuchProcess:
            return False
    stat = Path(f"/proc/{pid}/stat")
    if stat.parent.parent.exists():
        try:
            return stat.read_text().rsplit(")", 1)[1].split()[0] != "Z"
        except OSError:
            return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def assert_stops_cleanly(server: Server, stop: Callable[[], None], code: int = 130) -> None:
    """``stop()`` ends the server and every process it started, promptly, with exit code
    ``code`` (130 after Ctrl-C, 143 after SIGTERM: ucom(1), EXIT STATUS)."""
    pids = until(lambda: len(server.bus_pids()) == len(ARMAR3.buses) and server.bus_pids(),
                 what="every bus's process logged")
    children = server.children()  # --processes auto: at most one per core
    assert set(pids.values()) <= set(children), (children, server.stderr())
    started = time.monotonic()
    stop()
    assert server.wait(STOP_S) == code, server.stderr()
    until(lambda: not any(alive(pid) for pid in children), STOP_S - (time.monotonic() - started),
          "every process of the server gone")
    assert "Traceback" not in server.stderr()


# ---------------------------------------------------------------------- clients
class Raw:
    """A socketcand client on a raw socket; every read has a deadline."""

    def __init__(self, address: tuple[str, int]) -> None:
        self.sock = socket.create_connection(address, timeout=DEADLINE_S)
        self.pending = b""

    def send(self, data: str | bytes) -> None:
        self.sock.sendall(data.encode("ascii") if isinstance(data, str) else data)

    def element(self, timeout: float = DEADLINE_S) -> str:
        deadline = time.monotonic() + timeout
        while True:
            start = self.pending.find(b"<")
            end = self.pending.find(b">", start + 1)
            if start >= 0 and end >= 0:
                element, self.pending = self.pending[start:end + 1], self.pending[end + 1:]
                return element.decode("ascii")
            self.sock.settimeout(max(0.01, deadline - time.monotonic()))
            try:
                chunk = self.sock.recv(65536)
            except TimeoutError:
                raise AssertionError(f"nothing from the server in {timeout} s") from None
            assert chunk, f"server closed the connection; pending {self.pending!r}"
            self.pending += chunk

    def frame(self, ident: str, timeout: float = DEADLINE_S) -> list[str]:
        """The words of the next frame with identifier ``ident`` (others are skipped)."""
        while True:
            words = self.element(timeout)[1:-1].split()
            if words[:2] == ["frame", ident]:
                return words

    def frames_until(self, ident: str, data: str) -> list[list[str]]:
        """The frames before the frame ``ident data`` (which must come)."""
        before = []
        while (words := self.element()[1:-1].split())[1:2] + words[3:4] != [ident, data]:
            before.append(words)
        return before

    def until(self, end: bytes) -> bytes:
        """Everything the server sends up to and including ``end``."""
        deadline = time.monotonic() + DEADLINE_S
        while (at := self.pending.find(end)) < 0:
            self.sock.settimeout(max(0.01, deadline - time.monotonic()))
            chunk = self.sock.recv(65536)
            assert chunk, f"server closed the connection; pending {self.pending!r}"
            self.pending += chunk
        data, self.pending = self.pending[:at + len(end)], self.pending[at + len(end):]
        return data

    def handshake(self, bus: str, *, greeted: bool = False) -> None:
        if not greeted:
            assert self.element() == "< hi >"
        self.send(f"< open {bus} >")
        assert self.element() == "< ok >"
        self.send("< rawmode >")
        assert self.element() == "< ok >"

    def read_until_closed(self) -> bytes:
        deadline = time.monotonic() + DEADLINE_S
        data = self.pending
        while time.monotonic() < deadline:
            self.sock.settimeout(max(0.01, deadline - time.monotonic()))
            try:
                chunk = self.sock.recv(65536)
            except ConnectionResetError:
                return data
            if not chunk:
                return data
            data += chunk
        pytest.fail(f"the server kept the connection open; got {data!r}")

    def close(self) -> None:
        self.sock.close()


class Host:
    """The project's socketcand client with the bootloader client on top."""

    def __init__(self, port: int, bus: str) -> None:
        self.can = SocketcandBus(bus, LOCAL, port)
        self.link = Link(self.can, bus)
        self.client = BootloaderClient(self.link)

    def close(self) -> None:
        self.can.shutdown()


@contextlib.contextmanager
def host(port: int, bus: str) -> Iterator[Host]:
    h = Host(port, bus)
    try:
        yield h
    finally:
        h.close()


def hears(receiver: Raw, sender: Raw, frame: str) -> None:
    """``sender`` sends ``frame`` (``ID DATA``, one byte) until ``receiver`` gets it: a
    client is attached to its bus 20 ms after its rawmode ``< ok >``."""
    ident = frame.split()[0]

    def heard() -> bool:
        sender.send(f"< send {ident} 1 {frame.split()[1]} >")
        try:
            receiver.frame(ident, timeout=0.2)
        except AssertionError:
            return False
        return True

    until(heard, what=f"{frame} heard")


def transcript(address: tuple[str, int], elements: list[bytes]) -> list[bytes]:
    """What a server answers to each of ``elements`` sent first, one at a time (then to
    ``< open CAN0 >``), byte for byte."""
    client = Raw(address)
    try:
        answers = [client.element().encode()]
        for element in [*elements, b"< open CAN0 >"]:
            client.send(element + b"< echo >")
            answers.append(b"".join(client.until(b"< echo >")
                                    for _ in range(1 + element.count(b"< echo >"))))
        return answers
    finally:
        client.close()


# ---------------------------------------------------------------------- the tests
def test_every_bus_answers_its_chain_and_buses_are_apart() -> None:
    with served("--processes", "4") as server:  # auto: at most one per core
        pids = until(lambda: len(server.bus_pids()) == 4 and server.bus_pids(),
                     what="four bus processes logged")
        assert set(pids) == {b.name for b in ARMAR3.buses}
        assert len(set(pids.values())) == 4 and server.proc.pid not in pids.values()
        for spec in ARMAR3.buses:
            with host(server.port, spec.name) as h:
                result = h.client.init_chain()
                assert [a.seq_id for a in result.acks] == list(range(1, len(spec.boards) + 1))
        # two clients of CAN1 see each other's frames, a client of CAN2 does not
        a, b, c, d = Raw(server.address), Raw(server.address), Raw(server.address), \
            Raw(server.address)
        try:
            for client, bus in ((a, "CAN1"), (b, "CAN1"), (c, "CAN2"), (d, "CAN2")):
                client.handshake(bus)
            hears(c, d, "7C1 D0")
            hears(b, a, "7C0 A0")
            hears(a, b, "7C0 B0")
            a.send("< send 7C0 1 A1 >")
            b.frames_until("7C0", "A1")
            # a's frame went out on CAN1 before this one on CAN2: had c shared that bus,
            # it would have come first
            d.send("< send 7C1 1 D1 >")
            before = c.frames_until("7C1", "D1")
            assert all(w[1] != "7C0" for w in before), before
        finally:
            for client in (a, b, c, d):
                client.close()
        assert_stops_cleanly(server, server.interrupt)


def test_flash_into_can0_survives_a_restart_with_the_same_state(tmp_path: Path) -> None:
    plan = plan_of(image_words(700), name="multi.S")
    with served("--state", str(tmp_path)) as server:
        with host(server.port, "CAN0") as h:
            outcome = program(h, plan)
            assert outcome.all_verified
            assert h.client.info(seq(2)).progid == plan.progid
        assert_stops_cleanly(server, server.interrupt)
    assert len(list(tmp_path.iterdir())) >= len(ARMAR3.buses[0].boards)
    with served("--state", str(tmp_path)) as server:
        with host(server.port, "CAN0") as h:
            h.client.init_chain()
            for n in (1, 2, 3):
                info = h.client.info(seq(n))
                assert (info.flash_valid, info.progid, info.name) == (True, plan.progid,
                                                                      "multi.S")
        with host(server.port, "CAN1") as h:
            h.client.init_chain()
            assert not h.client.info(seq(1)).flash_valid  # another bus, untouched
        assert_stops_cleanly(server, lambda: server.proc.send_signal(signal.SIGTERM), 143)


BAD_FIRST = [b"< open CAN9 >", b"< open >", b"< open CAN0 CAN1 >", b"< rawmode >",
             b"< send 280 2 01 00 >", b"< send 7C0 0 >", b"< bogus 1 >", b"< >",
             b"< \xff\xfe >", b"< echo >", b"< open <CAN0 >", b"junk"]


def test_elements_before_the_open_get_the_answers_of_one_process() -> None:
    with served("--processes", "1") as one:
        expected = transcript(one.address, BAD_FIRST)
        with contextlib.closing(Raw(one.address)) as long_one:
            long_one.element()
            long_one.send(b"<" + b"x" * 5000)
            too_long = long_one.read_until_closed()
        assert_stops_cleanly_single(one)
    assert expected[1] == b"< error no bus CAN9 in ARMAR-III >< echo >"
    assert b"< error no bus open: send < open BUS > first >< echo >" in expected
    assert expected[-1] == b"< ok >< echo >"
    assert too_long == b"< error element too long >"
    with served("--processes", "auto") as auto:
        assert transcript(auto.address, BAD_FIRST) == expected
        with contextlib.closing(Raw(auto.address)) as long_one:
            long_one.element()
            long_one.send(b"<" + b"x" * 5000)
            assert long_one.read_until_closed() == too_long
        until(lambda: "sent an element longer than 4096 bytes" in auto.stderr(),
              what="the dropped client logged")
        # the bytes glued to the open go to the bus process with the connection
        with contextlib.closing(Raw(auto.address)) as glued:
            assert glued.element() == "< hi >"
            glued.send("< bogus >< open CAN3 >< rawmode >< send 280 2 01 00 >< echo >")
            assert glued.element() == "< error unsupported command bogus >"
            assert glued.element() == "< ok >"
            assert glued.element() == "< ok >"
            assert glued.frame("0C1")[:2] == ["frame", "0C1"]  # the Init Ack of CAN3's first
        with pytest.raises(can.CanError, match="CAN9"):
            SocketcandBus("CAN9", LOCAL, auto.port)


def assert_stops_cleanly_single(server: Server) -> None:
    server.interrupt()
    assert server.wait(STOP_S) == 130, server.stderr()


def test_max_clients_counts_every_bus_and_a_killed_bus_process_ends_the_serve() -> None:
    with served("--max-clients", "2") as server:
        first, second = Raw(server.address), Raw(server.address)
        try:
            first.handshake("CAN0")
            second.handshake("CAN1")
            with contextlib.closing(Raw(server.address)) as third:
                assert third.read_until_closed() == b"< error too many clients (2) >"
            first.close()

            def admitted() -> Raw | None:
                client = Raw(server.address)
                if client.element() == "< hi >":
                    return client
                client.close()
                return None

            third = until(admitted, what="a slot free again once a client left")
            third.handshake("CAN2", greeted=True)
            third.close()
        finally:
            first.close()
            second.close()
        pids = server.bus_pids()
        children = server.children()
        os.kill(pids["CAN1"], signal.SIGKILL)
        assert server.wait(STOP_S) == 4, server.stderr()
        err = server.stderr()
        assert "CAN1" in err and "SIGKILL" in err, err
        assert "ucom: bus error:" in err and "Traceback" not in err, err
        until(lambda: not any(alive(pid) for pid in children), STOP_S,
              "every other process of the server gone")


@given(ident=st.integers(0, 0x7FF), data=st.binary(max_size=8), padded=st.booleans(),
       hex_case=st.sampled_from([str.upper, str.lower]))
def test_the_plain_send_path_agrees_with_the_parser(ident: int, data: bytes, padded: bool,
                                                     hex_case: Any) -> None:
    words = [f"{ident:X}", str(len(data)), *(f"{b:02X}" if padded else f"{b:X}" for b in data)]
    element = (" send " + hex_case(" ".join(words)) + " ").encode("ascii")
    verb, *args = element_words(element)
    assert verb == "send"
    assert plain_send(element) == parse_send(args) == (ident, data)


@pytest.mark.parametrize("element", [b" send 800 0 ", b" send 1 2 00 ", b" send 1 9 ",
                                     b" send 1 1 100 ", b"send 1 1 0g", b" send 1234 0 ",
                                     b" send 1 0 00 ", b" send 1 1 "])
def test_the_plain_send_path_leaves_every_mistake_to_the_parser(element: bytes) -> None:
    assert plain_send(element) is None
    verb, *args = element_words(element)
    assert verb == "send"
    with pytest.raises(ElementError):
        parse_send(args)


def _plain_send_by_expression(element: bytes) -> tuple[int, bytes] | None:
    """What :func:`plain_send` returned when it read its form with the regular expression
    that defines it (``_PLAIN_SEND``): the reference its byte-by-byte reading keeps to."""
    m = socketcand_wire._PLAIN_SEND.fullmatch(element)
    if m is None or int(m[1], 16) > 0x7FF:
        return None
    words = m[3].split()
    if len(words) != int(m[2]):
        return None
    return int(m[1], 16), bytes(int(w, 16) for w in words)


_SEND_BYTES = st.sampled_from([b" ", b"  ", b"\t", b"send", b"sen", b"0", b"1", b"7", b"8",
                               b"9", b"A", b"f", b"F", b"g", b"80", b"7FF", b"800", b"1234",
                               b"00", b"0A", b"a0", b"fff", b">", b"<", b"\x80"])


@given(st.lists(_SEND_BYTES, max_size=14).map(b"".join))
def test_the_plain_send_path_reads_exactly_its_form(element: bytes) -> None:
    assert plain_send(element) == _plain_send_by_expression(element)


@given(ident=st.integers(0, 0xFFF), dlc=st.integers(0, 9), extra=st.integers(-1, 1),
       digits=st.lists(st.integers(0, 255), min_size=10, max_size=10),
       lead=st.sampled_from([b"", b" "]), tail=st.sampled_from([b"", b" "]),
       byte_format=st.sampled_from([b"%02X", b"%X", b"%02x", b"%03X"]))
def test_the_plain_send_path_reads_exactly_its_form_near_valid_elements(
        ident: int, dlc: int, extra: int, digits: list[int], lead: bytes, tail: bytes,
        byte_format: bytes) -> None:
    words = [b"send", b"%X" % ident, b"%d" % dlc,
             *(byte_format % b for b in digits[:max(0, dlc + extra)])]
    element = lead + b" ".join(words) + tail
    assert plain_send(element) == _plain_send_by_expression(element)


def test_the_plain_send_path_leaves_unusual_spacing_to_the_parser() -> None:
    element = b"\tsend  1 1\t0A "
    assert plain_send(element) is None
    verb, *args = element_words(element)
    assert verb == "send"
    assert parse_send(args) == (1, b"\x0a")


def test_fewer_processes_than_buses_share_out_the_buses_by_boards() -> None:
    assert bus_groups(ARMAR3) == [("CAN0",), ("CAN1",), ("CAN2",), ("CAN3",)]
    assert bus_groups(ARMAR3, 2) == [("CAN0", "CAN2"), ("CAN1", "CAN3")]  # 6 and 5 boards
    assert bus_groups(ARMAR3, 1) == [("CAN0", "CAN1", "CAN2", "CAN3")]
    assert bus_groups(ARMAR3, 9) == bus_groups(ARMAR3)


@pytest.mark.parametrize("value", ["0", "-1", "two", ""])
def test_processes_is_auto_or_a_positive_number(value: str) -> None:
    result = CliRunner().invoke(cli, ["fleet", "serve", "armar3", "--processes", value])
    assert result.exit_code == 2, result.output
    assert "--processes" in result.output


@pytest.mark.parametrize("processes", ["auto", "1"])
def test_defect_makes_the_boards_of_every_bus_mutants(processes: str) -> None:
    with served("--processes", processes, "--defect", "seq-from-zero") as server:
        until(lambda: "mutant boards (seq-from-zero)" in " ".join(server.stderr().split()),
              what="the banner naming the defect")
        for spec in (ARMAR3.buses[0], ARMAR3.buses[-1]):
            with host(server.port, spec.name) as h:
                init = h.client.init_chain()  # numbering from 0: only "0" is heard
                assert {a.seq_id for a in init.acks} == {0}, spec.name
        server.interrupt()
        assert server.wait(STOP_S) == 130, server.stderr()


def test_an_unknown_defect_is_refused_before_anything_is_served() -> None:
    result = CliRunner().invoke(cli, ["fleet", "serve", "armar3", "--defect", "seq-from-one"])
    assert result.exit_code == 3
    assert "--defect: unknown defect 'seq-from-one'; known: seq-from-zero" in result.output


def test_fleet_defects_lists_the_catalogue_as_text_and_json() -> None:
    from ucom_tools.virtual.board import mutants
    text = CliRunner().invoke(cli, ["fleet", "defects"], terminal_width=200)
    assert text.exit_code == 0
    assert [line.split()[0] for line in text.output.splitlines()[1:]] == list(mutants.NAMES)
    js = CliRunner().invoke(cli, ["fleet", "defects", "--json"])
    import json
    defects = json.loads(js.output)["defects"]
    assert [d["name"] for d in defects] == list(mutants.NAMES)
    assert all(d["section"] and d["symptom"] for d in defects)


def test_bus_option_of_the_run_time_commands_opens_that_bus_by_name() -> None:
    """``--bus CAN2`` over socketcand opens the served CAN2 and expects CAN2's boards
    (not the topology's first bus under CAN2's channel)."""
    import json
    with served() as server:
        until(lambda: len(server.bus_pids()) == 4, what="four bus processes logged")
        result = subprocess.run(
            [sys.executable, "-m", "ucom_tools", "remote", "check", "armar3", "-i",
             "socketcand", "--host", LOCAL, "--port", str(server.port), "--bus", "CAN2",
             "--json"], capture_output=True, text=True, timeout=60)
        boards = json.loads(result.stdout)["boards"]
        can2 = ARMAR3.bus("CAN2")
        assert [(b["bus"], b["where"]) for b in boards] == [
            ("CAN2", f"CAN2 board {s.position + 1} ({s.placement})") for s in can2.boards]
        assert result.returncode == 1  # nothing flashed: no program starts
        assert_stops_cleanly(server, server.interrupt)


@pytest.mark.parametrize("processes", ["auto", "1"])
def test_loss_loses_frames_between_each_client_and_its_bus(processes: str) -> None:
    """``--loss 0.2``: of 400 frames one client sends, another on the bus gets about
    (1 - 0.2)^2 of them; the server says how many each lost."""
    sent = 400
    with served("--processes", processes, "--loss", "0.2", "--seed", "5") as server:
        until(lambda: "losing 20.0% of the frames each way" in " ".join(
            server.stderr().split()), what="the banner naming the loss")
        a, b = Raw(server.address), Raw(server.address)
        try:
            a.handshake("CAN1")
            b.handshake("CAN1")
            hears(b, a, "7C1 00")  # attached (retried: the loss may take any one frame)
            for k in range(sent):
                a.send(f"< send 7C0 1 {k % 256:02X} >")
            got, marked = 0, False
            a.send("< send 7C2 1 EE >")  # the end mark, sent again while it is lost
            deadline = time.monotonic() + DEADLINE_S
            while not marked and time.monotonic() < deadline:
                try:
                    words = b.element(timeout=0.3)[1:-1].split()
                except AssertionError:  # quiet: the mark was lost
                    a.send("< send 7C2 1 EE >")
                    continue
                got += words[1:2] == ["7C0"]
                marked = words[1:2] == ["7C2"]
            assert marked, "the end mark never came"
            assert 0.45 * sent < got < 0.85 * sent, got  # 0.64 expected
        finally:
            a.close()
            b.close()
        until(lambda: re.search(r"\d+ frames lost on their way to it, \d+ from it",
                                server.stderr()), what="the losses logged")
        server.interrupt()
        assert server.wait(STOP_S) == 130, server.stderr()


def test_loss_must_be_a_share_below_one() -> None:
    result = CliRunner().invoke(cli, ["fleet", "serve", "armar3", "--loss", "1"])
    assert result.exit_code == 2 and "--loss" in result.output
    from ucom_tools.errors import InputError
    from ucom_tools.virtual.fleet import Fleet
    with pytest.raises(InputError, match="client_loss: a share of frames lost must be in"):
        Fleet(ARMAR3, client_loss=-0.1)
