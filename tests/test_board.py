"""The virtual UCoM's bootloader, exercised through real frames by the real host clients."""

from __future__ import annotations

import can
import pytest

from tests.conftest import chain_topology
from tests.helpers import enable_all, image_words, plan_of, program
from ucom_tools.protocol.programmer import Programmer
from ucom_tools.virtual.fleet import Fleet
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import (
    BoardState,
    ErrorCode,
    ReadyReason,
    Space,
    StatusOp,
    Target,
)
from ucom_tools.wire.ids import ALL, Function, encode_id, fixed, seq
from ucom_tools.wire.transfer import TransferPlan

from .helpers import WHEN


def errors_after(h, arbitration_id: int, data: bytes) -> list[m.Error]:
    h.link.send_raw(arbitration_id, data)
    return [g.message for g in h.link.drain(0.05) if isinstance(g.message, m.Error)]


def test_reset_before_init_is_silent_after_init_every_board_answers(host) -> None:
    h = host("armar3", "CAN0")
    assert h.client.reset() == []
    h.client.init_chain()
    replies = h.client.reset()
    assert sorted(r.address.number for r in replies) == [1, 2, 3]
    assert all(r.message.reason is ReadyReason.BOOT for r in replies)
    assert {r.message.value32 for r in replies} == {b.identity.serial for b in h.boards}
    assert [b.seq_id for b in h.boards] == [1, 2, 3]  # a warm reset keeps the seq ID


def test_info_of_an_empty_board(host) -> None:
    h = host("armar3", "CAN2")
    h.client.init_chain()
    info = h.client.info(seq(2))
    assert (info.state, info.seq_id, info.flash_valid, info.programmed) == (
        BoardState.BOOTLOADER, 2, False, None)
    assert info.serial == h.boards[1].identity.serial
    assert info.bootloader_version == (1, 0)


def test_flash_program_verify_info_and_start(host) -> None:
    h = host("armar3", "CAN0")
    plan = plan_of(image_words(3000, 100), name="armar3.fl.S")
    result = program(h, plan)
    assert result.all_verified and result.rounds == 1
    assert {o.progid for o in result.outcomes.values()} == {plan.progid}
    info = h.client.info(seq(1))
    assert (info.flash_valid, info.progid, info.name, info.size_words, info.programmed) == (
        True, plan.progid, "armar3.fl.S", plan.size_words, WHEN)
    assert h.boards[0].nv.p.read(0x0004, 3).tolist() == list(plan.blocks[0].words[:3])
    assert h.boards[0].nv.p.read(0, 4).tolist() == [0xE984, 0x8000, 0xE984, 0x8000]
    (started,) = h.client.start(seq(1))
    assert started.ok and started.state is BoardState.RUNNING_FLASH
    assert any("running (ProgID" in t for t in started.reports)
    assert any("without an image descriptor" in t for t in started.reports)
    assert h.boards[0].leds()["green"] == "blink"


def test_start_without_a_program_is_refused(host) -> None:
    h = host("armar3", "CAN0")
    h.client.init_chain()
    (result,) = h.client.start(seq(2))
    assert not result.started
    assert [e.code for e in result.errors] == [ErrorCode.NO_PROGRAM]
    assert h.boards[1].state is BoardState.BOOTLOADER


def test_autostart_survives_power_cycle_and_xreset_clears_it(host, tmp_path) -> None:
    fleet = Fleet.load("rosi", state_dir=tmp_path)
    h = host(fleet, "CAN0")
    plan = plan_of(image_words(600))
    assert program(h, plan).all_verified
    assert h.client.set_status(seq(1), StatusOp.AUTOSTART, 1)[0].ok
    replies = h.client.reset()
    assert replies[0].message.state is BoardState.RUNNING_FLASH
    # a fresh process on the same state directory = the robot powered up again
    h2 = host(Fleet.load("rosi", state_dir=tmp_path), "CAN0")
    assert h2.boards[0].state is BoardState.RUNNING_FLASH
    h2.client.init_chain()  # init works while the program runs
    replies = h2.client.reset(clear_autostart=True)
    assert replies[0].message.state is BoardState.BOOTLOADER
    assert not h2.client.info(seq(1)).autostart
    assert Fleet.load("rosi", state_dir=tmp_path).boards["CAN0"][0].state is \
        BoardState.BOOTLOADER


def test_autostart_needs_a_valid_program(host) -> None:
    h = host("rosi")
    h.client.init_chain()
    replies = h.client.set_status(seq(1), StatusOp.AUTOSTART, 1)
    assert replies[0].message.code is ErrorCode.NO_PROGRAM


