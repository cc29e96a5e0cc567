"""A consumer's raw writes (the CANopen gateway's, ``ops/remote_feed.py`` ``DriveWrites``)
reach the loop in order, but at most one a cycle that waits for the board's
acknowledgement: a Command (a CI outside the CI maps) is an acknowledged MCA write, a
round trip of 2-7 ms over socketcand, and the gateway's start switches all 27 of
ARMAR-III's joints off at once (27 such writes: the loop kept from its cycles past the
boards' 50 ms watchdog, which stopped every motor).  In process, in virtual time."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.runtime_rig import programmed, robot_of
from ucom_tools.config.attrtree.robot import bind
from ucom_tools.ops.remote import RemotePart
from ucom_tools.ops.remote_feed import LocalRun

OFF = 3  # ucom_tools.edgelists.armar3.Command.OFF (the board starts in position control, 0)
COMMANDS = ("Right Eye Command", "Left Eye Command", "Neck Yaw Command")
TARGETS = ("Right Eye Target", "Left Eye Target", "Neck Yaw Target")


@pytest.fixture
def part() -> Iterator[RemotePart]:
    fleet = programmed("armar3")
    robot = robot_of(fleet)
    assert robot.topology is not None
    p = RemotePart(robot, bind(robot.topology), on_fault="hold")
    try:
        p.start()
        p.cycle()
        yield p
    finally:
        p.close()
        robot.close()


def sent(part: RemotePart, name: str) -> int | None:
    """The raw value the loop holds for a CI now (what it wrote or maps)."""
    return part.raw(part.names.resolve(name))


def test_the_edges_of_the_test_are_what_it_assumes(part: RemotePart) -> None:
    for name in COMMANDS:
        assert not part.cyclic(name) and sent(part, name) == 0
    for name in TARGETS:
        assert part.cyclic(name)


def test_acknowledged_writes_go_one_a_cycle_in_order(part: RemotePart) -> None:
    run = LocalRun(part, 100.0)
    items = [item for k in range(3) for item in ((COMMANDS[k], OFF), (TARGETS[k], 100 + k))]
    run.drive(items)
    seen = []
    for _ in range(4):
        part.cycle()
        seen.append(([sent(part, c) for c in COMMANDS], [sent(part, t) for t in TARGETS]))
    # cycle 1: the first Command (it waits for its answer), nothing after it; cycle 2: the
    # first Target (mapped: no wait) and the second Command; ...
    assert seen == [
        ([OFF, 0, 0], [0, 0, 0]),
        ([OFF, OFF, 0], [100, 0, 0]),
        ([OFF, OFF, OFF], [100, 101, 0]),
        ([OFF, OFF, OFF], [100, 101, 102]),
    ]
    assert run.drives.applied == 6 and run.drives.refused == 0 and not run.drives.queued


def test_mapped_writes_alone_all_go_in_one_cycle(part: RemotePart) -> None:
    run = LocalRun(part, 100.0)
    run.drive([(t, 200 + k) for k, t in enumerate(TARGETS)])
    part.cycle()
    assert [sent(part, t) for t in TARGETS] == [200, 201, 202]
    assert run.drives.applied == 3


def test_a_refused_write_is_counted_and_the_next_goes_on(part: RemotePart) -> None:
    run = LocalRun(part, 100.0)
    run.drive([("No Such Edge", 1), (TARGETS[0], 7)])
    part.cycle()  # the unknown name may have cost the cycle's acknowledged write
    part.cycle()
    assert run.drives.refused == 1 and "No Such Edge" in run.drives.reason
    assert sent(part, TARGETS[0]) == 7
