"""Writes the loop does not wait for (``ops/remote/par_write.py``): a PAR, or a CI outside the CI
maps (an axis's Command), set with ``wait=False`` while the loop runs is written by a
conversation the loop steps after its cycles; the call itself sends nothing and returns.
In process and in virtual time: the board's own value (MCA Dump) says when it arrived."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.runtime_rig import programmed, robot_of
from ucom_tools.config.attrtree.robot import bind
from ucom_tools.config.scenario import FaultKind, InjectedFault
from ucom_tools.ops.remote import RemotePart
from ucom_tools.wire.ids import seq


@pytest.fixture
def part() -> Iterator[RemotePart]:
    fleet = programmed("armar3")
    robot = robot_of(fleet)
    assert robot.topology is not None
    p = RemotePart(robot, bind(robot.topology), on_fault="hold")
    p.fleet = fleet  # type: ignore[attr-defined]
    try:
        p.start()
        yield p
    finally:
        p.close()
        robot.close()


def set_raw(part: RemotePart, name: str, raw: int) -> None:
    ref = part.names.resolve(name)
    part.set(ref, ref.value(raw), wait=False)


def on_board(part: RemotePart, name: str) -> int:
    ref = part.names.resolve(name)
    x = part.exchanges[ref.bus]
    edges = x.configured[ref.board].edges
    return x.mca.dump(seq(ref.board), ref.kind, ref.index, 1,
                      edges.ci if ref.kind.name == "CI" else edges.par)[0]


@pytest.mark.parametrize(("name", "value"), [("RightEye P", 1234), ("Right Eye Command", 3)])
def test_a_write_not_waited_for_arrives_while_the_loop_runs(part: RemotePart, name: str,
                                                            value: int) -> None:
    ref = part.names.resolve(name)
    assert not part.cyclic(ref)  # a PAR, or a CI no map carries: acknowledged writes
    before = on_board(part, name)
    assert before != value
    sent = part.robot.buses[ref.bus].link.dispatcher.sent
    set_raw(part, name, value)
    assert part.robot.buses[ref.bus].link.dispatcher.sent == sent  # nothing sent yet
    assert part.raw(ref) == value  # the PC holds it at once
    for _ in range(20):
        part.cycle()
    assert on_board(part, name) == value
    assert not [w for w in part.writes if w.result != "done"]


def test_writes_of_one_edge_go_in_order_the_last_one_winning(part: RemotePart) -> None:
    for value in (1000, 2000, 3000):
        set_raw(part, "RightEye P", value)
    for _ in range(40):
        part.cycle()
    assert on_board(part, "RightEye P") == 3000
    assert part.raw("RightEye P") == 3000


def test_a_write_the_board_does_not_acknowledge_is_put_back_and_reported(
        part: RemotePart) -> None:
    before = part.raw("RightEye P")
    part.fleet.inject(InjectedFault(FaultKind("power-off"), "CAN0", 3,  # type: ignore[attr-defined]
                                    for_s=30.0))
    set_raw(part, "RightEye P", 4321)  # asked before the PC knows it is lost
    for _ in range(3000):
        part.cycle()
        if part.writes:
            break
    assert part.raw("RightEye P") == before
    [failed] = part.writes
    assert failed.name == "RightEye P" and failed.result.startswith("failed")