def test_extram_program_is_volatile(host) -> None:
    h = host("rosi")
    plan = plan_of(image_words(500), target=Target.EXTRAM)
    assert program(h, plan).all_verified
    info = h.client.info(seq(1))
    assert info.extram_valid and info.target is Target.EXTRAM and not info.flash_valid
    assert h.boards[0].nv.p.read(4, 1).tolist() == [0xFFFF]  # flash untouched
    assert h.client.start(seq(1), Target.EXTRAM)[0].state is BoardState.RUNNING_EXTRAM
    h.client.reset()
    assert not h.client.info(seq(1)).extram_valid
    assert h.client.start(seq(1), Target.EXTRAM)[0].errors[0].code is ErrorCode.NO_PROGRAM


def test_malformed_and_unknown_frames_get_errors_and_never_stop_a_board(host) -> None:
    h = host("armar3", "CAN0")
    h.client.init_chain()
    errs = errors_after(h, encode_id(Function.SET_STATUS, seq(1)), b"\x01\x01\x01")
    assert [(e.code, e.function) for e in errs] == [(ErrorCode.BAD_LENGTH, 7)]
    errs = errors_after(h, encode_id(Function.SET_STATUS, seq(1)), b"\x0f\x01")
    assert [e.code for e in errs] == [ErrorCode.BAD_VALUE]
    errs = errors_after(h, encode_id(30, seq(2)), b"\x00")
    assert [(e.code, e.function) for e in errs] == [(ErrorCode.UNKNOWN_FUNCTION, 30)]
    assert errors_after(h, encode_id(30, ALL), b"\x00") == []  # broadcast: ignored
    errs = errors_after(h, encode_id(Function.MCA_CONTROLLER_INPUT, seq(3)), bytes(8))
    assert [e.code for e in errs] == [ErrorCode.NOT_RUNNING]
    assert errors_after(h, encode_id(Function.INFO, seq(1)), bytes(8)) == []  # board traffic
    # an extended frame is carried, and the boards ignore it: no answer, no Error
    h.can.send(can.Message(arbitration_id=0x1234567, data=b"\x01", is_extended_id=True))
    assert list(h.link.drain(0.05)) == []
    with pytest.raises(can.CanOperationError, match="remote"):
        h.can.send(can.Message(arbitration_id=0x123, is_remote_frame=True, dlc=1))
    assert h.client.info(seq(1)).seq_id == 1  # still working


def test_program_frames_need_prog_enable(host) -> None:
    h = host("armar3", "CAN0")
    h.client.init_chain()
    errs = errors_after(h, *m.encode(m.ProgramBegin(Target.FLASH, 1, 4), seq(2)))
    assert [e.code for e in errs] == [ErrorCode.NOT_ENABLED]
    assert errors_after(h, *m.encode(m.ProgramBegin(Target.FLASH, 1, 4), ALL)) == []


def test_protected_and_unmapped_addresses_are_refused(host) -> None:
    h = host("rosi")
    h.client.init_chain()
    enable_all(h)
    for frame in (m.ProgramBegin(Target.FLASH, 1, 4), m.ProgramErase(Space.P, 0x80, 1),
                  m.ProgramErase(Space.X, 0x1F, 1), m.ProgramErase(Space.P, 0x7E, 1)):
        h.link.send(frame, ALL)
    errs = [g.message for g in h.link.drain(0.05) if isinstance(g.message, m.Error)]
    assert [(e.code, e.detail) for e in errs] == [
        (ErrorCode.PROTECTED_ADDRESS, 0x8000), (ErrorCode.PROTECTED_ADDRESS, 0x1_1F00),
        (ErrorCode.UNMAPPED_ADDRESS, 0x7E00)]


def test_a_block_outside_the_erased_pages_is_refused(host) -> None:
    h = host("rosi")
    h.client.init_chain()
    enable_all(h)
    plan = plan_of(image_words(8))
    for frame in (plan.begin(), *plan.meta(), m.ProgramPrepare(0)):
        h.link.send(frame, ALL)
    assert any(isinstance(g.message, m.Ready) for g in h.link.drain(0.05))
    h.link.send(m.ProgramBlock(Space.P, 0x8000, 1, 0), ALL)
    h.link.send(m.ProgramBlock(Space.P, 0x0100, 1, 0), ALL)
    errs = [g.message for g in h.link.drain(0.05) if isinstance(g.message, m.Error)]
    assert [e.code for e in errs] == [ErrorCode.PROTECTED_ADDRESS, ErrorCode.SEQUENCE]


def test_erase_takes_page_erase_time(host) -> None:
    h = host("rosi")
    h.client.init_chain()
    enable_all(h)
    plan = plan_of(image_words(256 * 10 - 4))  # P:0004-09FF = pages 0..9
    for frame in (plan.begin(), *plan.meta(), *plan.erases(), plan.prepare()):
        h.link.send(frame, ALL)
    t0 = h.sim.now
    got = h.link.recv(1.0)
    assert isinstance(got.message, m.Ready) and got.message.reason is ReadyReason.ERASED
    elapsed_us = (got.timestamp - h.fleet.epoch) * 1e6 - t0
    assert 10 * 20_000 <= elapsed_us < 10 * 20_000 + 1_000


