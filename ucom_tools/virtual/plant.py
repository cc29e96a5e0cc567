"""The physical world behind a virtual UCoM@3M: three brushed DC motors, gears, loads, sensors.

A :class:`ThreeAxisPlant` implements :class:`~ucom_tools.virtual.programs.base.Plant` for
the three-motor plug-on board (dissertation Tab. 4.3: 3 motors at 24 V / 5 A, 6 quadrature
inputs, current sensing per motor, 2 analog inputs).  Every figure below is ours: the
dissertation gives none for the ARMAR-III drives.  They are chosen so that the B.5 eyes
tree's gains give a well-damped cascade on this plant (see
:mod:`ucom_tools.virtual.programs.armar3`).

Drive of motor k (from the FPGA, read once per :meth:`ThreeAxisPlant.advance`):

- ``PWM0 + k`` (0x20-0x22) holds a signed 16-bit duty in two's complement; full scale
  :data:`~ucom_tools.edgelists.armar3.PWM_FULL` = 16000 = 100 % of :data:`SUPPLY_V`
  (larger values saturate at 100 %).
- The stage drives only while bit k of OUTPUT_ENABLE is set and the FPGA is not neutral
  (:meth:`VirtualFpga.outputs_enabled`); otherwise it is high impedance: no current, the
  motor coasts.  Enabled with duty 0 the bridge shorts the motor (back-EMF braking).

Per axis (:class:`AxisParams`, SI units; motor-side quantities on the motor shaft):

- armature resistance R [ohm]; inductance neglected (L/R << the 100 us substep);
- torque constant Kt [N m/A] = back-EMF constant Ke [V s/rad];
- the stage limits the current to +-:data:`CURRENT_LIMIT_A` = 5 A;
- rotor inertia J_m [kg m^2], viscous friction b [N m s/rad] and Coulomb friction T_c [N m]
  at the motor shaft (the gear's friction referred to the motor), with sticking at rest;
- gear ratio N (motor revolutions per joint revolution), rigid, no backlash;
- load inertia J_l [kg m^2] at the joint, seen by the motor as J_l / N^2; no gravity
  (the eyes turn about a vertical axis); an unused axis has J_l = 0 and no end stops;
- mechanical end stops on the joint [rad]: the joint stops dead there (no bounce), the
  motor stalls and its current rises to (V / R), at most 5 A;
- polarities (+1/-1): how the board is wired.  ``motor_polarity`` -1 means a positive
  duty turns the joint towards negative sensor counts (the eyes need ``Set Joint Moving
  Direction`` bit k for that reason); ``joint_sensor_polarity`` / ``motor_encoder_polarity``
  -1 means the sensor counts down when the joint turns positively.

Sensors:

- the joint sensor of axis k feeds quadrature channel 2k with :data:`JOINT_SENSOR_EDGES`
  = 360 000 edges per joint revolution (90 000 lines x 4), i.e. 1000 edges/degree; behind
  the eyes' prescaler 4 that is 250 counts/degree, so +-10 000 counts = +-40 degrees;
- the motor encoder of axis k feeds channel 2k+1 with :data:`MOTOR_ENCODER_EDGES` = 2048
  edges per motor revolution (512 lines x 4);
- the FPGA counts the edges and applies its prescaler (:meth:`VirtualFpga.encoder_edges`;
  nothing is counted in the neutral state);
- current sense: ADC channel k = |i| * :data:`CURRENT_SENSE_V_PER_A` (0.5 V/A, magnitude
  only, like an LMD18200-style sense output), 12 bit, 0..4095 for 0..3.3 V, so 5 A reads
  2.5 V = 3102;
- ADC channels 6 and 7: the board's two analog inputs, constant (:data:`ANALOG_INPUTS_V`,
  1.0 V and 2.0 V unless given); channels 3-5 read 0.

Defaults (:class:`AxisParams`; a small 24 V motor of the Maxon RE 25 class, ours):
R 4 ohm, Kt = Ke 0.0235 N m/A (24 V / Ke = 1021 rad/s, 9750 rpm; 6 A stall at 24 V, so
the 5 A limit acts above a duty of 83 %), J_m 3e-6 kg m^2 (rotor, gearhead input, encoder
disk), b 1e-5 N m s/rad, T_c 1 mN m (gearhead friction: 0.043 A, 0.17 V, a duty of 113 of
16000 to break away), N 200, J_l 2e-4 kg m^2 (reflected 5e-9: negligible), end stops
+-0.9 rad.  Derived: mechanical time constant J / (Kt^2/R + b) = 20 ms; one PWM unit
(1.5 mV) gives 4.3 joint counts/s at steady state (behind prescaler 4), so the eyes'
Velocity P = 1 closes the velocity loop at about 4.3 / 20 ms = 210 rad/s, four times the
position loop's P = 50 /s: a well-damped cascade.  The eyes' Max Velocity of 500 counts/s
is 2 degrees/s; the joint's no-load speed is 4.7 rad/s (270 degrees/s, 68 000 counts/s);
homing at a duty of 7000 runs at about 29 000 counts/s and stalls at 2.6 A.

Integration: a fixed substep of :data:`SUBSTEP_US` = 100 us, the last one of a call
shortened to what remains, semi-implicit in the damping terms (stable for any dt, same
result for the same calls).  A motor at rest before and after a substep (sticking, or
stalled at an end stop) skips the rest of the call's substeps: they would repeat that one
exactly.  No randomness.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from ucom_tools.edgelists.armar3 import PWM_FULL
from ucom_tools.virtual.fpga import QuadratureDecoder, VirtualFpga
from ucom_tools.wire.fpga import Reg

SUPPLY_V = 24.0
"""Motor supply [V] (Tab. 4.3)."""
CURRENT_LIMIT_A = 5.0
"""Current limit of each output stage [A] (Tab. 4.3)."""
SUBSTEP_US = 100.0
"""Integration substep [us]."""
MOTOR_ENCODER_EDGES = 2048
"""Motor encoder edges per motor revolution (512 lines, quadrature x4)."""
JOINT_SENSOR_EDGES = 360_000
"""Joint sensor edges per joint revolution (90 000 lines x4 = 1000 edges/degree)."""
CURRENT_SENSE_V_PER_A = 0.5
"""Current-sense gain [V/A], magnitude of the current."""
ADC_FULL_SCALE_V = 3.3
ADC_MAX = 4095
ANALOG_INPUTS_V = (1.0, 2.0)
"""The two analog inputs (ADC channels 6 and 7) [V]."""
MAX_AXES = 3

_TWO_PI = 2 * math.pi
_SUBSTEP_S = SUBSTEP_US * 1e-6
_PWM0, _OUTPUT_ENABLE = int(Reg.PWM0), int(Reg.OUTPUT_ENABLE)


@dataclass(frozen=True)
class AxisParams:
    """One motor, its gear and load (SI units; see the module docstring)."""

    resistance: float = 4.0
    """Armature resistance [ohm]."""
    torque_constant: float = 0.0235
    """Kt [N m/A] = Ke [V s/rad] (406 rpm/V, no-load 9750 rpm at 24 V)."""
    rotor_inertia: float = 3.0e-6
    """J_m [kg m^2]."""
    viscous_friction: float = 1.0e-5
    """b at the motor [N m s/rad]."""
    coulomb_friction: float = 1.0e-3
    """T_c at the motor [N m]."""
    gear_ratio: float = 200.0
    """N, motor revolutions per joint revolution."""
    load_inertia: float = 2.0e-4
    """J_l at the joint [kg m^2] (eyeball and camera)."""
    end_stops: tuple[float, float] | None = (-0.9, 0.9)
    """Joint end stops [rad] (about +-51.6 degrees), None for a free shaft."""
    motor_polarity: int = 1
    joint_sensor_polarity: int = 1
    motor_encoder_polarity: int = 1
    start_angle: float = 0.0
    """Joint angle at power-up [rad]."""

    def __post_init__(self) -> None:
        for name in ("motor_polarity", "joint_sensor_polarity", "motor_encoder_polarity"):
            if getattr(self, name) not in (1, -1):
                raise ValueError(f"{name} must be +1 or -1")
        if min(self.resistance, self.torque_constant, self.rotor_inertia,
               self.gear_ratio) <= 0:
            raise ValueError("resistance, torque constant, rotor inertia and gear ratio "
                             "must be positive")
        if min(self.viscous_friction, self.coulomb_friction, self.load_inertia) < 0:
            raise ValueError("friction and load inertia must not be negative")
        if self.end_stops is not None and not (
                self.end_stops[0] <= self.start_angle <= self.end_stops[1]):
            raise ValueError("start angle outside the end stops")


EYE_AXIS = AxisParams(motor_polarity=-1)
"""An ARMAR-III eye: wired so that the tree's ``Set Joint Moving Direction`` bit is needed."""
UNUSED_AXIS = AxisParams(load_inertia=0.0, end_stops=None)
"""A motor with nothing attached (the eyes board's Motor C)."""
EYES_BOARD = (EYE_AXIS, EYE_AXIS, UNUSED_AXIS)
"""Right eye (A), left eye (B), unused (C): the B.5 "Eyes" board."""
ARMAR3_BOARD = (EYE_AXIS, EYE_AXIS, EYE_AXIS)
"""Three eye-like axes, each wired as every ARMAR-III tree expects (its ``Set Joint Moving
Direction`` bit set): the plant of a virtual board whose joints are not known."""


