"""``ucom fleet serve ROBOT --extra-bus NAME``: a served bus with no boards on it, where
clients in other processes meet (a CANopen gateway and its master).

The server is ``python -m ucom_tools fleet serve armar3`` on 127.0.0.1 and a free port
(:func:`tests.test_multiserve.served`); the clients are python-can's own socketcand
interface, and canopen's ``Network`` over it.  A client is put on its bus 20 ms after
its rawmode answer, so each test first waits until the clients hear each other
(:func:`meet`: a probe sent until it arrives, with a deadline); nothing sleeps to
synchronise."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator

import can
import canopen
import pytest
from canopen.objectdictionary import ObjectDictionary, ODVariable
from click.testing import CliRunner

from tests.test_multiserve import LOCAL, STOP_S, served, until
from ucom_tools.cli.main import cli

DEADLINE_S = 10.0
PROBE = 0x7E5
"""The identifier of :func:`meet`'s probes (not used by the frames under test)."""


@contextlib.contextmanager
def clients(port: int, *channels: str) -> Iterator[list[can.BusABC]]:
    """A python-can socketcand client on each channel."""
    buses: list[can.BusABC] = []
    try:
        for channel in channels:
            buses.append(can.Bus(interface="socketcand", host=LOCAL, port=port,
                                 channel=channel))
        yield buses
    finally:
        for bus in buses:
            bus.shutdown()


def meet(sender: can.BusABC, *receivers: can.BusABC) -> None:
    """Wait until each of ``receivers`` hears ``sender`` (all are on the bus): a probe
    every 20 ms until each has one, within :data:`DEADLINE_S`; then nothing of it is
    left to read: the last probe every receiver had, and a marker frame after it."""
    deadline = time.monotonic() + DEADLINE_S
    heard = set()
    while len(heard) < len(receivers):
        if time.monotonic() > deadline:
            pytest.fail(f"the clients did not meet within {DEADLINE_S} s")
        sender.send(can.Message(arbitration_id=PROBE, data=b"\x01", is_extended_id=False))
        for i, bus in enumerate(receivers):
            msg = bus.recv(0.02 / len(receivers))
            while msg is not None:
                if msg.arbitration_id == PROBE and not msg.is_error_frame:
                    heard.add(i)
                msg = bus.recv(0.0)
    sender.send(can.Message(arbitration_id=PROBE, data=b"\x02", is_extended_id=False))
    for bus in receivers:  # read up to the marker: the frames after it are the test's
        received(bus, 0)


def received(bus: can.BusABC, count: int) -> list[can.Message]:
    """The next ``count`` data frames on ``bus`` (error frames and probes skipped, up to
    :func:`meet`'s marker included), within :data:`DEADLINE_S`."""
    deadline = time.monotonic() + DEADLINE_S
    got: list[can.Message] = []
    marker = count == 0
    while len(got) < count or marker:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            pytest.fail(f"{len(got)} of {count} frames within {DEADLINE_S} s")
        msg = bus.recv(remaining)
        if msg is None or msg.is_error_frame:
            continue
        if msg.arbitration_id == PROBE:
            marker = marker and msg.data != b"\x02"
            continue
        got.append(msg)
    return got


def frames(base: int, count: int) -> list[can.Message]:
    return [can.Message(arbitration_id=base + i % 16, data=bytes([i, i >> 8, 0xA5]),
                        is_extended_id=False) for i in range(count)]


