"""The bundled robots' trees and their binding through the topologies (tree, tree_block)."""

from __future__ import annotations

from pathlib import Path

import pytest

from ucom_tools.config import attrtree, topology
from ucom_tools.config.attrtree import TreeEdgeKind, bind, check, load
from ucom_tools.errors import TreeError

ROOT = Path(__file__).resolve().parent.parent
EYES = ROOT / "attribute_trees" / "armar3" / "head_right.tree"
MOTOR_C = (2, 5, 8, 12, 17, 18, 21, 26, 29, 32, 44, 45, 46, 49, 52, 61, 62, 63, 64, 69, 70)
"""Indices of the eyes example's edges that belong to its unused motor C (or its encoders)."""


def test_every_armar3_board_is_bound_explicitly() -> None:
    topo = topology.load("armar3")
    specs = [b for bus in topo.buses for b in bus.boards]
    assert len(specs) == 11
    assert all(s.tree is not None and s.tree_block is None for s in specs)
    by_placement = {s.placement: s.tree for s in specs}
    assert by_placement["head right"] == EYES
    assert len(set(by_placement.values())) == 11


def test_armar3_trees_share_the_generic_program_of_b5() -> None:
    robot = bind(topology.load("armar3"))
    eyes = load(EYES).boards[0]
    program = [(e.index, e.kind, e.generic) for e in eyes.edges]
    assert len(robot.boards) == 11
    for b in robot.boards:
        assert [(e.index, e.kind, e.generic) for e in b.board.edges] == program, b.where


def test_armar3_unique_names_come_from_the_joints() -> None:
    robot = bind(topology.load("armar3"))
    for b in robot.boards:
        if b.spec.placement == "head right":
            continue  # the example's own names ("Right Eye", "RightEye")
        board = b.board
        joints = [j.title() if not j.startswith("wheel") else j.capitalize()
                  for j in b.spec.joints]
        for letter, joint in zip("ABC", joints, strict=False):
            assert board.generic(f"Motor{letter} Target").unique == f"{joint} Target"
            assert board.generic(f"Motor{letter} P").unique == f"{joint} P"
            assert board.generic(f"Reset {letter} PWM").unique == f"Reset {joint} PWM"
        if len(joints) == 3:
            assert not any(e.unique.startswith("MotorC") for e in board.edges)


def test_unused_motor_c_is_configured_like_the_example() -> None:
    eyes = load(EYES).boards[0]
    robot = bind(topology.load("armar3"))
    two_axis = [b for b in robot.boards if len(b.spec.joints) == 2]
    assert len(two_axis) == 6
    for b in two_axis:
        for i in MOTOR_C:
            assert b.board.edges[i] == eyes.edges[i], (b.where, i)
    assert eyes.edge("MotorC Velocity P").default == attrtree.Value.parse("0")


def test_armar3_defaults_are_complete_for_used_axes() -> None:
    robot = bind(topology.load("armar3"))
    for b in robot.boards:
        n = len(b.spec.joints)
        board = b.board
        assert board.edge("LoopTime(ms)").default == attrtree.Value.parse("1")
        mask = board.edge("Set Joint Moving Direction(BitMask)").default
        assert mask is not None and mask.number == (1 << n) - 1
        for letter in "ABC"[:n]:
            for g in (f"Motor{letter} Max Position", f"Motor{letter} Velocity P",
                      f"Motor{letter} Command", f"Motor{letter} Target"):
                assert board.generic(g).default is not None, (b.where, g)
            hi = board.generic(f"Motor{letter} Max Position").default
            lo = board.generic(f"Motor{letter} Min Position").default
            assert hi is not None and lo is not None and lo.number == -hi.number


def test_robot_wide_identity_is_prefix_and_unique_name() -> None:
    robot = bind(topology.load("armar3"))
    assert robot.board("CAN0", 2).prefix == "Eyes"
    assert robot.edge("Eyes", "Right Eye Target").index == 3
    assert robot.edge("Neck", "Max PWM").index == robot.edge("Torso", "Max PWM").index == 34
    with pytest.raises(KeyError):
        robot.edge("Eyes", "Neck Pitch Target")
    with pytest.raises(KeyError):
        robot.board("CAN0", 3)


def test_lauron4_has_its_own_leg_program() -> None:
    robot = bind(topology.load("lauron4"))
    assert len(robot.boards) == 7
    programs = {tuple((e.index, e.kind, e.generic) for e in b.board.edges)
                for b in robot.boards}
    assert len(programs) == 1
    (program,) = programs
    armar3 = {e.generic for e in load(EYES).boards[0].edges}
    assert not armar3 & {g for _, _, g in program}
    assert [sum(k is kind for _, k, _ in program) for kind in TreeEdgeKind] == [11, 15, 30]


def test_lauron4_legs_name_alpha_beta_gamma_and_the_head_pan_tilt() -> None:
    robot = bind(topology.load("lauron4"))
    for b in robot.boards:
        board = b.board
        if b.spec.placement == "camera head":
            assert board.generic("Axis1 Position Setpoint").unique == "Pan Position Setpoint"
            assert board.generic("Axis3 Position").unique == "Axis3 Position"
            assert board.generic("Axis3 Velocity Kp").default == attrtree.Value.parse("0")
        else:
            for axis, joint in zip((1, 2, 3), ("Alpha", "Beta", "Gamma"), strict=True):
                assert board.generic(f"Axis{axis} Position").unique == f"{joint} Position"
            assert board.edge("Ground Contact Threshold(N)").default is not None
    assert [b.board.prefix for b in robot.boards] == [
        "FrontLeftLeg", "MiddleLeftLeg", "RearLeftLeg", "FrontRightLeg", "MiddleRightLeg",
        "RearRightLeg", "CameraHead"]


def test_check_collects_every_problem_and_bind_raises_the_first(tmp_path: Path) -> None:
    text = 'name = "t"\n[[bus]]\nname = "CAN0"\n'
    text += '[[bus.board]]\nplacement = "a"\nboard = "3M"\n'
    text += '[[bus.board]]\nplacement = "b"\nboard = "3M"\n'
    text += f'[[bus.board]]\nplacement = "c"\nboard = "3M"\ntree = "{EYES}"\n'
    path = tmp_path / "t.toml"
    path.write_text(text)
    topo = topology.load(str(path))
    result = check(topo)
    assert not result.ok
    assert [p.line for p in result.problems] == [4, 7]
    assert [b.board.prefix for b in result.boards] == ["Eyes"]
    with pytest.raises(TreeError, match="CAN0 board 1 \\(a\\) has no attribute tree"):
        bind(topo)
