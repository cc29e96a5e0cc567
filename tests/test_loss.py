"""Flashing over a bus that loses frames: at random (seeded), and one chosen frame at a
time.  The real host code (ops.flash and the protocol clients) runs over a python-can
wrapper that drops frames in both directions; the virtual boards are the real peers."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import can
import pytest

from tests.helpers import image_words, plan_of
from ucom_tools.config.topology import load
from ucom_tools.image.formats import load_image
from ucom_tools.ops.flash import flash
from ucom_tools.ops.flash_types import FlashRequest
from ucom_tools.ops.robot import BusHandle, ConnectSpec, Robot
from ucom_tools.protocol.bootloader import BootloaderClient
from ucom_tools.protocol.link import Link
from ucom_tools.virtual.bus.loss import DropRule, LossyBus
from ucom_tools.virtual.canbus import VirtualUcomBus
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.wire.codes import ReadyReason, Space, StatusOp
from ucom_tools.wire.ids import ALL, Function, seq

IMAGE = load_image("firmware_images/armar3.fl.S")


@contextmanager
def lossy_robot(*, loss: float = 0.0, seed: int = 0, drop: DropRule | None = None,
                topology: str = "armar3", bus: str = "CAN0") -> Iterator[tuple[Robot, Fleet]]:
    fleet = Fleet.load(topology)
    topo = load(topology)
    lossy = LossyBus(VirtualUcomBus(bus, fleet=fleet), loss=loss, seed=seed, drop=drop)
    link = Link(lossy, bus)
    handle = BusHandle(bus, lossy, link, BootloaderClient(link), topo.bus(bus), virtual=True)
    robot = Robot(ConnectSpec(virtual=topology), {bus: handle}, topo)
    try:
        yield robot, fleet
    finally:
        robot.close()


def flash_holds_image(fleet: Fleet, bus: str, n: int) -> bool:
    """The board's flash really holds every word of the image (not just its claim)."""
    board = fleet.boards[bus][n - 1]
    for (space, address), word in IMAGE.words.items():
        mem = board.nv.space(space)
        if mem.read(address, 1)[0] != word:
            return False
    return True


@pytest.mark.parametrize("seed", range(5))
def test_one_percent_loss_both_ways_five_of_five_flashes_verify(seed: int) -> None:
    with lossy_robot(loss=0.01, seed=seed) as (robot, fleet):
        result = flash(robot, FlashRequest(IMAGE))
        lossy = robot.buses["CAN0"].bus
        assert isinstance(lossy, LossyBus)
        assert lossy.dropped["tx"] > 10  # frames were lost (few come back: rx losses are rare)
        assert [(b.seq_id, b.outcome) for b in result.boards] == [
            (1, "verified"), (2, "verified"), (3, "verified")], [b.detail for b in result.boards]
        (bus,) = result.buses
        assert bus.rounds >= 2 and bus.resent_frames < 1000  # frames, not whole blocks
        for n in (1, 2, 3):
            assert flash_holds_image(fleet, "CAN0", n)


def test_five_percent_loss_still_verifies() -> None:
    with lossy_robot(loss=0.05, seed=11) as (robot, fleet):
        result = flash(robot, FlashRequest(IMAGE))
        assert all(b.verified for b in result.boards), [b.detail for b in result.boards]
        assert len(result.boards) == 3
        assert all(flash_holds_image(fleet, "CAN0", n) for n in (1, 2, 3))


def once(predicate: DropRule) -> DropRule:
    """Drop the first frame the predicate matches, and no other."""
    state = {"done": False}

    def rule(direction: str, msg: can.Message) -> bool:
        if not state["done"] and predicate(direction, msg):
            state["done"] = True
            return True
        return False
    return rule


def fn(msg: can.Message) -> int:
    return msg.arbitration_id >> 6


