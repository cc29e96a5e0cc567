"""A flash as a request: the operation says facts (an outcome, the bus without seq IDs),
the command line words them (its advice is not in ``ops``)."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from ucom_tools.cli.main import cli
from ucom_tools.image.formats import load_image
from ucom_tools.ops.flash import flash
from ucom_tools.ops.flash_types import FlashRequest
from ucom_tools.ops.options import NotInitialised
from ucom_tools.ops.robot import ConnectSpec, open_robot

LAURON4 = "firmware_images/lauron4.fl.S"


def test_a_board_the_image_does_not_fit_is_refused_without_cli_advice() -> None:
    robot = open_robot(ConnectSpec(virtual="rosi"))
    try:
        result = flash(robot, FlashRequest(load_image(LAURON4)))
    finally:
        robot.close()
    (board,) = result.boards
    assert board.outcome == "refused" and board.detail.startswith("refused: App-ID")
    assert "--force" not in board.detail


def test_the_command_line_adds_its_own_advice_to_a_refused_board() -> None:
    r = CliRunner().invoke(cli, ["program", "1", LAURON4, "--virtual", "rosi", "--init",
                                 "--json"])
    assert r.exit_code == 1, r.output
    assert "; --force programs it anyway" in r.output


def test_without_seq_ids_the_flash_names_the_bus_and_the_cli_says_what_to_do() -> None:
    robot = open_robot(ConnectSpec(virtual="rosi"))
    try:
        with pytest.raises(NotInitialised) as caught:
            flash(robot, FlashRequest(load_image("firmware_images/rosi.fl.S"), init=False))
    finally:
        robot.close()
    assert caught.value.bus == "CAN0"
    assert str(caught.value) == "CAN0: no board has a seq ID yet"
    r = CliRunner().invoke(cli, ["extram-load", "1", "firmware_images/rosi.fl.S",
                                 "--virtual", "rosi"])
    assert r.exit_code != 0
    assert ("CAN0: no board has a seq ID yet. Option 6 (ExtRAMLoad) works only after a "
            "successful init chain (option 2)") in " ".join(r.output.split())
