"""Ctrl-C during programming: the transfer is aborted, no board keeps a startable
half-image, and the job says so per board (every phase: ``tests/test_flash_interrupt.py``)."""

from __future__ import annotations

import threading

import pytest

from ucom_tools.image.formats import load_image
from ucom_tools.ops.flash import flash
from ucom_tools.ops.flash_types import FlashInterrupted, FlashRequest
from ucom_tools.ops.robot import ConnectSpec, open_robot
from ucom_tools.wire.codes import BoardState
from ucom_tools.wire.ids import seq


def test_cancel_aborts_the_transfer_and_boards_stay_in_their_bootloader() -> None:
    robot = open_robot(ConnectSpec(virtual="armar3"))
    try:
        image = load_image("firmware_images/armar3.fl.S")
        cancel = threading.Event()

        def progress(bus: str, sent: int, total: int, boards: int) -> None:
            if sent > total // 3:
                cancel.set()

        with pytest.raises(FlashInterrupted) as caught:
            flash(robot, FlashRequest(image, bus="CAN0"), progress=progress, cancel=cancel)
        assert [(b.seq_id, b.outcome) for b in caught.value.result.boards] == [
            (1, "kept"), (2, "kept"), (3, "kept")]  # erased boards had no program to lose
        assert all("no program, as found" in b.detail for b in caught.value.result.boards)
        h = robot.buses["CAN0"]
        assert robot.buses["CAN0"].bus.sim.stats.by_function[11] < 12288 // 4
        for n in (1, 2, 3):
            info = h.client.info(seq(n))
            assert not info.flash_valid and info.state is BoardState.BOOTLOADER
            assert not info.prog_enable
        assert h.client.start(seq(1))[0].errors[0].code.name == "NO_PROGRAM"
        # and the bus is usable right away: a new flash succeeds
        assert flash(robot, FlashRequest(image, bus="CAN0")).all_verified
    finally:
        robot.close()
