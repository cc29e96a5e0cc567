"""Flashing the way users run it (issue 8, B): over socketcand to a served fleet, with a
second client on the bus, with frames lost, and with servers that stay silent or drop the
connection.  The fleet runs in real time in this process; the host side is the real CLI
and the real ucom socketcand client."""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress

import pytest
from click.testing import CliRunner, Result

from ucom_tools.cli.main import cli
from ucom_tools.config.topology import load
from ucom_tools.image.formats import load_image
from ucom_tools.ops.flash import flash
from ucom_tools.ops.flash_types import FlashRequest
from ucom_tools.ops.robot import BusHandle, ConnectSpec, Robot
from ucom_tools.protocol.bootloader import BootloaderClient
from ucom_tools.protocol.link import Link
from ucom_tools.transport.socketcand import SocketcandBus
from ucom_tools.virtual.bus.loss import LossyBus
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.virtual.serve.socketcand import FleetServer

BIG = "firmware_images/bench64k.fl.S"  # 64 KiB
TOPOLOGY = "tests/data/armar3_can0.toml"


def ucom(*args: str) -> Result:
    return CliRunner().invoke(cli, list(args))


@contextmanager
def served(topology: str = "armar3") -> Iterator[tuple[int, Fleet]]:
    fleet = Fleet.load(topology, realtime=True)
    server = FleetServer(fleet, "127.0.0.1", 0)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield server.address[1], fleet
    finally:
        server.shutdown()
        server.server_close()
        thread.join(10)
        fleet.close()


def remote(port: int) -> list[str]:
    return ["-i", "socketcand", "--host", "127.0.0.1", "--port", str(port)]


class Neighbour:
    """A second client on the bus: asks every board for its Info, again and again, and
    reads what comes back; counts the frames it saw."""

    def __init__(self, port: int, channel: str = "CAN0") -> None:
        self.bus = SocketcandBus(channel, "127.0.0.1", port)
        self.frames = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        import can

        request = can.Message(arbitration_id=0x200, data=b"", is_extended_id=False)
        while not self.stop.is_set():
            self.bus.send(request)
            deadline = time.monotonic() + 0.05
            while (left := deadline - time.monotonic()) > 0:
                if self.bus.recv(left) is not None:
                    self.frames += 1

    def __enter__(self) -> Neighbour:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(10)
        self.bus.shutdown()


def test_a_64_kib_image_over_socketcand_verifies_with_a_second_client_on_the_bus() -> None:
    with served() as (port, fleet), Neighbour(port) as neighbour:
        r = ucom("flash", BIG, *remote(port), "--topology", TOPOLOGY, "--json")
        assert r.exit_code == 0, r.stderr + r.stdout[-2000:]
        data = json.loads(r.stdout)
        assert [(b["placement"], b["outcome"]) for b in data["boards"]] == [
            ("neck", "verified"), ("head left", "verified"), ("head right", "verified")]
        assert neighbour.frames > 100  # the neighbour was busy all along
    image = load_image(BIG)
    board = fleet.boards["CAN0"][2]
    assert board.nv.record.flash_valid and board.nv.record.progid == image.progid


def test_a_topology_board_that_never_answers_fails_a_socketcand_flash() -> None:
    """The issue's case: a topology of 4 boards on a bus where 3 answer."""
    with served() as (port, _fleet):
        r = ucom("flash", "firmware_images/armar3.fl.S", *remote(port), "--topology",
                 "tests/data/arm_ok.toml", "--bus", "CAN1", "--json")
    assert r.exit_code == 1, r.stderr
    boards = json.loads(r.stdout)["boards"]
    assert [b["outcome"] for b in boards].count("verified") == 3
    missing = [b for b in boards if b["outcome"] == "missing"]
    assert len(missing) == 2 and all("no board there answered" in b["detail"] for b in missing)


