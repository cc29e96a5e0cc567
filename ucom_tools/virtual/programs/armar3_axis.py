"""The per-axis controller of ``armar3.fl.S`` (:mod:`ucom_tools.virtual.programs.armar3`,
whose docstring defines it): its constants, the edge indices it reads and writes, one
axis's configuration from PAR (:class:`AxisConfig`) and its state and cycle (:class:`Axis`:
sensing, the position/velocity cascade, homing, Settled).  The program around it (all
three axes, CI/SO/PAR, the load, the quiet-cycle shortcut) is
:class:`~ucom_tools.virtual.programs.armar3.Armar3Model`."""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Final

from ucom_tools.edgelists.armar3 import AXES, SPEC, Command
from ucom_tools.edgelists.model import EdgeKind
from ucom_tools.virtual.hardware.fpga import QuadratureDecoder
from ucom_tools.virtual.hardware.numeric import clamp, round_half_even, signed16
from ucom_tools.virtual.programs.base import Hardware
from ucom_tools.wire.fpga import Reg

BASE_US: Final = 100.0
"""Execution time of a cycle with every controller off [us]."""
AXIS_US: Final = 200.0
"""Additional execution time per active axis [us]."""
VELOCITY_FILTER_US: Final = 2000.0
"""Time constant of the velocity low-pass [us]."""
STANDSTILL_US: Final = 200_000.0
"""No count change for this long: velocity 0 [us]."""
SETTLED_COUNTS: Final = 5
"""Position tolerance of Settled [counts]."""
SETTLED_SPEED: Final = 50.0
"""Velocity threshold of Settled [counts/s]."""
SETTLED_US: Final = 20_000.0
"""How long both must hold before Settled is 1 [us]."""
LIMIT_APPROACH_PER_S: Final = 20.0
"""In VELOCITY mode the speed towards a position limit is at most this gain [1/s] times the
distance left: braking starts 50 counts before the limit at 1000 counts/s."""
STALL_COUNTS: Final = 2
"""Homing: the end stop is reached when the joint counter moves by at most this ..."""
STALL_US: Final = 20_000.0
"""... for this long [us] while driving ..."""
STALL_CURRENT_MV: Final = 100.0
"""... and the current sense reads at least this [mV] (0.2 A at 0.5 V/A)."""
HOMING_TIMEOUT_US = 20_000_000.0
"""Homing fails (Reset Answer -1) without a stall within this time [us]."""

NEVER_HOMED: Final = 0
HOMING: Final = 1
HOMED: Final = 2
HOMING_FAILED: Final = -1
"""Values of ``MotorX Reset Answer``."""


def _indices(kind: EdgeKind) -> dict[str, int]:
    return {e.name: i for i, e in enumerate(SPEC.of(kind))}


CI_INDEX: Final = _indices(EdgeKind.CI)
SO_INDEX: Final = _indices(EdgeKind.SO)
PAR_INDEX: Final = _indices(EdgeKind.PAR)
"""Each edge's index in its kind's values, by name."""


def _per_axis(table: dict[str, int], pattern: str) -> tuple[int, ...]:
    """Index of the edge ``pattern`` names for each axis k ({a}: A, B, C; {j} and {m}: its
    joint and motor counter, 2k and 2k+1)."""
    return tuple(table[pattern.format(a=a, j=2 * k, m=2 * k + 1)] for k, a in enumerate(AXES))


_COMMAND: Final = _per_axis(CI_INDEX, "Motor{a} Command")
_TARGET: Final = _per_axis(CI_INDEX, "Motor{a} Target")
_TARGET_VEL: Final = _per_axis(CI_INDEX, "Motor{a} TargetVel")
_RESET_OFFSET: Final = _per_axis(CI_INDEX, "Motor{a} Reset Offset")
_JOINT_ENCODER: Final = _per_axis(SO_INDEX, "Encoder {j}")
_MOTOR_ENCODER: Final = _per_axis(SO_INDEX, "Encoder {m}")
_VOLTAGE: Final = _per_axis(SO_INDEX, "Voltage {a}")
_RESET_ANSWER: Final = _per_axis(SO_INDEX, "Motor{a} Reset Answer")
_VELOCITY: Final = _per_axis(SO_INDEX, "Velocity {a}")
_SETTLED: Final = _per_axis(SO_INDEX, "Motor {a} Settled")