def test_every_frame_of_a_client_reaches_every_other_client_in_order() -> None:
    with served("--extra-bus", "CO0", "--extra-bus", "co.1") as server:
        until(lambda: "CO0, co.1 without boards (--extra-bus)" in " ".join(
            server.stderr().split()), what="the banner naming the extra buses")
        with clients(server.port, "CO0", "CO0", "CO0", "co.1", "co.1") as buses:
            a, b, c, d, e = buses
            meet(a, b, c)
            meet(b, a)
            meet(e, d)
            sent = [*frames(0x180, 200), can.Message(arbitration_id=0x1ABCDEF0,
                                                     data=b"\x01\x02", is_extended_id=True)]
            for msg in sent:
                a.send(msg)
            for bus in (b, c):
                got = received(bus, len(sent))
                assert [(m.arbitration_id, m.is_extended_id, bytes(m.data)) for m in got] \
                    == [(m.arbitration_id, m.is_extended_id, bytes(m.data)) for m in sent]
                stamps = [m.timestamp for m in got]
                assert stamps == sorted(stamps)
            b.send(can.Message(arbitration_id=0x5FF, data=bytes(range(8)),
                               is_extended_id=False))
            for bus in (a, c):  # the reply reaches the others (a: its first after the probes)
                (got_reply,) = received(bus, 1)
                assert (got_reply.arbitration_id, bytes(got_reply.data)) == (0x5FF,
                                                                             bytes(range(8)))
            e.send(can.Message(arbitration_id=0x77, data=b"\x77", is_extended_id=False))
            (first,) = received(d, 1)  # another extra bus: nothing of CO0's came to it
            assert (first.arbitration_id, bytes(first.data)) == (0x77, b"\x77")
        server.interrupt()
        assert server.wait(STOP_S) == 130, server.stderr()


def test_a_client_alone_on_an_extra_bus_is_not_acknowledged() -> None:
    """As on a real bus with one node: its frame gets the error frame of a missing
    acknowledge (CAN_ERR_ACK), and nothing else comes."""
    with served("--processes", "1", "--extra-bus", "CO0") as server, \
            clients(server.port, "CO0") as (alone,):
        alone.send(can.Message(arbitration_id=0x701, data=b"\x00", is_extended_id=False))
        msg = alone.recv(DEADLINE_S)
        assert msg is not None and msg.is_error_frame and msg.arbitration_id == 0x20


def _od() -> ObjectDictionary:
    od = ObjectDictionary()
    name = ODVariable("Manufacturer device name", 0x1008, 0)
    name.data_type, name.access_type = 0x09, "const"  # VISIBLE_STRING
    name.default = "Right Eye"
    od.add_object(name)
    return od


def test_canopen_networks_on_both_sides_do_an_sdo_upload() -> None:
    """A segmented SDO upload (9 bytes: three frames each way) between canopen's
    LocalNode and RemoteNode, each in a Network of its own over the extra bus."""
    with served("--extra-bus", "CO0") as server, \
            clients(server.port, "CO0", "CO0") as (slave_bus, master_bus):
        meet(master_bus, slave_bus)
        meet(slave_bus, master_bus)
        slave, master = canopen.Network(slave_bus), canopen.Network(master_bus)
        slave.connect()
        master.connect()
        try:
            slave.add_node(canopen.LocalNode(12, _od()))
            node = master.add_node(canopen.RemoteNode(12, _od()))
            assert node.sdo.upload(0x1008, 0) == b"Right Eye"
            assert node.sdo[0x1008].raw == "Right Eye"
        finally:
            master.disconnect()
            slave.disconnect()


@pytest.mark.parametrize(("names", "message"), [
    (["CAN0"], "'CAN0' is a bus of ARMAR-III (CAN0, CAN1, CAN2, CAN3); an extra bus needs "
               "a name of its own"),
    (["CO0", "CO0"], "'CO0' is given twice"),
    (["bad name"], "'bad name' is not a channel name"),
    (["0CO"], "'0CO' is not a channel name"),
    (["CO/1"], "'CO/1' is not a channel name"),
    (["C" * 16], "is not a channel name: 1-15 characters"),
])
def test_extra_bus_names_are_checked_before_anything_is_served(names: list[str],
                                                               message: str) -> None:
    args = [word for name in names for word in ("--extra-bus", name)]
    result = CliRunner().invoke(cli, ["fleet", "serve", "armar3", "--port", "0", *args],
                                terminal_width=400)
    assert result.exit_code == 2, result.output
    assert message in " ".join(result.output.split())
    assert "listening" not in result.output


def test_processes_count_the_extra_buses() -> None:
    """--processes N: at most one process per bus, the extra ones counted."""
    result = CliRunner().invoke(cli, ["fleet", "serve", "armar3", "--processes", "6",
                                      "--extra-bus", "CO0"], terminal_width=400)
    assert result.exit_code == 2
    assert "which has 5 buses" in " ".join(result.output.split())
