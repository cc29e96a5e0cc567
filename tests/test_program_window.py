"""Programming goes on while it makes progress: a round that brings nothing is no verdict,
several in a row are, and the repair rounds end at a deadline derived from the work.

The real host code (``ops.flash`` and the ``Programmer``) runs over the in-process
virtual fleet in virtual time, behind a python-can wrapper that loses chosen frames (or a
seeded share of them): deterministic, and nothing sleeps."""

from __future__ import annotations

import random

import can
import pytest

from tests.helpers import image_words, plan_of
from tests.test_loss import IMAGE, flash_holds_image, lossy_robot, once
from ucom_tools.ops.flash import flash
from ucom_tools.ops.flash_types import FlashRequest
from ucom_tools.protocol import programmer
from ucom_tools.protocol.programmer import PROGRESS_WINDOW, Programmer
from ucom_tools.virtual.bus.loss import DropRule, LossyBus
from ucom_tools.wire.codes import StatusOp
from ucom_tools.wire.ids import ALL, Function, seq

PLAN = IMAGE.plan()
BLOCK, SLOT = 2, 5
FRAME = (0x2C0 | SLOT, bytes(PLAN.blocks[BLOCK].payload()[8 * SLOT:8 * SLOT + 8]))
"""One data frame of armar3.fl.S: slot 5 of block 2."""


def lost(times: int, frame: tuple[int, bytes] = FRAME) -> DropRule:
    """The first ``times`` times the host sends ``frame`` it is lost on its way."""
    count = {"n": 0}

    def rule(direction: str, msg: can.Message) -> bool:
        if direction == "tx" and (msg.arbitration_id, bytes(msg.data)) == frame \
                and count["n"] < times:
            count["n"] += 1
            return True
        return False
    return rule


def test_a_lost_resend_costs_a_round_not_the_transfer() -> None:
    """The frame is lost in round 1 and its resend in round 2 (a round without progress);
    round 3 brings it: every board verified, its flash holding the image."""
    with lossy_robot(drop=lost(2)) as (robot, fleet):
        result = flash(robot, FlashRequest(IMAGE))
        lossy = robot.buses["CAN0"].bus
        assert isinstance(lossy, LossyBus) and lossy.dropped["tx"] == 2
        assert [b.outcome for b in result.boards] == ["verified"] * 3, [
            b.detail for b in result.boards]
        (bus,) = result.buses
        assert bus.rounds == 3 and bus.resent_frames == 2
        assert all(flash_holds_image(fleet, "CAN0", n) for n in (1, 2, 3))


def test_the_old_one_round_rule_gave_that_transfer_up(monkeypatch: pytest.MonkeyPatch) -> None:
    """With a window of one round (the rule before) the same losses fail every board:
    'the last round brought no progress'."""
    monkeypatch.setattr(programmer, "PROGRESS_WINDOW", 1)
    with lossy_robot(drop=lost(2)) as (robot, _):
        result = flash(robot, FlashRequest(IMAGE))
        assert [b.outcome for b in result.boards] == ["failed"] * 3
        assert all("1 data frame(s) still missing after 2 round(s)" in b.detail
                   and "brought no progress" in b.detail for b in result.boards)


def test_resends_lost_for_fewer_rounds_than_the_window_still_verify() -> None:
    with lossy_robot(drop=lost(PROGRESS_WINDOW)) as (robot, _):
        result = flash(robot, FlashRequest(IMAGE))
        assert result.all_verified and result.buses[0].rounds == PROGRESS_WINDOW + 1


def test_a_window_of_rounds_without_progress_ends_the_transfer() -> None:
    """The frame never arrives: after the round that reported it missing, the window's
    rounds bring nothing and the transfer ends, naming what is missing and why."""
    with lossy_robot(drop=lost(10 ** 6)) as (robot, fleet):
        result = flash(robot, FlashRequest(IMAGE))
        (bus,) = result.buses
        assert bus.rounds == 1 + PROGRESS_WINDOW
        for b in result.boards:
            assert not b.verified
            assert b.detail.startswith(f"1 data frame(s) still missing after "
                                       f"{1 + PROGRESS_WINDOW} round(s); the last "
                                       f"{PROGRESS_WINDOW} rounds brought no progress")
            assert not fleet.boards["CAN0"][b.seq_id - 1].nv.record.flash_valid


def test_a_board_silent_for_a_whole_round_is_asked_again_in_the_next() -> None:
    """Every Program Finished of board 2 in round 1 is lost (three questions): it is not
    given up, round 2 asks it again and it reports VERIFIED."""
    count = {"n": 0}

    def first_three(direction: str, msg: can.Message) -> bool:
        if direction == "rx" and msg.arbitration_id == (Function.PROGRAM_FINISHED << 6 | 2) \
                and count["n"] < 3:
            count["n"] += 1
            return True
        return False

    with lossy_robot(drop=first_three) as (robot, _):
        result = flash(robot, FlashRequest(IMAGE))
        assert count["n"] == 3
        assert result.all_verified, [b.detail for b in result.boards]
        assert result.buses[0].rounds == 2


def test_a_lost_end_answer_alone_is_asked_again_within_the_round() -> None:
    with lossy_robot(drop=once(lambda d, msg: d == "rx" and msg.arbitration_id >> 6
                               == Function.PROGRAM_FINISHED)) as (robot, _):
        result = flash(robot, FlashRequest(IMAGE))
        assert result.all_verified and result.buses[0].rounds == 1


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_five_percent_loss_both_ways_verifies_and_rounds_go_past_a_barren_one(
        seed: int) -> None:
    """Seeded random loss each way, the served fleet's ``--loss 0.05`` in process."""
    with lossy_robot(loss=0.05, seed=seed) as (robot, fleet):
        result = flash(robot, FlashRequest(IMAGE))
        assert all(b.verified for b in result.boards), [b.detail for b in result.boards]
        assert all(flash_holds_image(fleet, "CAN0", n) for n in (1, 2, 3))


def test_repair_rounds_end_at_their_deadline_when_too_little_gets_through(host) -> None:
    """Boards that miss 99 % of the data frames on the wire: every round brings a few
    (progress), so neither the window nor the round bound ends it; the repair deadline
    does, derived from the work (the image once more at the bitrate, END's round trips)."""
    h = host("armar3", "CAN0")
    rng = random.Random(7)
    h.sim.drop = lambda node, arb, data: len(data) == 8 and arb >> 6 == Function.PROGRAM \
        and rng.random() < 0.99
    init = h.client.init_chain()
    h.client.set_status(ALL, StatusOp.PROG_ENABLE, 1, expect=[seq(n) for n in init.numbers])
    plan = plan_of(image_words(2000))
    p = Programmer(h.link, max_rounds=10 ** 6)
    allowed = p.repair_time(plan, len(init.numbers))
    t0 = h.link.clock()
    result = p.transfer(plan, [seq(n) for n in init.numbers])
    spent = h.link.clock() - t0
    assert not result.all_verified
    assert 3 < result.rounds < 1000
    for o in result.outcomes.values():
        assert "the repair rounds took the time they have" in o.status, o.status
    # the preamble and first round, the repair deadline, and the round under way at it
    assert allowed < spent < 2 * allowed