_CMD_OFF: Final = int(Command.OFF)
_CMD_POSITION: Final = int(Command.POSITION)
_CMD_VELOCITY: Final = int(Command.VELOCITY)
_CMD_HOMING: Final = int(Command.HOMING)
# the commands as plain ints (an IntEnum member costs a lookup on every use)
_CONTROLLED: Final = (_CMD_POSITION, _CMD_VELOCITY, _CMD_HOMING)
"""The Commands that run a controller (any other value is OFF)."""
_QUAD_COUNT0: Final = int(Reg.QUAD_COUNT0)


@dataclass(frozen=True, slots=True)
class AxisConfig:
    """One axis's parameters in controller units, derived from PAR (anew whenever a PAR
    value changes)."""

    p: float
    i: float
    d: float
    feedforward: float
    vp: float
    vi: float
    vd: float
    v_max: float
    """counts/s"""
    max_position: int
    min_position: int
    reset_pwm: int
    max_pwm: float
    invert_pwm: bool
    """Set Joint Moving Direction bit k."""
    invert_joint: bool
    """Revert Encoder CountDir bit 2k ..."""
    invert_motor: bool
    """... and 2k+1."""


_AXIS_SLOTS: Final = ("active", "anchor", "ci_slots", "command", "hold", "homing_us",
               "joint_channel", "joint_position", "joint_view", "k", "motor_channel",
               "motor_position", "motor_view", "pos_previous", "pos_sum", "pwm", "raw",
               "reset_answer", "sensed", "settled", "settled_us", "since_us", "so_slots",
               "stall_anchor", "stall_us", "value", "vel_previous", "vel_sum")


