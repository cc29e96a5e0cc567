"""Ctrl-C during programming: the transfer is aborted and no board keeps a startable
half-image."""

from __future__ import annotations

import threading

import pytest

from ucom_tools.image import load_image
from ucom_tools.ops.flash import flash
from ucom_tools.ops.robot import ConnectSpec, open_robot
from ucom_tools.protocol.programmer import Cancelled
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

        with pytest.raises(Cancelled):
            flash(robot, image, bus="CAN0", progress=progress, cancel=cancel)
        h = robot.buses["CAN0"]
        assert robot.buses["CAN0"].bus.sim.stats.by_function[11] < 12288 // 4
        for n in (1, 2, 3):
            info = h.client.info(seq(n))
            assert not info.flash_valid and info.state is BoardState.BOOTLOADER
        assert h.client.start(seq(1))[0].errors[0].code.name == "NO_PROGRAM"
        # and the bus is usable right away: a new flash succeeds
        assert flash(robot, image, bus="CAN0").all_verified
    finally:
        robot.close()
