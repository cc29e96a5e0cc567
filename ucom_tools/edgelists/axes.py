"""How the DSP programs ucom-tools knows name the edges of one axis (``MotorA Target``,
``Axis1 Position Setpoint``, ...): each edge's role to its axis (:class:`Role`) and each
program's :class:`AxisModel`.  Pure data about the programs, used wherever a robot's
joints are found from its trees (the CANopen gateway, ``ucom_tools.gateway.joints``; the
recordings' and viewers' joint states, ``ucom_tools.trace.mcap_record``)."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

AXIS_LETTERS = "ABCDEFGHIJKLMNOPQRSTUVWXYZ"
"""Axis k's letter (A = 0), as the programs' edge names and the topology's canopen_node
spell it."""


class Role(StrEnum):
    """What an edge is to its axis (the gateway's name for it)."""

    COMMAND = "Command"
    TARGET = "Target"
    TARGET_VEL = "TargetVel"
    RESET_OFFSET = "Reset Offset"
    RESET_PWM = "Reset PWM"
    MAX_VELOCITY = "Max Velocity"
    MIN_POSITION = "Min Position"
    MAX_POSITION = "Max Position"
    JOINT_SENSOR = "Joint Sensor"
    VELOCITY = "Velocity"
    RESET_ANSWER = "Reset Answer"
    SETTLED = "Settled"


@dataclass(frozen=True)
class AxisModel:
    """How one program names the edges of its axis k: each role's generic name, a pattern
    with ``{a}`` the axis letter (A, B, C), ``{n}`` its number from 1 and ``{j}`` its
    joint counter (2k); and what its Command values mean."""

    program: str
    """The program's name (:attr:`ProgramSpec.name`)."""
    axes: int
    patterns: tuple[tuple[Role, str], ...]
    name_suffix: str
    """What the Target's unique name has after the joint's name (" Target")."""
    velocity_scale: int
    """Counts/s (or 0.01 deg/s) per raw unit of the Max Velocity edge."""
    command_off: int
    command_position: int
    command_velocity: int
    command_homing: int | None
    """None: no homing per axis."""

    def generic(self, role: Role, axis: int) -> str | None:
        """The generic name of axis ``axis``'s (0-based) edge in ``role``; None if the
        program has none."""
        for r, pattern in self.patterns:
            if r is role:
                return pattern.format(a=AXIS_LETTERS[axis], n=axis + 1, j=2 * axis)
        return None


ARMAR3 = AxisModel(
    "armar3 cascaded PID", 3,
    ((Role.COMMAND, "Motor{a} Command"), (Role.TARGET, "Motor{a} Target"),
     (Role.TARGET_VEL, "Motor{a} TargetVel"), (Role.RESET_OFFSET, "Motor{a} Reset Offset"),
     (Role.RESET_PWM, "Reset {a} PWM"), (Role.MAX_VELOCITY, "Motor{a} Max Velocity (x1000)"),
     (Role.MIN_POSITION, "Motor{a} Min Position"), (Role.MAX_POSITION, "Motor{a} Max Position"),
     (Role.JOINT_SENSOR, "Encoder {j}"), (Role.VELOCITY, "Velocity {a}"),
     (Role.RESET_ANSWER, "Motor{a} Reset Answer"), (Role.SETTLED, "Motor {a} Settled")),
    " Target", 1000, command_off=3, command_position=0, command_velocity=1, command_homing=2)
"""``armar3.fl.S`` (:mod:`ucom_tools.edgelists.armar3`, its ``Command``)."""

LAURON4 = AxisModel(
    "lauron4 leg", 3,
    ((Role.COMMAND, "Leg Mode"), (Role.TARGET, "Axis{n} Position Setpoint"),
     (Role.TARGET_VEL, "Axis{n} Velocity Setpoint"),
     (Role.RESET_OFFSET, "Axis{n} Reference Offset"),
     (Role.MAX_VELOCITY, "Axis{n} Velocity Limit"), (Role.MIN_POSITION, "Axis{n} Lower Limit"),
     (Role.MAX_POSITION, "Axis{n} Upper Limit"), (Role.JOINT_SENSOR, "Axis{n} Position"),
     (Role.VELOCITY, "Axis{n} Velocity")),
    " Position Setpoint", 1, command_off=0, command_position=1, command_velocity=2,
    command_homing=None)
"""``lauron4.fl.S`` (:mod:`ucom_tools.edgelists.lauron4`, its ``LegMode``)."""

MODELS = {m.program: m for m in (ARMAR3, LAURON4)}
"""The programs whose axes can be joints, by program name."""


__all__ = ["ARMAR3", "AXIS_LETTERS", "LAURON4", "MODELS", "AxisModel", "Role"]
