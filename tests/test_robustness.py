"""No frame whatsoever stops a board; the fleet is a python-can interface like any other."""

from __future__ import annotations

import can
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ucom_tools.protocol.bootloader import BootloaderClient
from ucom_tools.protocol.link import Link
from ucom_tools.virtual.canbus import VirtualUcomBus
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.wire.ids import seq

frames = st.lists(st.tuples(st.integers(0, 0x7FF), st.binary(max_size=8)), min_size=1,
                  max_size=40)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(frames)
def test_arbitrary_frames_never_stop_a_board(junk: list[tuple[int, bytes]]) -> None:
    fleet = Fleet.load("armar3")
    bus = VirtualUcomBus("CAN0", fleet=fleet)
    try:
        client = BootloaderClient(Link(bus))
        assert [a.seq_id for a in client.init_chain().acks] == [1, 2, 3]
        for arb, data in junk:
            bus.send(can.Message(arbitration_id=arb, data=data, is_extended_id=False))
        while bus.recv(0.05) is not None:
            pass
        # whatever happened (a reset, a new seq ID, a started transfer), every board is
        # alive and answers after a fresh init
        result = client.init_chain()
        assert sorted(a.serial for a in result.acks) == sorted(
            b.identity.serial for b in fleet.boards["CAN0"])
        for n in (1, 2, 3):
            assert client.info(seq(n)).seq_id == n
    finally:
        bus.shutdown()


def test_python_can_finds_the_virtual_fleet_by_interface_name() -> None:
    with can.Bus(interface="ucom_virtual", channel="rosi/CAN0") as bus:
        client = BootloaderClient(Link(bus))
        assert len(client.init_chain().acks) == 1
    from ucom_tools.virtual.fleet import forget_shared
    forget_shared()