SINGLE_LOSSES = {
    "Init BEGIN": lambda d, msg: d == "tx" and fn(msg) == Function.INIT_REQUEST
    and msg.data[0] == 1,
    "Init Ack of board 2": lambda d, msg: d == "rx" and msg.arbitration_id == 0x0C2,
    "Init NEXT 3": lambda d, msg: d == "tx" and fn(msg) == Function.INIT_REQUEST
    and bytes(msg.data) == b"\x02\x03",
    "an Info frame": lambda d, msg: d == "rx" and fn(msg) == Function.INFO
    and msg.data[0] == 4,
    "the ProgEnable answer": lambda d, msg: d == "rx" and fn(msg) == Function.READY
    and msg.data[0] == ReadyReason.STATUS,
    "Program BEGIN": lambda d, msg: d == "tx" and fn(msg) == Function.PROGRAM
    and len(msg.data) < 8 and msg.data[0] == 1,
    "a META frame": lambda d, msg: d == "tx" and fn(msg) == Function.PROGRAM
    and len(msg.data) == 6 and msg.data[0] == 2,
    "an ERASE frame": lambda d, msg: d == "tx" and fn(msg) == Function.PROGRAM
    and len(msg.data) == 6 and msg.data[0] == 3,
    "PREPARE": lambda d, msg: d == "tx" and fn(msg) == Function.PROGRAM
    and len(msg.data) == 3 and msg.data[0] == 4,
    "Ready ERASED": lambda d, msg: d == "rx" and fn(msg) == Function.READY
    and msg.data[0] == ReadyReason.ERASED,
    "a BLOCK frame": lambda d, msg: d == "tx" and fn(msg) == Function.PROGRAM
    and len(msg.data) == 7,
    "a data frame": lambda d, msg: d == "tx" and fn(msg) == Function.PROGRAM
    and len(msg.data) == 8,
    "END": lambda d, msg: d == "tx" and fn(msg) == Function.PROGRAM
    and len(msg.data) == 1 and msg.data[0] == 6,
    "Program Finished": lambda d, msg: d == "rx" and fn(msg) == Function.PROGRAM_FINISHED,
    "the Info read-back": lambda d, msg: d == "tx" and fn(msg) == Function.INFO_REQUEST
    and msg.arbitration_id != 0x200,
}


@pytest.mark.parametrize("what", SINGLE_LOSSES)
def test_a_single_lost_frame_is_asked_again_not_a_board_failure(what: str) -> None:
    with lossy_robot(drop=once(SINGLE_LOSSES[what])) as (robot, fleet):
        result = flash(robot, FlashRequest(IMAGE))
        lossy = robot.buses["CAN0"].bus
        assert isinstance(lossy, LossyBus)
        assert sum(lossy.dropped.values()) == 1, what
        assert [b.outcome for b in result.boards] == ["verified"] * 3, [
            b.detail for b in result.boards]
        assert all(flash_holds_image(fleet, "CAN0", n) for n in (1, 2, 3))


def test_a_lost_resume_costs_the_drain_time_not_the_transfer(host) -> None:
    """Slow flash makes the boards pause; every RESUME is lost."""
    from tests.conftest import chain_topology

    fleet = chain_topology(2, timing="[timing]\nword_program_us = 80.0")
    inner = VirtualUcomBus("CAN0", fleet=fleet)
    lossy = LossyBus(inner, drop=lambda d, msg: d == "rx" and fn(msg) == Function.READY
                     and msg.data[0] == ReadyReason.RESUME)
    try:
        link = Link(lossy, "CAN0")
        client = BootloaderClient(link)
        from ucom_tools.protocol.programmer import Programmer

        init = client.init_chain()
        client.set_status(ALL, StatusOp.PROG_ENABLE, 1, expect=[seq(1), seq(2)])
        plan = plan_of(image_words(4000))
        result = Programmer(link).transfer(plan, [seq(n) for n in init.numbers])
        assert lossy.dropped["rx"] > 0  # RESUMEs were lost
        assert result.all_verified
    finally:
        lossy.shutdown()


