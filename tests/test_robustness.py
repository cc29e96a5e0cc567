"""No frame whatsoever stops a board; the fleet is a python-can interface like any other."""

from __future__ import annotations

import can
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.helpers import HeldBack
from ucom_tools.errors import FrameError
from ucom_tools.protocol.bootloader import BootloaderClient
from ucom_tools.protocol.link import Link
from ucom_tools.protocol.timeouts import DEFAULT
from ucom_tools.virtual.canbus import VirtualUcomBus
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.wire import messages as m
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


class _LateAcks:
    """What :class:`~tests.helpers.HeldBack` holds: the first ``count`` Init Acks of board
    number ``number`` (the PC asks again, the board answers again, the first answer comes
    after all)."""

    def __init__(self, number: int, count: int = 1) -> None:
        self.number, self.count = number, count

    def __call__(self, msg: can.Message) -> bool:
        try:
            _, got = m.decode(msg.arbitration_id, bytes(msg.data))
        except FrameError:
            return False
        if self.count and isinstance(got, m.InitAck) and got.seq_id == self.number:
            self.count -= 1
            return True
        return False


def test_an_init_ack_that_comes_after_its_retry_costs_the_chain_nothing() -> None:
    """Board 2's first answer is held back past the step's wait: the host asks again, the
    board answers again, the chain goes on, and the late answer is recorded as what it is
    (every Init Ack seen, in order: the conformance suite counts them) without making
    the board two boards or cutting the chain short."""
    fleet = Fleet.load("armar3")
    late = _LateAcks(2)
    bus = HeldBack(VirtualUcomBus("CAN0", fleet=fleet), late, delay=2 * DEFAULT.init_step)
    try:
        client = BootloaderClient(Link(bus))
        result = client.init_chain()
        assert late.count == 0 and not bus.held  # the first answer was held back, then came
        serials = [b.identity.serial for b in sorted(fleet.boards["CAN0"],
                                                     key=lambda b: b.identity.position)]
        expected = list(zip((1, 2, 3), serials, strict=True))
        assert [(a.seq_id, a.serial) for a in result.acks][:3] == expected
        assert [(a.seq_id, a.serial) for a in result.acks[3:]] == [expected[1]]  # the late one
        assert result.numbers == [1, 2, 3] and not result.duplicates()
        for n, serial in expected:
            assert client.info(seq(n)).serial == serial
    finally:
        bus.shutdown()
