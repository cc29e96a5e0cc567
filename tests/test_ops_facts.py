"""The operations say facts, the command line and the console word them (issue 37):
ops/options raises NotInitialised naming the bus only, cli/menu.init_advice words it."""

from __future__ import annotations

import ast
from collections.abc import Callable
from pathlib import Path

import pytest

from ucom_tools.cli.menu import OPTIONS, init_advice
from ucom_tools.ops import options as ops
from ucom_tools.ops.robot import ConnectSpec, Robot, open_robot
from ucom_tools.wire.codes import StatusOp

OPS = Path(__file__).resolve().parent.parent / "ucom_tools" / "ops"


@pytest.mark.parametrize("call", [
    lambda r: ops.info(r, ops.parse_ref("2")),
    lambda r: ops.reset(r, ops.parse_ref("2")),
    lambda r: ops.set_status(r, ops.parse_ref("all"), StatusOp.PROG_ENABLE, 1),
    lambda r: ops.set_seqid(r, ops.parse_ref("1"), 5),
    lambda r: ops.start(r, ops.parse_ref("all")),
])
def test_an_operation_before_init_raises_the_bus_and_no_advice(
        call: Callable[[Robot], object]) -> None:
    robot = open_robot(ConnectSpec(virtual="rosi"))
    try:
        with pytest.raises(ops.NotInitialised) as caught:
            call(robot)
    finally:
        robot.close()
    assert caught.value.bus == "CAN0"
    assert str(caught.value) == "CAN0: no board has a seq ID yet"


def test_the_advice_names_the_option_and_differs_on_the_command_line_and_console() -> None:
    for o in OPTIONS:
        if not o.needs_init:
            continue
        cli = init_advice("CAN1", o.number)
        console = init_advice("CAN1", o.number, console=True)
        head = (f"CAN1: no board has a seq ID yet. Option {o.number} ({o.title}) works only "
                "after a successful init chain (option 2): ")
        assert cli.startswith(head + "run 'ucom init' first") and "add --init" in cli
        assert console.startswith(head + "run option 2 (Init) first")
        assert "--init" not in console and "'ucom init'" not in console
        assert ("'ucom flash' runs it itself" in cli) == (o.number in (5, 6))


def test_no_string_in_ops_tells_the_user_to_run_a_ucom_command_first() -> None:
    for path in sorted(OPS.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                assert "run 'ucom" not in node.value, path.name