def test_a_board_that_never_gets_a_block_is_never_reported_verified() -> None:
    """Board 2 misses every data frame of block 3, in every round: the others verify,
    it fails, naming what is missing, and its flash is not marked valid."""
    fleet = Fleet.load("armar3")
    victim = fleet.boards["CAN0"][1]
    state = {"block": -1}

    def deaf(node: object, arb: int, data: bytes) -> bool:
        if arb >> 6 != Function.PROGRAM or node is not victim:
            return False
        if len(data) == 7:
            state["block"] = data[4]
            return False
        return len(data) == 8 and state["block"] == 3

    fleet.buses["CAN0"].drop = deaf
    topo = load("armar3")
    bus = VirtualUcomBus("CAN0", fleet=fleet)
    link = Link(bus, "CAN0")
    handle = BusHandle("CAN0", bus, link, BootloaderClient(link), topo.bus("CAN0"), virtual=True)
    robot = Robot(ConnectSpec(virtual="armar3"), {"CAN0": handle}, topo)
    try:
        result = flash(robot, FlashRequest(IMAGE))
        outcomes = {b.seq_id: b for b in result.boards}
        assert outcomes[1].verified and outcomes[3].verified
        assert not outcomes[2].verified
        assert "still missing" in outcomes[2].detail and "no progress" in outcomes[2].detail
        assert not victim.nv.record.flash_valid
        assert not handle.client.info(seq(2)).flash_valid
    finally:
        robot.close()


def test_data_frames_of_a_block_addressed_to_another_board_are_not_stored(host) -> None:
    """A BLOCK frame addressed to board 2 opens a block for board 2 only: board 1, also in
    the transfer, ignores the data frames that follow it."""
    h = host("armar3", "CAN0")
    from tests.helpers import enable_all
    from ucom_tools.wire import messages as m

    h.client.init_chain()
    enable_all(h)
    plan = plan_of(image_words(64 * 4 - 4))  # one block: P:0004-00FF
    for frame in (plan.begin(), *plan.meta(), *plan.erases(), plan.prepare()):
        h.link.send(frame, ALL)
    h.link.drain(0.2)
    block = plan.blocks[0]
    h.link.send(block.header(), seq(2))
    for frame in block.data_frames():
        h.link.send(frame, ALL)
    h.link.send(m.ProgramEnd(), ALL)
    results = {g.address.number: g.message for g in h.link.drain(0.1)
               if isinstance(g.message, m.ProgramResult)}
    assert results[2].status.name == "VERIFIED"
    assert results[1].status.name == "MISSING" and results[3].status.name == "MISSING"
    assert h.boards[0].nv.space(Space.P).read(4, 4).tolist() == [0xFFFF] * 4


def test_a_block_whose_data_fails_its_crc_is_not_programmed_and_asked_again_in_full(
        host) -> None:
    """One data frame reaches board 1 with a flipped bit: the block's CRC does not match,
    the board programs nothing of it, reports it missing in full, and the next round
    brings it; the flash ends up holding exactly the image."""
    h = host("rosi")
    board = h.boards[0]
    state = {"done": False}

    def corrupt(node: object, arb: int, data: bytes) -> bool:
        if node is board and len(data) == 8 and arb == 0x2C5 and not state["done"]:
            state["done"] = True
            board.on_frame(arb, bytes([data[0] ^ 0x01]) + data[1:], h.sim.now)
            return True  # the board took the corrupted copy instead
        return False

    h.sim.drop = corrupt
    plan = plan_of(image_words(1000))
    from tests.helpers import program

    result = program(h, plan)
    assert state["done"] and result.all_verified and result.rounds == 2
    rx_blocks = plan.blocks[0]
    assert result.outcomes[seq(1)].resent_frames == rx_blocks.frames
    for b in plan.blocks:
        assert board.nv.space(b.space).read(b.address, len(b.words)).tolist() == list(b.words)