class Axis:
    """Motor k's controller: counters, velocity estimate, mode, loops, homing, Settled.

    One :meth:`cycle` a control cycle does what the model's parts do in turn (every
    quantity in the same IEEE operations and order):

    - the joint and motor counters (channels 2k and 2k+1): direction bit, the signed
      16-bit view, the extension to an unbounded position by the wrapped difference;
    - the velocity estimate: the count difference over the time since the count last
      changed, then the low-pass;
    - the mode's controller: two discrete PIDs (position, velocity) with per-cycle sum and
      difference and conditional integration (anti-windup);
    - Settled, the PWM and the SO values.

    The state is kept flat (no objects per counter or loop): the cycle runs 11 000 times
    a virtual second in a fleet."""

    __slots__ = _AXIS_SLOTS

    def __init__(self, k: int) -> None:
        self.k = k
        self.joint_channel, self.motor_channel = 2 * k, 2 * k + 1
        self.joint_view = 0
        """Joint counter after the direction bit, signed 16 bit."""
        self.joint_position = 0
        """The extended joint count."""
        self.motor_view = 0
        self.motor_position = 0
        self.sensed = False
        """The counters were read once (the first reading: no motion yet)."""
        self.anchor = 0
        """Velocity estimate: the joint count at its last change ..."""
        self.since_us = 0.0
        """... the time since ..."""
        self.raw = 0.0
        """... the unfiltered and ..."""
        self.value = 0.0
        """... the filtered velocity [counts/s]."""
        self.pos_sum = 0.0
        self.pos_previous: float | None = None
        """Position loop: sum and last error (None: no difference yet)."""
        self.vel_sum = 0.0
        self.vel_previous: float | None = None
        """Velocity loop: sum and last error."""
        self.command: int | None = None
        self.hold: int | None = None
        """Target of the position loop in HOMING (after the stall), else None."""
        self.reset_answer = NEVER_HOMED
        self.homing_us = 0.0
        self.stall_anchor = 0
        self.stall_us = 0.0
        self.settled_us = 0.0
        self.settled = False
        self.active = False
        self.pwm = 0.0
        """The program's PWM (before the direction bit)."""
        self.ci_slots = (_COMMAND[k], _TARGET[k], _TARGET_VEL[k], _RESET_OFFSET[k])
        self.so_slots = (_JOINT_ENCODER[k], _MOTOR_ENCODER[k], _VOLTAGE[k], _RESET_ANSWER[k],
                         _VELOCITY[k], _SETTLED[k])

    def at_rest(self) -> bool:
        """Could the cycle repeat itself (see :class:`_Quiet`): no velocity, the count where
        it last changed, no homing under way."""
        return (self.raw == 0.0 and self.value == 0.0 and self.joint_position == self.anchor
                and self.sensed and self.since_us > 0
                and not (self.command == _CMD_HOMING and self.hold is None))

    def state(self) -> tuple[object, ...]:
        """Everything a cycle reads or writes but the time since the count changed and
        Settled's time (:data:`_STATE`; floats by their bits: 0.0 is not -0.0).

        Spelt out, not a loop over the names: the quiet check (``Armar3Model.step``)
        takes it twice a cycle of a board at rest, and ``getattr`` by name with a float's
        ``hex()`` cost some 20,000 instructions a call (a tenth of a moving fleet's
        time in process); ``tests/test_armar3_axis_state.py`` holds it to :data:`_STATE`."""
        pos_previous, vel_previous = self.pos_previous, self.vel_previous
        return (self.active, self.anchor, self.command, self.hold, self.joint_channel,
                self.joint_position, self.joint_view, self.k, self.motor_channel,
                self.motor_position, self.motor_view, self.reset_answer, self.sensed,
                self.settled, self.stall_anchor, pos_previous is None, vel_previous is None,
                _FLOAT_BITS.pack(self.homing_us, self.pos_sum, self.pwm, self.raw,
                                 self.stall_us, self.value, self.vel_sum,
                                 0.0 if pos_previous is None else pos_previous,
                                 0.0 if vel_previous is None else vel_previous))

    def reset_velocity(self, position: int) -> None:
        self.anchor = position
        self.since_us = 0.0
        self.raw = 0.0
        self.value = 0.0

    def _reset_loops(self) -> None:
        self.pos_sum, self.pos_previous = 0.0, None
        self.vel_sum, self.vel_previous = 0.0, None

    def set_joint(self, hw: Hardware, invert: bool, value: int) -> None:
        """Load the joint counter (FPGA channel 2k) with ``value``."""
        hw.fpga.write(_QUAD_COUNT0 + self.joint_channel, -value if invert else value)
        self.joint_view = signed16(value)
        self.joint_position = value

    def cycle(self, hw: Hardware, counters: list[QuadratureDecoder], c: AxisConfig,
              ci: list[int], so: list[int], adc: list[int], dt_us: float, control: bool,
              resumed: bool) -> int:
        """Sense, control (if ``control``: else only sense and report) and report one
        cycle; returns the PWM register's value (before the 16-bit mask)."""
        position = self._sense(counters, c)
        value = self._estimate_velocity(position, dt_us)
        if control:
            self._control(hw, c, ci, position, value, dt_us, resumed)
        self._report(so, adc)
        return round_half_even(-self.pwm if c.invert_pwm else self.pwm)

    def _sense(self, counters: list[QuadratureDecoder], c: AxisConfig) -> int:
        """Read the joint and motor counters (direction bits, the signed 16-bit views) and
        extend them by the wrapped difference; returns the joint position."""
        raw_count = counters[self.joint_channel].count
        view = (-raw_count if c.invert_joint else raw_count) & 0xFFFF
        if view & 0x8000:
            view -= 0x10000
        raw_count = counters[self.motor_channel].count
        mview = (-raw_count if c.invert_motor else raw_count) & 0xFFFF
        if mview & 0x8000:
            mview -= 0x10000
        if self.sensed:
            step = (view - self.joint_view) & 0xFFFF
            position = self.joint_position + (step - 0x10000 if step & 0x8000 else step)
            step = (mview - self.motor_view) & 0xFFFF
            self.motor_position += step - 0x10000 if step & 0x8000 else step
        else:  # the first reading: no motion yet
            position = view
            self.motor_position = mview
            self.reset_velocity(position)
            self.sensed = True
        self.joint_view, self.joint_position, self.motor_view = view, position, mview
        return position

    def _estimate_velocity(self, position: int, dt_us: float) -> float:
        """The count difference over the time since the count last changed, low-passed;
        returns the filtered velocity [counts/s]."""
        since = self.since_us + dt_us
        self.since_us = since
        if since <= 0:  # (as written: a nan goes on below)
            return self.value
        raw = self.raw
        anchor = self.anchor
        if position != anchor:
            self.raw = raw = (position - anchor) * 1e6 / since
            self.anchor, self.since_us = position, 0.0
        elif since >= STANDSTILL_US:
            self.raw = raw = 0.0
        elif (raw if raw >= 0 else -raw) * since > 1e6:  # slower than one count since
            self.raw = raw = math.copysign(1e6 / since, raw)
        value = self.value
        self.value = value = value + dt_us / (VELOCITY_FILTER_US + dt_us) * (raw - value)
        return value

    def _control(self, hw: Hardware, c: AxisConfig, ci: list[int], position: int,
                 value: float, dt_us: float, resumed: bool) -> None:
        """The mode's controller (the Command from CI), the PWM, and Settled."""
        command_slot, target_slot, target_vel_slot, reset_offset_slot = self.ci_slots
        command = ci[command_slot]
        if command not in _CONTROLLED:
            command = _CMD_OFF
        if command != self.command or resumed:
            self._enter(command, resumed)
            self.command = command
        self.active = command != _CMD_OFF
        goal: int | None = None
        if command == _CMD_OFF:
            pwm = 0.0
        elif command == _CMD_HOMING and self.hold is None:
            self._home(hw, c, ci[reset_offset_slot], dt_us)
            pwm = self.pwm
        elif command == _CMD_VELOCITY:
            pwm = self._velocity_mode(c, ci[target_vel_slot], position, value)
        else:
            hold = self.hold
            if hold is not None:
                goal, feedforward = hold, 0.0
            else:
                target, low_p, high_p = ci[target_slot], c.min_position, c.max_position
                goal = int(low_p if target < low_p else high_p if target > high_p
                           else target)
                feedforward = c.feedforward * ci[target_vel_slot]
            pwm = self._velocity_loop(self._position_loop(goal - position, feedforward, c)
                                      - value, c)
        self.pwm = pwm
        if goal is not None and abs(goal - self.joint_position) <= SETTLED_COUNTS \
                and abs(self.value) <= SETTLED_SPEED:
            self.settled_us += dt_us
        else:
            self.settled_us = 0.0
        self.settled = self.settled_us >= SETTLED_US

    def _velocity_mode(self, c: AxisConfig, target_vel: int, position: int,
                       value: float) -> float:
        """VELOCITY: the target velocity, slowed towards a position limit, through the
        velocity loop; returns the PWM."""
        v_cmd = clamp(target_vel, -c.v_max, c.v_max)
        if c.p > 0:
            gain = min(c.p, LIMIT_APPROACH_PER_S)
            high = max(0.0, gain * (c.max_position - position))
            low = min(0.0, gain * (c.min_position - position))
        else:
            high = math.inf if position < c.max_position else 0.0
            low = -math.inf if position > c.min_position else 0.0
        return self._velocity_loop(clamp(v_cmd, low, high) - value, c)

    def _position_loop(self, error: int, feedforward: float, c: AxisConfig) -> float:
        """The outer loop: a discrete PID as :meth:`_velocity_loop`, with the target
        velocity's feedforward; returns the velocity command, bounded to the maximum."""
        p, i, d, limit = c.p, c.i, c.d, c.v_max
        previous = self.pos_previous
        difference = 0.0 if previous is None else error - previous
        self.pos_previous = error
        total = self.pos_sum + error if i else 0.0
        out = feedforward + p * error + i * total + d * difference
        if (out if out >= 0 else -out) > limit and (out > 0) == (error > 0):
            total = self.pos_sum if i else 0.0  # anti-windup: hold the sum
            out = feedforward + p * error + i * total + d * difference
        self.pos_sum = total
        return -limit if out < -limit else limit if out > limit else out

    def _report(self, so: list[int], adc: list[int]) -> None:
        """The axis's SO values."""
        joint_so, motor_so, voltage_so, answer_so, velocity_so, settled_so = self.so_slots
        so[joint_so] = self.joint_view
        so[motor_so] = self.motor_view
        so[voltage_so] = min(3300, round_half_even(adc[self.k] * 3300 / 4095))
        so[answer_so] = self.reset_answer
        velocity = round_half_even(self.value)
        so[velocity_so] = -32768 if velocity < -32768 else 32767 if velocity > 32767 \
            else velocity
        so[settled_so] = int(self.settled)

    def _velocity_loop(self, error: float, c: AxisConfig) -> float:
        """The inner loop: a discrete PID ``u = P e + I sum(e) + D (e - e_prev)`` whose sum
        does not grow while the output saturates in the error's direction (with I = 0 the
        sum is held at 0)."""
        p, i, d, limit = c.vp, c.vi, c.vd, c.max_pwm
        previous = self.vel_previous
        difference = 0.0 if previous is None else error - previous
        self.vel_previous = error
        total = self.vel_sum + error if i else 0.0
        out = 0.0 + p * error + i * total + d * difference
        if (out if out >= 0 else -out) > limit and (out > 0) == (error > 0):
            total = self.vel_sum if i else 0.0  # anti-windup: hold the sum
            out = 0.0 + p * error + i * total + d * difference
        self.vel_sum = total
        return -limit if out < -limit else limit if out > limit else out

    def stop(self) -> None:
        if self.reset_answer == HOMING:
            self.reset_answer = HOMING_FAILED
        self.command = None
        self.hold = None
        self._reset_loops()
        self.pwm, self.active, self.settled, self.settled_us = 0.0, False, False, 0.0

    def _enter(self, command: int, resumed: bool) -> None:
        self._reset_loops()
        self.settled_us = 0.0
        if self.reset_answer == HOMING:  # left HOMING before the stall
            self.reset_answer = HOMING_FAILED
        self.hold = None
        if command == _CMD_HOMING:
            if resumed:
                self.hold = self.joint_position
            else:
                self.reset_answer = HOMING
                self.homing_us = 0.0
                self.stall_anchor, self.stall_us = self.joint_position, 0.0

    def _home(self, hw: Hardware, c: AxisConfig, offset: int, dt_us: float) -> None:
        position = self.joint_position
        self.homing_us += dt_us
        if abs(position - self.stall_anchor) > STALL_COUNTS:
            self.stall_anchor, self.stall_us = position, 0.0
        elif hw.adc[self.k] * 3300 / 4095 >= STALL_CURRENT_MV:
            self.stall_us += dt_us
        else:  # no current: the stage does not drive (e.g. the FPGA is neutral)
            self.stall_us = 0.0
        if c.reset_pwm == 0 or self.homing_us > HOMING_TIMEOUT_US:
            self.reset_answer, self.hold = HOMING_FAILED, position
            self.pwm = 0.0
        elif self.stall_us >= STALL_US:
            self.set_joint(hw, c.invert_joint, offset)
            self.reset_velocity(offset)
            self.reset_answer, self.hold = HOMED, offset
            self.pwm = 0.0
        else:
            self.pwm = clamp(c.reset_pwm, -c.max_pwm, c.max_pwm)


_STATE: Final = tuple(sorted(set(_AXIS_SLOTS) - {"since_us", "settled_us", "so_slots",
                                                "ci_slots"}))
"""What :meth:`Axis.state` compares."""
_FLOAT_BITS: Final = struct.Struct("<9d")
"""The float part of :meth:`Axis.state`, by its bits."""