def test_flow_control_pauses_the_stream_for_slow_flash(host) -> None:
    fleet = chain_topology(2, timing="[timing]\nword_program_us = 80.0")
    h = host(fleet)
    plan = plan_of(image_words(4000))
    result = program(h, plan)
    assert result.all_verified and result.rounds == 1
    ready = h.sim.stats.by_function[Function.READY]
    assert ready > 2 * 2 + 2  # ERASED and STATUS acks plus PAUSE/RESUME pairs
    assert all(b.overruns == 0 for b in h.boards)


def test_the_host_keeps_a_slow_boards_ring_from_filling(host) -> None:
    """Boards that need 1.6 ms a data frame: by their ring size and time per frame (Ready
    ERASED) the host holds its frames back before a ring fills, where PAUSE alone came too
    late for a host ahead of the bus: one round, no frame lost to an overrun."""
    fleet = chain_topology(3, timing="[timing]\nword_program_us = 400.0")
    h = host(fleet)
    result = program(h, plan_of(image_words(4000)))
    assert result.all_verified and (result.rounds, result.resent_frames) == (1, 0)
    assert [b.overruns for b in h.boards] == [0, 0, 0]


def test_only_missed_frames_are_sent_again(host) -> None:
    h = host("armar3", "CAN1")
    victim = h.boards[1]
    state = {"in_block": False, "drop": 2}

    def drop(node, arb, data) -> bool:  # board 2 misses the data of block 5, once
        if arb >> 6 != Function.PROGRAM or node is not victim:
            return False
        if len(data) < 8:
            state["in_block"] = data[0] == 0x05 and data[4] == 5
            return False
        if state["in_block"] and state["drop"]:
            state["drop"] -= 1
            return True
        return False

    h.sim.drop = drop
    plan = plan_of(image_words(3000))
    result = program(h, plan)
    assert result.all_verified and result.rounds == 2
    assert result.resent_frames == 2  # the two lost frames, not their 64-frame block
    assert result.data_frames == sum(b.frames for b in plan.blocks) + 2
    assert result.outcomes[seq(2)].resent_frames == 2
    assert result.outcomes[seq(1)].resent_frames == 0


def test_power_loss_mid_transfer_leaves_the_board_in_its_bootloader(host) -> None:
    h = host("rosi")
    assert program(h, plan_of(image_words(1000), name="old.S")).all_verified
    h.client.set_status(seq(1), StatusOp.AUTOSTART, 1)
    h.client.set_status(seq(1), StatusOp.AUTOSTART, 0)
    board = h.boards[0]
    blocks_seen = {"n": 0}

    def cut_power(node, arb, data) -> bool:
        if node is board and arb >> 6 == Function.PROGRAM and len(data) == 7:
            blocks_seen["n"] += 1
            if blocks_seen["n"] == 3:
                board.power_off()
        return False

    h.sim.drop = cut_power
    h.client.set_status(seq(1), StatusOp.AUTOSTART, 1)
    result = program(h, plan_of(image_words(3000, seed=7), name="new.S"))
    assert not result.all_verified
    h.sim.drop = None
    board.power_on(h.sim.now)
    assert board.state is BoardState.BOOTLOADER  # AutoStart must not start half an image
    h.client.init_chain()
    info = h.client.info(seq(1))
    assert not info.flash_valid and not info.autostart
    assert h.client.start(seq(1))[0].errors[0].code is ErrorCode.NO_PROGRAM


def test_fixed_id_boards_answer_on_their_fixed_identifier(host) -> None:
    h = host(chain_topology(2, extra={1: "fixed_id = 12"}))
    replies = h.client.set_status(fixed(12), StatusOp.PROG_ENABLE, 1)
    assert replies[0].address == fixed(12)
    h.client.init_chain()
    assert h.client.info(fixed(12)).seq_id == 2


@pytest.mark.parametrize("boards, target", [(1, 0.90), (31, 0.85)])
def test_transfer_efficiency_meets_the_protocol_targets(host, boards: int, target: float
                                                        ) -> None:
    """64 KiB image: payload bits per wire bit, every frame counted from ProgEnable on."""
    h = host(chain_topology(boards))
    init = h.client.init_chain()
    s0 = (h.sim.stats.bits, h.sim.stats.payload_bits)
    enable_all(h)
    words = image_words(32768 - 3840, 3840)
    plan = TransferPlan.build(words, entry=4, name="64k", when=WHEN)
    assert plan.size_words * 2 >= 64 * 1024
    result = Programmer(h.link).transfer(plan, [seq(n) for n in init.numbers])
    assert result.all_verified
    wire = h.sim.stats.bits - s0[0]
    useful = plan.size_words * 16  # the image's payload, not the protocol's own bytes
    assert useful / wire >= target * 64 / 111
