"""``ucom fleet fault`` against ``ucom fleet serve``: the ``< ucom_fault ... >`` element on
the socketcand port, in one process and with a process per bus (a board's fault to its
bus's process, the emergency stop to every one), a served scenario, the exit codes, and
python-can's own socketcand client, which still talks to the server.

Every wait has a deadline; nothing sleeps to synchronise (conditions are polled)."""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
from click.testing import CliRunner

from tests.helpers import served_in_process
from tests.test_multiserve import LOCAL, Raw, served, until
from ucom_tools.cli.main import cli
from ucom_tools.config import topology as topo
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import InitAckKind, InitOp
from ucom_tools.wire.ids import ALL, Function, encode_id

ARMAR3 = topo.load("armar3")
PROBE = m.InitRequest(InitOp.PROBE_FIRST)
"""Every powered board whose init input is free answers Init Ack FIRST: the first one of
its bus (one with an unpowered predecessor too), none while the PC cannot reach them."""


def fault(port: int, *args: str) -> tuple[int, str]:
    result = CliRunner().invoke(cli, ["fleet", "fault", "--host", LOCAL, "--port", str(port),
                                      *args])
    return result.exit_code, result.output


def first_serials(raws: dict[str, Raw], wait_s: float = 0.3) -> dict[str, set[int]]:
    """PROBE_FIRST on every bus at once; the serials that answered within ``wait_s``."""
    for raw in raws.values():
        raw.send(f"< send 280 2 0{InitOp.PROBE_FIRST:X} 00 >")
    out: dict[str, set[int]] = {}
    deadline = time.monotonic() + wait_s
    for bus, raw in raws.items():  # (the answers of the later buses have come meanwhile)
        out[bus] = set()
        while True:
            try:
                words = raw.element(max(0.02, deadline - time.monotonic()))[1:-1].split()
            except AssertionError:  # nothing more within the wait
                break
            if words[0] == "frame" and int(words[1], 16) >> 6 == Function.INIT_ACK:
                ack = m.InitAck.decode(bytes.fromhex(words[3]))
                if ack.kind is InitAckKind.FIRST:
                    out[bus].add(ack.serial)
    return out


def serial(bus: str, n: int) -> int:
    return ARMAR3.bus(bus).boards[n - 1].serial


# ---------------------------------------------------------------------- one process
@pytest.fixture
def one_process() -> Iterator[tuple[object, int]]:
    with served_in_process("armar3") as (fleet, port):
        yield fleet, port


def test_a_fault_by_hand_is_applied_at_once_and_answered(one_process) -> None:
    fleet, port = one_process
    board = fleet.boards["CAN0"][2]  # type: ignore[attr-defined]
    code, out = fault(port, "CAN0/3", "power-off", "--for", "0.4")
    assert (code, out) == (0, "CAN0 board 3 (head right) powered off for 0.4 s\n")
    assert not board.powered  # applied before the answer came
    (shown,) = fleet.snapshot()["injected"]  # type: ignore[attr-defined]
    assert (shown["target"], shown["until_s"] - shown["since_s"]) == ("CAN0/3",
                                                                       pytest.approx(0.4))
    code, out = fault(port, "CAN1", "cable", "--for", "0.5", "--json")
    assert code == 0 and json.loads(out) == {
        "server": f"{LOCAL}:{port}", "kind": "cable", "target": "CAN1", "bus": "CAN1",
        "board": None, "for_s": 0.5, "done": "CAN1 cut from the PC for 0.5 s"}
    code, out = fault(port, "robot", "estop", "--for", "0.2")
    assert code == 0 and out.startswith("emergency stop: all 11 boards of ARMAR-III")
    until(lambda: all(b.powered for bs in fleet.boards.values()  # type: ignore[attr-defined]
                      for b in bs if b is not board), what="power back after the estop")
    until(lambda: board.powered, what="its own power-off over")


def test_the_exit_codes_say_what_went_wrong(one_process) -> None:
    fleet, port = one_process
    code, out = fault(port, "CAN0/9", "bus-off", "--for", "1")
    assert code == 3, out
    assert f"{LOCAL}:{port} refused it: board: no board 9 on CAN0; its boards: 1 (neck)" in out
    code, out = fault(port, "CAN7", "cable", "--for", "1")
    assert code == 3 and "no bus 'CAN7' in ARMAR-III; its buses: CAN0, CAN1" in out, out
    for words, message in [
            (["CAN0", "power-off", "--for", "1"], "power-off acts on a board"),
            (["CAN0/1", "cable", "--for", "1"], "cable acts on a bus"),
            (["CAN0/1", "melt", "--for", "1"], "'melt' is no fault kind"),
            (["CAN0/1", "bus-off"], "bus-off needs a duration"),
            (["CAN0/1"], "give TARGET KIND")]:
        code, out = fault(port, *words)
        assert code == 2 and message in out, (words, out)
    assert fleet.snapshot()["injected"] == []  # type: ignore[attr-defined]  # nothing done
    with socket.socket() as unused:  # a port where nobody listens
        unused.bind((LOCAL, 0))
        free = unused.getsockname()[1]
    code, out = fault(free, "estop", "--for", "1")
    assert code == 4 and f"cannot connect to {LOCAL}:{free}" in out, out