class MotorAxis:
    """State of one motor, gear and joint (the LAURON-IV leg's joints add a torque from
    outside: :class:`ucom_tools.virtual.programs.lauron4.LegPlant`)."""

    def __init__(self, p: AxisParams) -> None:
        self.p = p
        self.inertia = p.rotor_inertia + p.load_inertia / p.gear_ratio ** 2
        self.angle = p.start_angle
        """Joint angle [rad]."""
        self.speed = 0.0
        """Motor speed [rad/s]."""
        self.current = 0.0
        """Motor current [A]."""
        self.joint_edges, self.motor_edges = self._edge_indices()
        self.sensed_angle = self.angle
        """The angle the edge counts are of."""
        self._fixed = (self.inertia, p.torque_constant, p.resistance, p.gear_ratio,
                       *(p.end_stops if p.end_stops is not None else (-math.inf, math.inf)))
        """J, Kt, R, N and the end stops (none: never reached)."""
        self._substep_terms = self._terms(_SUBSTEP_S)

    def _edge_indices(self) -> tuple[int, int]:
        """The joint sensor's and the motor encoder's edge count at the current angle."""
        p = self.p
        return (math.floor(p.joint_sensor_polarity * self.angle * JOINT_SENSOR_EDGES / _TWO_PI),
                math.floor(p.motor_encoder_polarity * self.angle * p.gear_ratio
                           * MOTOR_ENCODER_EDGES / _TWO_PI))

    def _terms(self, h: float) -> tuple[float, float, float, float, float]:
        """What a substep of ``h`` seconds needs besides the state and the voltage: the
        denominators J + h (b + Kt^2 / R) (driven) and J + h b (not driven, or the current
        limited), the Coulomb friction's share h T_c / (denominator) of each, and h Kt."""
        p = self.p
        damped = self.inertia + h * (p.viscous_friction + p.torque_constant ** 2 / p.resistance)
        free = self.inertia + h * p.viscous_friction
        return (damped, h * p.coulomb_friction / damped, free,
                h * p.coulomb_friction / free, h * p.torque_constant)

    def integrate(self, volts: float | None, h: float, steps: int = 1) -> None:
        """``steps`` substeps of ``h`` seconds each with ``volts`` at the terminals (None:
        stage off, no current).

        A substep: speed = (J speed + h Kt V / R) / (J + h (b + Kt^2 / R)), implicit in the
        viscous and back-EMF damping; where that speed means a current beyond the stage's
        limit, the current is held at the limit instead: speed = (J speed + h Kt i) /
        (J + h b).  Then Coulomb friction takes up to h T_c / (the denominator) off the
        speed (sticking at 0), the joint turns by h speed / N and stops dead at an end stop.
        Without a stage (None) only b and T_c act."""
        inertia, kt, resistance, gear, low, high = self._fixed
        damped, damped_coulomb, free, free_coulomb, limited_push = (
            self._substep_terms if h == _SUBSTEP_S else self._terms(h))
        if volts is None:
            push, damped, damped_coulomb = h * 0.0, free, free_coulomb
        else:
            push = h * (kt * volts / resistance)
        angle, speed = self.angle, self.speed
        # the hot spot: abs() and math.copysign() are written out as comparisons, the
        # products of loop invariants computed once (the same operations on the same
        # operands: the same result), the driven and the undriven substep apart
        if volts is None:
            for _ in range(steps):
                base = inertia * speed
                speed = (base + push) / damped
                if -damped_coulomb <= speed <= damped_coulomb:
                    speed = 0.0  # sticks
                else:
                    speed = speed - damped_coulomb if speed > 0.0 else speed + damped_coulomb
                angle += h * speed / gear
                if angle <= low:
                    angle, speed = low, max(speed, 0.0)
                elif angle >= high:
                    angle, speed = high, min(speed, 0.0)
                if speed == 0.0 and base == 0.0:
                    # at rest before and after (sticking, or stalled at an end stop), so
                    # the angle did not change either: the remaining substeps repeat this
                    # one exactly
                    break
        else:
            limit = CURRENT_LIMIT_A
            push_high, push_low = limited_push * limit, limited_push * -limit
            low_limit = -limit
            for _ in range(steps):
                base = inertia * speed
                speed = (base + push) / damped
                coulomb = damped_coulomb
                current = (volts - kt * speed) / resistance
                if current > limit:  # the stage limits; no back-EMF damping
                    speed = (base + push_high) / free
                    coulomb = free_coulomb
                elif current < low_limit:
                    speed = (base + push_low) / free
                    coulomb = free_coulomb
                if -coulomb <= speed <= coulomb:
                    speed = 0.0  # sticks
                else:
                    speed = speed - coulomb if speed > 0.0 else speed + coulomb
                angle += h * speed / gear
                if angle <= low:
                    angle, speed = low, max(speed, 0.0)
                elif angle >= high:
                    angle, speed = high, min(speed, 0.0)
                if speed == 0.0 and base == 0.0:
                    break  # as above
        self.angle, self.speed = angle, speed
        self.current = 0.0 if volts is None else max(-CURRENT_LIMIT_A, min(
            CURRENT_LIMIT_A, (volts - kt * speed) / resistance))

    def sense(self, counters: list[QuadratureDecoder] | None, k: int) -> None:
        """Feed the edges since the last call to quadrature ``counters`` 2k and 2k+1 (the
        FPGA's; None in its neutral state, which counts nothing)."""
        self.sensed_angle = self.angle
        joint, motor = self._edge_indices()
        if counters is not None:
            if joint != self.joint_edges:
                counters[2 * k].feed(joint - self.joint_edges)
            if motor != self.motor_edges:
                counters[2 * k + 1].feed(motor - self.motor_edges)
        self.joint_edges, self.motor_edges = joint, motor


