"""Model of ``lauron4.fl.S``, the LAURON-IV leg program (dissertation 5.5.1; design in
``attribute_trees/lauron4/README.md``), for :data:`ucom_tools.edgelists.lauron4.SPEC`, and
:func:`make`, which puts it on a board with :class:`LegPlant`, the leg (or camera head) it
drives (:mod:`ucom_tools.virtual.hardware.lauron4_leg`, with the drive's constants).

The dissertation names only "the velocity cascade of every leg and of the head"; all
figures below are ours.

The drive (the same on all 20 joints, so the program's constants describe every board):
a 24 V motor, R = :data:`MOTOR_RESISTANCE` 2 ohm, Ke = Kt = :data:`MOTOR_KE` 0.03 V s/rad,
a 180:1 gear (:data:`GEAR_RATIO`), a 2048-edge motor encoder on channel 2k+1 and a joint
sensor of 1000 edges/degree on channel 2k, which the program counts through prescaler 10
(:data:`JOINT_PRESCALER`): one count is 0.01 deg, the unit of positions.

Sensing, every cycle, axis k:

- position = joint counter 2k as signed 16 bit (negated if bit 2k of
  ``Encoder Direction(BitMask)``); before a reference run it counts from power-up;
- velocity [0.01 deg/s] = the wrapped difference of motor counter 2k+1 (negated if bit
  2k+1) over the cycle (one count per 1 ms cycle is 0.98 deg/s; no filter, whose lag
  would let the velocity overshoot its limit);
- motor current [mA] = ADC channel k (the 3M board's current sense, magnitude, 0.5 V/A),
  signed with the current command; foot force X/Y/Z [0.1 N] = (ADC 3/4/5 - 2048) x 2
  (a strain-gauge amplifier, 0.2 N per LSB), low-passed with ``Foot Force Filter(ms)``
  (0: unfiltered); supply [mV] = ADC 6 x 10 (a divider on the board's analog input 1);
- reference switch of axis k = digital input bit k (closed above the reference mark).

Control of axis k (``Leg Mode``, :class:`~ucom_tools.edgelists.lauron4.LegMode`), gains as
the spec's units, limits read every cycle (a PAR or CI change acts in the next cycle):

- velocity command: POSITION and COMPLIANT ``Kp (clamp(set point, lower, upper) - pos)
  + velocity set point``; VELOCITY the velocity set point; then bounded by the joint
  limits (at most ``Kp (upper - pos)``, at least ``Kp (lower - pos)``: it brakes into a
  limit and returns into the limits; with Kp = 0 it stops at a limit), then to
  +-``Velocity Limit``;
- current command = ``Velocity Kp e + Velocity Ki sum(e)`` on e = command - velocity,
  limited to +-``Current Limit(mA)`` x ``Torque Limit(%)`` / 100; the sum does not grow
  while the output saturates in the error's direction, and is 0 in COMPLIANT (the joint is
  a spring-damper about its set point and gives way to a load above its torque limit);
- PWM = (R i + Ke w_motor) / supply x 16000 (the motor's voltage for that current at the
  measured speed), limited to +-``PWM Limit``, negated by bit k of
  ``Motor Direction(BitMask)``, written to PWM0+k as signed 16 bit; OUTPUT_ENABLE bit k
  while the axis is driven.  OFF, a stopped program or a neutral FPGA drive nothing.
- An axis is in use while its current limit x torque limit and velocity limit are > 0
  (the head's axis 3 is not).

Reference run: a ``Reference Run`` value greater than the last one starts homing of every
axis in use, in any mode (ignored while stopped): an axis below its mark (switch open)
runs up to it at :data:`HOMING_FAST`, then every axis backs off below the mark at
:data:`HOMING_FAST` and runs onto it at :data:`HOMING_SLOW`; the cycle the switch closes,
counter 2k := ``Reference Offset`` (the joint position of the mark), the axis is referenced
and holds there until every axis is done; then ``Leg Mode`` rules again.
:data:`HOMING_TIMEOUT_US` without the switch leaves an axis unreferenced.  Homing ignores
the joint limits (the positions are not yet known).

``Leg Status(BitMask)`` per axis: referenced; settled (a position loop runs, |target -
position| <= :data:`SETTLED_COUNTS` and |velocity| <= :data:`SETTLED_SPEED` for
:data:`SETTLED_US`, or in VELOCITY |command - velocity| <= :data:`SETTLED_SPEED` as long);
limit hit (a set point was clamped, the command bounded by a limit, or the position
outside the limits); over current (measured current above ``Current Limit(mA)``).
``Ground Contact`` = 1 while the filtered Z force exceeds ``Ground Contact
Threshold(N)``; a threshold of 0 means no foot: forces read 0, no contact.

Load (:meth:`Lauron4Model.step`): :data:`BASE_US` = 100 us per cycle (as ``armar3.fl.S``:
MCA loop, administration, communication) plus :data:`FOOT_US` = 30 us with a foot sensor
plus :data:`AXIS_US` = 200 us per driven axis: a leg in control 730 us of 1 ms, a head
500 us, everything off 130 us.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Final

from ucom_tools.edgelists.lauron4 import AXES, PWM_FULL, SPEC, LegMode, Status
from ucom_tools.edgelists.model import EdgeKind, ProgramSpec
from ucom_tools.virtual.hardware.lauron4_leg import (  # the board's constants re-exported
    ADC_FORCE,
    ADC_MID,
    ADC_SUPPLY,
    COXA,
    CURRENT_MA_PER_LSB,
    FEMUR,
    FORCE_DECI_N_PER_LSB,
    FRICTION,
    GEAR_RATIO,
    GROUND_DAMPING,
    GROUND_STIFFNESS,
    GROUND_Z,
    HEAD_JOINTS,
    JOINT_PRESCALER,
    LEG_JOINTS,
    MOTOR_COUNTS_PER_UNIT,
    MOTOR_KE,
    MOTOR_RESISTANCE,
    SUPPLY_MV_PER_LSB,
    TANGENT_DAMPING,
    TANGENT_STIFFNESS,
    TIBIA,
    UNIT_RAD,
    LegPlant,
)
from ucom_tools.virtual.hardware.motor import SUPPLY_V
from ucom_tools.virtual.hardware.numeric import clamp, round_half_even, signed16
from ucom_tools.virtual.programs.base import Hardware, Plant
from ucom_tools.wire.fpga import Reg

__all__ = [  # the program's names and, as before, the board's and the leg's
    "ADC_FORCE", "ADC_MID", "ADC_SUPPLY", "AXIS_US", "BASE_US", "COXA", "CURRENT_MA_PER_LSB",
    "FEMUR", "FOOT_US", "FORCE_DECI_N_PER_LSB", "FRICTION", "GEAR_RATIO", "GROUND_DAMPING",
    "GROUND_STIFFNESS", "GROUND_Z", "HEAD_JOINTS", "HOMING_FAST", "HOMING_SLOW",
    "HOMING_TIMEOUT_US", "JOINT_PRESCALER", "LEG_JOINTS", "MOTOR_COUNTS_PER_UNIT", "MOTOR_KE",
    "MOTOR_RESISTANCE", "SETTLED_COUNTS", "SETTLED_SPEED", "SETTLED_US", "SPEC",
    "SUPPLY_MV_PER_LSB", "TANGENT_DAMPING", "TANGENT_STIFFNESS", "TIBIA", "UNIT_RAD",
    "Lauron4Model", "LegPlant", "make"]

# ---------------------------------------------------------------- the program's constants
SETTLED_COUNTS: Final = 10
"""Position tolerance of Settled [0.01 deg]."""
SETTLED_SPEED: Final = 200.0
"""Velocity tolerance of Settled [0.01 deg/s]: two motor-encoder counts per 1 ms cycle
(one count is 98)."""
SETTLED_US: Final = 20_000.0
"""How long the tolerances must hold [us]."""
HOMING_FAST: Final = 2000.0
"""Homing speed up to the reference mark and back off it [0.01 deg/s]."""
HOMING_SLOW: Final = 200.0
"""Homing speed onto the mark [0.01 deg/s]: the mark is found to 0.002 deg at 1 ms."""
HOMING_TIMEOUT_US = 30_000_000.0
BASE_US: Final = 100.0
"""Execution time of a cycle with nothing driven and no foot [us]."""
FOOT_US: Final = 30.0
"""Foot-force filtering and contact, when a foot sensor is configured [us]."""
AXIS_US: Final = 200.0
"""Per driven axis (control or homing) [us]."""

class _Homing:
    """Where an axis is in a reference run (plain ints: compared every cycle)."""

    IDLE: Final = 0
    """Not homing."""
    SEEK: Final = 1
    """Below the mark: fast up to it."""
    LEAVE: Final = 2
    """On the mark: fast back below it."""
    APPROACH: Final = 3
    """Slowly onto the mark."""
    DONE: Final = 4
    """Referenced, holding at the mark until every axis is done."""


_SEARCHING: Final = (_Homing.SEEK, _Homing.LEAVE, _Homing.APPROACH)


def _indices(kind: EdgeKind) -> dict[str, int]:
    return {e.name: i for i, e in enumerate(SPEC.of(kind))}


_CI: Final = _indices(EdgeKind.CI)
_SO: Final = _indices(EdgeKind.SO)
_PAR: Final = _indices(EdgeKind.PAR)


def _axis_indices(table: dict[str, int], pattern: str) -> tuple[int, ...]:
    return tuple(table[pattern.format(n=n + 1)] for n in range(AXES))


_SETPOINT: Final = _axis_indices(_CI, "Axis{n} Position Setpoint")
_VEL_SETPOINT: Final = _axis_indices(_CI, "Axis{n} Velocity Setpoint")
_TORQUE: Final = _axis_indices(_CI, "Axis{n} Torque Limit(%)")
_POSITION: Final = _axis_indices(_SO, "Axis{n} Position")
_VELOCITY: Final = _axis_indices(_SO, "Axis{n} Velocity")
_CURRENT: Final = _axis_indices(_SO, "Axis{n} Motor Current")
_FORCE: Final = tuple(_SO[f"Foot Force {a}"] for a in "XYZ")
_KP: Final = _axis_indices(_PAR, "Axis{n} Position Kp")
_VKP: Final = _axis_indices(_PAR, "Axis{n} Velocity Kp")
_VKI: Final = _axis_indices(_PAR, "Axis{n} Velocity Ki")
_VLIMIT: Final = _axis_indices(_PAR, "Axis{n} Velocity Limit")
_ILIMIT: Final = _axis_indices(_PAR, "Axis{n} Current Limit(mA)")
_UPPER: Final = _axis_indices(_PAR, "Axis{n} Upper Limit")
_LOWER: Final = _axis_indices(_PAR, "Axis{n} Lower Limit")
_OFFSET: Final = _axis_indices(_PAR, "Axis{n} Reference Offset")
_LEG_MODE: Final = _CI["Leg Mode"]
_REFERENCE_RUN: Final = _CI["Reference Run"]
_GROUND_CONTACT: Final = _SO["Ground Contact"]
_LEG_STATUS: Final = _SO["Leg Status(BitMask)"]
_SUPPLY_VOLTAGE: Final = _SO["Supply Voltage(mV)"]
_PWM_LIMIT: Final = _PAR["PWM Limit"]
_ENCODER_DIRECTION: Final = _PAR["Encoder Direction(BitMask)"]
_MOTOR_DIRECTION: Final = _PAR["Motor Direction(BitMask)"]
_CONTACT_THRESHOLD: Final = _PAR["Ground Contact Threshold(N)"]
_FOOT_FILTER: Final = _PAR["Foot Force Filter(ms)"]

# the enums' members as plain ints for the code that runs every cycle (an IntEnum member
# costs a lookup on every use)
_OFF: Final = int(LegMode.OFF)
_VELOCITY_MODE: Final = int(LegMode.VELOCITY)
_COMPLIANT: Final = int(LegMode.COMPLIANT)
_REFERENCED: Final = int(Status.REFERENCED)
_SETTLED: Final = int(Status.SETTLED)
_LIMIT_HIT: Final = int(Status.LIMIT_HIT)
_OVER_CURRENT: Final = int(Status.OVER_CURRENT)
_QUAD_COUNT0: Final = int(Reg.QUAD_COUNT0)
_QUAD_PRESCALE0: Final = int(Reg.QUAD_PRESCALE0)
_PWM0: Final = int(Reg.PWM0)
_OUTPUT_ENABLE: Final = int(Reg.OUTPUT_ENABLE)
_DIGITAL_IN: Final = int(Reg.DIGITAL_IN)


class _Axis:
    """The controller state of one axis."""

    def __init__(self, k: int) -> None:
        self.k = k
        self.position = 0
        self.motor_count = 0
        self.velocity = 0.0
        self.current = 0
        """Measured motor current [mA], signed with the command."""
        self.integral = 0.0
        self.command = 0.0
        """Current command [mA]."""
        self.driven = False
        self.referenced = False
        self.homing = _Homing.IDLE
        self.hold = 0
        self.settled_us = 0.0
        self.settled = False
        self.limit_hit = False

    def reset_control(self) -> None:
        self.integral = self.command = 0.0
        self.driven = self.settled = False
        self.settled_us = 0.0


class Lauron4Model:
    """``lauron4.fl.S`` on a virtual board: implements
    :class:`~ucom_tools.virtual.programs.base.ProgramModel` for
    :data:`ucom_tools.edgelists.lauron4.SPEC`."""

    def __init__(self, hardware: Hardware) -> None:
        self.spec: ProgramSpec = SPEC  # an instance field (see compiled.py)
        self.hw = hardware
        self.ci = [e.default for e in SPEC.of(EdgeKind.CI)]
        self.so = [e.default for e in SPEC.of(EdgeKind.SO)]
        self.par = [e.default for e in SPEC.of(EdgeKind.PAR)]
        self.axes = [_Axis(k) for k in range(AXES)]
        self.forces = [0.0, 0.0, 0.0]
        """Filtered foot force X, Y, Z [0.1 N]."""
        self._stopped = False
        self._last_reference_run = self.ci[_REFERENCE_RUN]
        self._homing_us = 0.0
        fpga = hardware.fpga
        for k in range(AXES):
            fpga.write(_QUAD_PRESCALE0 + 2 * k, JOINT_PRESCALER)
            fpga.write(_QUAD_PRESCALE0 + 2 * k + 1, 1)
        self._outputs_off()
        for a in self.axes:
            a.motor_count = fpga.read(_QUAD_COUNT0 + 2 * a.k + 1)

    # ------------------------------------------------------------------ ProgramModel
    def loop_us(self) -> float:
        return float(self.par[_PAR["Cycle Time(us)"]])

    def step(self, dt_us: float) -> float:
        dt_us = max(0.0, dt_us)
        neutral = self.hw.fpga.neutral  # STATUS bit 0
        self._sense(dt_us)
        run = self.ci[_REFERENCE_RUN]
        if run > self._last_reference_run and not (self._stopped or neutral):
            self._start_homing()
        self._last_reference_run = run
        if self._stopped or neutral:
            for a in self.axes:
                a.reset_control()
            self._outputs_off()
        else:
            self._control(dt_us)
        self._report()
        foot = FOOT_US if self.par[_CONTACT_THRESHOLD] else 0.0
        return BASE_US + foot + AXIS_US * sum(a.driven for a in self.axes)

    def stop(self) -> None:
        self._stopped = True
        for a in self.axes:
            a.reset_control()
            a.homing = _Homing.IDLE  # an unfinished reference run is aborted
        self._outputs_off()

    def release(self) -> None:
        self._stopped = False

    # ------------------------------------------------------------------ sensing
    def _sense(self, dt_us: float) -> None:
        direction = self.par[_ENCODER_DIRECTION]
        adc = self.hw.adc
        counters = self.hw.fpga.quad  # as VirtualFpga.read(QUAD_COUNT0 + n)
        for a in self.axes:
            joint, motor = 2 * a.k, 2 * a.k + 1
            count = counters[joint].count
            a.position = signed16(-count if direction >> joint & 1 else count)
            count = counters[motor].count
            moved = signed16(count - a.motor_count)
            a.motor_count = count
            if dt_us > 0:
                sign = -1 if direction >> motor & 1 else 1
                a.velocity = sign * moved / MOTOR_COUNTS_PER_UNIT * 1e6 / dt_us
            a.current = round_half_even(math.copysign(adc[a.k] * CURRENT_MA_PER_LSB, a.command))
        tau_us = self.par[_FOOT_FILTER] * 1000.0
        blend = 1.0 if tau_us == 0 else 1.0 - math.exp(-dt_us / tau_us)
        for i, channel in enumerate(ADC_FORCE):
            raw_force = (adc[channel] - ADC_MID) * FORCE_DECI_N_PER_LSB
            self.forces[i] += blend * (raw_force - self.forces[i])

    # ------------------------------------------------------------------ control
    def _in_use(self, k: int) -> bool:
        par = self.par
        return (par[_ILIMIT[k]] * self.ci[_TORQUE[k]] > 0 and par[_VLIMIT[k]] > 0)

    def _start_homing(self) -> None:
        self._homing_us = 0.0
        for a in self.axes:
            a.reset_control()
            if self._in_use(a.k):
                a.referenced = False
                a.homing = _Homing.SEEK
            else:
                a.homing = _Homing.IDLE

    def _home(self, a: _Axis, switches: int, kp: float) -> float | None:
        """The velocity command of a homing axis, None when it is not homing."""
        if a.homing == _Homing.IDLE:
            return None
        closed = bool(switches >> a.k & 1)
        if a.homing == _Homing.SEEK:
            if not closed:
                return HOMING_FAST
            a.homing = _Homing.LEAVE
        if a.homing == _Homing.LEAVE:
            if closed:
                return -HOMING_FAST
            a.homing = _Homing.APPROACH
        if a.homing == _Homing.APPROACH:
            if not closed:
                return HOMING_SLOW
            offset = self.par[_OFFSET[a.k]]
            direction = self.par[_ENCODER_DIRECTION]
            channel = 2 * a.k
            self.hw.fpga.write(_QUAD_COUNT0 + channel,
                               -offset if direction >> channel & 1 else offset)
            a.position = a.hold = offset
            a.referenced = True
            a.homing = _Homing.DONE
        return kp * (a.hold - a.position)

    def _control(self, dt_us: float) -> None:
        ci, par = self.ci, self.par
        mode = ci[_LEG_MODE]
        fpga = self.hw.fpga
        registers = fpga.registers  # PWM0 + k and OUTPUT_ENABLE, as VirtualFpga.write
        switches = fpga.read(_DIGITAL_IN)
        homing = any(a.homing in _SEARCHING for a in self.axes)
        if homing:
            self._homing_us += dt_us
            if self._homing_us > HOMING_TIMEOUT_US:
                homing = False
        if not homing:
            for a in self.axes:
                a.homing = _Homing.IDLE
        supply = max(1.0, self.hw.adc[ADC_SUPPLY] * SUPPLY_MV_PER_LSB / 1000.0)
        pwm_limit = par[_PWM_LIMIT]
        motor_direction = par[_MOTOR_DIRECTION]
        enable = 0
        for a in self.axes:
            k = a.k
            kp = par[_KP[k]] * 1e-2
            i_max = par[_ILIMIT[k]] * ci[_TORQUE[k]] / 100.0
            v_max = float(par[_VLIMIT[k]])
            upper, lower = par[_UPPER[k]], par[_LOWER[k]]
            upper = max(upper, lower)
            v_cmd = self._home(a, switches, kp) if homing else None
            target: float | None = None
            # before its mark is found an axis's position says nothing about its limits
            a.limit_hit = a.homing not in _SEARCHING and not lower <= a.position <= upper
            if v_cmd is None:
                if mode == _OFF or not self._in_use(k):
                    a.reset_control()
                    registers[_PWM0 + k] = 0
                    continue
                if mode == _VELOCITY_MODE:
                    v_cmd = float(ci[_VEL_SETPOINT[k]])
                else:
                    setpoint = ci[_SETPOINT[k]]
                    target = clamp(setpoint, lower, upper)
                    a.limit_hit |= target != setpoint
                    v_cmd = kp * (target - a.position) + ci[_VEL_SETPOINT[k]]
                if kp > 0:
                    low, high = kp * (lower - a.position), kp * (upper - a.position)
                else:  # no position loop: stop at a limit
                    low = -math.inf if a.position > lower else 0.0
                    high = math.inf if a.position < upper else 0.0
                bounded = clamp(v_cmd, low, high)
                a.limit_hit |= bounded != v_cmd
                v_cmd = bounded
            elif a.homing == _Homing.DONE:
                target = a.hold
            v_cmd = clamp(v_cmd, -v_max, v_max)
            error = v_cmd - a.velocity
            compliant = mode == _COMPLIANT and a.homing == _Homing.IDLE
            a.command = self._current(a, error, i_max, compliant, par)
            a.driven = True
            self._settle(a, target, error, dt_us)
            w_motor = a.velocity * UNIT_RAD * GEAR_RATIO
            volts = MOTOR_RESISTANCE * a.command / 1000.0 + MOTOR_KE * w_motor
            pwm = round_half_even(clamp(volts / supply * PWM_FULL, -pwm_limit, pwm_limit))
            if motor_direction >> k & 1:
                pwm = -pwm
            registers[_PWM0 + k] = pwm & 0xFFFF
            enable |= 1 << k
        registers[_OUTPUT_ENABLE] = enable

    def _current(self, a: _Axis, error: float, i_max: float, compliant: bool,
                 par: list[int]) -> float:
        vkp, vki = par[_VKP[a.k]] * 1e-3, par[_VKI[a.k]] * 1e-4
        if compliant or not vki:
            a.integral = 0.0
            return clamp(vkp * error, -i_max, i_max)
        integral = a.integral + vki * error
        out = vkp * error + integral
        if abs(out) > i_max and (out > 0) == (error > 0):
            integral = a.integral  # anti-windup: hold the sum
            out = vkp * error + integral
        a.integral = clamp(integral, -i_max, i_max)
        return clamp(out, -i_max, i_max)

    def _settle(self, a: _Axis, target: float | None, error: float, dt_us: float) -> None:
        if a.homing in _SEARCHING:
            ok = False  # searching the mark
        elif target is None:
            ok = abs(error) <= SETTLED_SPEED
        else:
            ok = (abs(target - a.position) <= SETTLED_COUNTS
                  and abs(a.velocity) <= SETTLED_SPEED)
        a.settled_us = a.settled_us + dt_us if ok else 0.0
        a.settled = a.settled_us >= SETTLED_US

    def _outputs_off(self) -> None:
        registers = self.hw.fpga.registers  # as VirtualFpga.write(PWM0 + k, 0) ...
        for k in range(AXES):
            registers[_PWM0 + k] = 0
        registers[_OUTPUT_ENABLE] = 0

    # ------------------------------------------------------------------ reporting
    def _report(self) -> None:
        so, par = self.so, self.par
        status = 0
        for a in self.axes:
            k = a.k
            so[_POSITION[k]] = a.position
            so[_VELOCITY[k]] = int(clamp(round_half_even(a.velocity), -32768, 32767))
            so[_CURRENT[k]] = int(clamp(a.current, -10000, 10000))
            limit = par[_ILIMIT[k]]
            flags = ((_REFERENCED if a.referenced else 0)
                     | (_SETTLED if a.settled and a.driven else 0)
                     | (_LIMIT_HIT if a.limit_hit and a.driven else 0)
                     | (_OVER_CURRENT if abs(a.current) > limit else 0))
            status |= flags << 4 * k
        threshold = par[_CONTACT_THRESHOLD]
        for i, index in enumerate(_FORCE):
            so[index] = (int(clamp(round_half_even(self.forces[i]), -5000, 5000))
                         if threshold else 0)
        so[_GROUND_CONTACT] = int(bool(threshold) and self.forces[2] > threshold)
        so[_LEG_STATUS] = status
        so[_SUPPLY_VOLTAGE] = min(40950, self.hw.adc[ADC_SUPPLY] * SUPPLY_MV_PER_LSB)


def make(hardware: Hardware, placement: str = "", plant: Plant | None = None,
         ) -> tuple[Lauron4Model, LegPlant]:
    """The program on ``hardware`` with the plant its board drives, chosen by the board's
    ``placement`` in the topology (the program cannot tell, the robot's mechanics can): a
    camera head ("head": pan, tilt, no foot, no ground), a right leg ("right": alpha's
    motor mounted the other way round, which the right legs' trees undo with Motor
    Direction bit 0), else a left leg on the ground.  ``plant``: the board's plant from
    a program before, kept when it is that leg (the caller resumes it)."""
    text = placement.lower()
    model = Lauron4Model(hardware)
    if "head" in text:
        if isinstance(plant, LegPlant) and plant.key == LegPlant.key_of(
                HEAD_JOINTS, None, False, (0.0, 0.0, None), SUPPLY_V):
            return model, plant
        return model, LegPlant(hardware.fpga, hardware.adc, HEAD_JOINTS, ground_z=None,
                               foot_sensor=False, marks=(0.0, 0.0, None))
    params = LEG_JOINTS
    if "right" in text:
        params = (replace(LEG_JOINTS[0], motor_polarity=-1), *LEG_JOINTS[1:])
    if isinstance(plant, LegPlant) and plant.key == LegPlant.key_of(
            params, GROUND_Z, True, (0.0, 0.0, 0.0), SUPPLY_V):
        return model, plant
    return model, LegPlant(hardware.fpga, hardware.adc, params)