def test_one_percent_loss_over_socketcand_still_verifies() -> None:
    with served() as (port, _fleet):
        topo = load(TOPOLOGY)
        bus = LossyBus(SocketcandBus("CAN0", "127.0.0.1", port), loss=0.01, seed=7)
        link = Link(bus, "CAN0", margin=0.25)
        handle = BusHandle("CAN0", bus, link, BootloaderClient(link), topo.bus("CAN0"),
                           virtual=False)
        robot = Robot(ConnectSpec(interface="socketcand"), {"CAN0": handle}, topo)
        try:
            result = flash(robot, FlashRequest(load_image("firmware_images/armar3.fl.S")))
        finally:
            robot.close()
        assert bus.dropped["tx"] > 0
        assert [b.outcome for b in result.boards] == ["verified"] * 3, [
            b.detail for b in result.boards]


# ----------------------------------------------------------------------------- B11
@contextmanager
def silent_server() -> Iterator[int]:
    """Accepts connections and never says a word."""
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        held: list[socket.socket] = []
        done = threading.Event()

        def accept() -> None:
            listener.settimeout(0.2)
            while not done.is_set():
                try:
                    held.append(listener.accept()[0])
                except TimeoutError:
                    continue
                except OSError:
                    return

        thread = threading.Thread(target=accept, daemon=True)
        thread.start()
        try:
            yield listener.getsockname()[1]
        finally:
            done.set()
            thread.join(5)
            for s in held:
                s.close()


def test_a_server_that_accepts_and_stays_silent_is_a_bus_failure_not_a_hang() -> None:
    with silent_server() as port:
        t0 = time.monotonic()
        r = ucom("init", *remote(port), "-c", "CAN0")
        elapsed = time.monotonic() - t0
    assert r.exit_code == 4
    assert f"socketcand 127.0.0.1:{port} did not answer the connection within 2 s" in r.stderr
    assert elapsed < 10 and "Traceback" not in r.stderr


class CuttingProxy:
    """Forwards a socketcand connection to ``target`` and cuts it (both ways) once the
    client has sent ``cut_after`` bytes."""

    def __init__(self, target: int, cut_after: int) -> None:
        self.target = target
        self.cut_after = cut_after
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.cut = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        client, _ = self.listener.accept()
        upstream = socket.create_connection(("127.0.0.1", self.target))
        sent = 0

        def down() -> None:
            try:
                while chunk := upstream.recv(65536):
                    client.sendall(chunk)
            except OSError:
                pass

        threading.Thread(target=down, daemon=True).start()
        try:
            while sent < self.cut_after and (chunk := client.recv(4096)):
                upstream.sendall(chunk)
                sent += len(chunk)
        except OSError:
            pass
        self.cut.set()
        for s in (client, upstream):
            with suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            s.close()

    def close(self) -> None:
        self.listener.close()
        self.thread.join(10)


def test_a_connection_lost_mid_flash_is_a_bus_failure_naming_the_server() -> None:
    with served() as (port, _fleet):
        proxy = CuttingProxy(port, cut_after=40_000)  # well into the data frames
        try:
            r = ucom("flash", BIG, *remote(proxy.port), "-c", "CAN0")
        finally:
            proxy.close()
    assert proxy.cut.is_set()
    assert r.exit_code == 4, r.stdout[-1500:] + r.stderr
    assert f"socketcand 127.0.0.1:{proxy.port}" in r.stderr
    assert "closed the connection" in r.stderr or "connection lost" in r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.parametrize("cut_after", [10, 60])  # in the handshake; after two requests
def test_a_connection_lost_early_is_a_bus_failure_too(cut_after: int) -> None:
    with served("rosi") as (port, _fleet):
        proxy = CuttingProxy(port, cut_after=cut_after)
        try:
            r = ucom("init", *remote(proxy.port), "-c", "CAN0")
        finally:
            proxy.close()
    assert proxy.cut.is_set()
    assert r.exit_code == 4, r.stdout + r.stderr
    assert f"socketcand 127.0.0.1:{proxy.port}" in r.stderr
    assert "Traceback" not in r.stderr