def _adc(volts: float) -> int:
    volts = volts if volts < ADC_FULL_SCALE_V else ADC_FULL_SCALE_V
    return round((volts if volts > 0.0 else 0.0) / ADC_FULL_SCALE_V * ADC_MAX)


_ADC_ZERO = _adc(0.0)


class ThreeAxisPlant:
    """Motors, gears, loads and sensors of a three-motor plug-on board.

    ``axes`` motors are fitted (1..3; the others are absent: no current, no edges);
    ``params`` is one :class:`AxisParams` for all of them or one per fitted axis
    (default: the eyes board, :data:`EYES_BOARD`)."""

    def __init__(self, fpga: VirtualFpga, adc: list[int], axes: int = MAX_AXES,
                 params: AxisParams | Sequence[AxisParams] = EYES_BOARD,
                 analog_inputs_v: tuple[float, float] = ANALOG_INPUTS_V) -> None:
        if not 1 <= axes <= MAX_AXES:
            raise ValueError(f"axes must be 1..{MAX_AXES}")
        if len(adc) < 8:
            raise ValueError("the ADC has 8 channels")
        if isinstance(params, AxisParams):
            params = [params] * axes
        if len(params) < axes:
            raise ValueError(f"{axes} axes need {axes} AxisParams, got {len(params)}")
        self.fpga = fpga
        self.adc = adc
        self.axes = [MotorAxis(p) for p in params[:axes]]
        adc[6], adc[7] = (_adc(v) for v in analog_inputs_v)
        self._write_current_sense()

    # ------------------------------------------------------------------ Plant protocol
    def advance(self, dt_us: float) -> None:
        if dt_us < 0:
            raise ValueError("time runs forward")
        fpga = self.fpga
        neutral = fpga.neutral
        registers = fpga.registers
        enabled = 0 if neutral else registers[_OUTPUT_ENABLE]  # fpga.outputs_enabled()
        counters = None if neutral else fpga.quad
        full = int(dt_us // SUBSTEP_US)
        rest = dt_us - full * SUBSTEP_US
        adc = self.adc
        for k, axis in enumerate(self.axes):  # the axes do not interact
            volts: float | None = None
            if enabled >> k & 1:
                pwm = registers[_PWM0 + k] & 0xFFFF
                duty = (pwm - 0x10000 if pwm & 0x8000 else pwm) / PWM_FULL
                duty = duty if duty < 1.0 else 1.0  # max(-1.0, min(1.0, duty))
                duty = duty if duty > -1.0 else -1.0
                volts = axis.p.motor_polarity * duty * SUPPLY_V
            if axis.speed == 0.0 and not volts:  # at rest and undriven: nothing changes
                axis.current = 0.0
                if axis.angle != axis.sensed_angle:
                    axis.sense(counters, k)
                adc[k] = _ADC_ZERO  # the current sense of 0 A
                continue
            if full:
                axis.integrate(volts, _SUBSTEP_S, full)
            if rest > 1e-9:
                axis.integrate(volts, rest * 1e-6)
            if axis.angle != axis.sensed_angle:  # else the edge counts are the same
                axis.sense(counters, k)
            # the current sense (as _write_current_sense)
            current = axis.current
            adc[k] = _adc((current if current >= 0.0 else -current) * CURRENT_SENSE_V_PER_A)
        for k in range(len(self.axes), MAX_AXES):  # no motor fitted
            adc[k] = _ADC_ZERO

    def _write_current_sense(self) -> None:
        adc = self.adc
        for k, axis in enumerate(self.axes):
            adc[k] = _adc(abs(axis.current) * CURRENT_SENSE_V_PER_A)
        for k in range(len(self.axes), MAX_AXES):  # no motor fitted
            adc[k] = _ADC_ZERO

    # ------------------------------------------------------------------ for tests
    def joint_angle(self, k: int) -> float:
        """True joint angle of axis k [rad]."""
        return self.axes[k].angle

    def joint_velocity(self, k: int) -> float:
        """True joint velocity of axis k [rad/s]."""
        return self.axes[k].speed / self.axes[k].p.gear_ratio

    def motor_current(self, k: int) -> float:
        """Motor current of axis k [A] (signed)."""
        return self.axes[k].current

    def joint_edges(self, k: int) -> float:
        """True joint angle of axis k in joint-sensor edges (before any prescaler)."""
        p = self.axes[k].p
        return p.joint_sensor_polarity * self.axes[k].angle * JOINT_SENSOR_EDGES / (2 * math.pi)