def test_a_server_that_does_not_take_faults_is_named() -> None:
    """A socketcand server without the extension (socketcand itself) refuses the element."""
    listener = socket.create_server((LOCAL, 0))
    port = listener.getsockname()[1]

    def serve() -> None:
        conn, _ = listener.accept()
        with conn:
            conn.sendall(b"< hi >")
            conn.recv(4096)
            conn.sendall(b"< error unsupported command ucom_fault >")
            conn.recv(4096)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        code, out = fault(port, "estop", "--for", "1")
    finally:
        thread.join(5)
        listener.close()
    assert code == 4 and "does not take faults (no ucom fleet serve?)" in out, out


def test_the_element_is_refused_on_a_bus_connection_and_python_can_still_talks(
        one_process) -> None:
    _fleet, port = one_process
    raw = Raw((LOCAL, port))
    try:
        raw.handshake("CAN0")
        raw.send("< ucom_fault CAN0/1 bus-off 1 >")
        assert raw.element() == ("< error ucom_fault: send it on a connection of its own, "
                                 "before any open>")
    finally:
        raw.close()
    raw = Raw((LOCAL, port))
    try:
        assert raw.element() == "< hi >"
        raw.send("< ucom_fault CAN0/1 bus-off one >")
        assert raw.element() == "< error ucom_fault: SECONDS one is not a decimal number >"
        raw.send("< ucom_fault CAN0/1 bus-off 0.05 >")
        assert raw.element() == "< ok CAN0 board 1 (neck) bus-off for 0.05 s >"
    finally:
        raw.close()
    with can.Bus(interface="socketcand", host=LOCAL, port=port, channel="CAN2") as bus:
        bus.send(can.Message(arbitration_id=encode_id(Function.INIT_REQUEST, ALL),
                             data=PROBE.encode(), is_extended_id=False))
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            msg = bus.recv(0.5)
            if msg is not None and msg.arbitration_id >> 6 == Function.INIT_ACK:
                assert m.InitAck.decode(bytes(msg.data)).serial == serial("CAN2", 1)
                break
        else:
            pytest.fail("python-can's socketcand client got no answer")


# ---------------------------------------------------------------------- a process per bus
def test_a_process_per_bus_routes_each_fault_and_the_estop_reaches_every_bus(
        tmp_path: Path) -> None:
    scenario = tmp_path / "cable.toml"
    scenario.write_text('[[fault]]\nat = 0\nkind = "cable"\nbus = "CAN1"\nfor = 1.5\n')
    with served("--processes", "2", "--scenario", str(scenario)) as server:
        raws = {b.name: Raw(server.address) for b in ARMAR3.buses}
        try:
            for bus, raw in raws.items():
                raw.handshake(bus)
            firsts = {b.name: {serial(b.name, 1)} for b in ARMAR3.buses}
            until(lambda: first_serials(raws) == firsts, what="every bus's first board")
            # the scenario: CAN1's cable is cut from its first MCA Alive on
            raws["CAN1"].send(f"< send {encode_id(Function.MCA_ALIVE, ALL):03X} 0 >")
            got = first_serials(raws)
            assert got["CAN1"] == set() and got["CAN0"] == firsts["CAN0"], got
            # a board's fault goes to its bus's process: CAN2's first board off, so the
            # second one sees no predecessor
            code, out = fault(server.port, "CAN2/1", "power-off", "--for", "30")
            assert (code, out) == (0, "CAN2 board 1 (left shoulder front) powered off for "
                                      "30 s\n")
            assert first_serials(raws)["CAN2"] == {serial("CAN2", 2)}
            # the emergency stop reaches every process and every bus
            code, out = fault(server.port, "estop", "--for", "1.2")
            assert (code, out) == (0, "emergency stop: all 11 boards of ARMAR-III (CAN0, "
                                      "CAN1, CAN2, CAN3) powered off for 1.2 s\n")
            assert first_serials(raws) == {b.name: set() for b in ARMAR3.buses}
            firsts["CAN2"] = {serial("CAN2", 2)}  # its own power-off outlasts the estop
            until(lambda: first_serials(raws) == firsts, what="every board back but one")
            assert "injected a fault: emergency stop" in server.stderr()
        finally:
            for raw in raws.values():
                raw.close()
        server.interrupt()
        assert server.wait() == 130, server.stderr()
    assert "Traceback" not in server.stderr()
