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

Integration (:meth:`ucom_tools.virtual.hardware.motor.MotorAxis.integrate`, the rule the LAURON-IV
leg uses too): a fixed substep of :data:`SUBSTEP_US` = 100 us, the last one of a call
shortened to what remains, semi-implicit in the damping terms (stable for any dt, same
result for the same calls).  A motor at rest before and after a substep (sticking, or
stalled at an end stop) skips the rest of the call's substeps: they would repeat that one
exactly.  No randomness.

The plant is the board's hardware, not its program's: a program that starts again gets the
plant it left (:meth:`ThreeAxisPlant.resume`), which coasted meanwhile (output stages off)
and, after a power loss, is bound to the board's new FPGA: its motor encoders count from 0
again (incremental), its joint sensors read the joint's position (absolute: a potentiometer
over SSI, dissertation 5.2.1, :attr:`~ucom_tools.virtual.hardware.fpga.QuadratureDecoder.absolute`),
from the start angle's reading of the first power-on.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Final, Protocol

from ucom_tools.edgelists.armar3 import PWM_FULL
from ucom_tools.virtual.hardware.fpga import VirtualFpga
from ucom_tools.virtual.hardware.motor import (
    _SUBSTEP_S,
    CURRENT_LIMIT_A,  # noqa: F401 - re-exported, as it was defined here
    JOINT_SENSOR_EDGES,
    MOTOR_ENCODER_EDGES,  # noqa: F401 - re-exported
    SUBSTEP_US,
    SUPPLY_V,
    AxisParams,
    MotorAxis,
)
from ucom_tools.virtual.hardware.numeric import round_half_even
from ucom_tools.wire.fpga import Reg

CURRENT_SENSE_V_PER_A: Final = 0.5
"""Current-sense gain [V/A], magnitude of the current."""
ADC_FULL_SCALE_V: Final = 3.3
ADC_MAX: Final = 4095
ANALOG_INPUTS_V: Final = (1.0, 2.0)
"""The two analog inputs (ADC channels 6 and 7) [V]."""
MAX_AXES: Final = 3
_PWM_FULL: Final = PWM_FULL

_PWM0: Final = int(Reg.PWM0)
_OUTPUT_ENABLE: Final = int(Reg.OUTPUT_ENABLE)

EYE_AXIS: Final = AxisParams(motor_polarity=-1)
"""An ARMAR-III eye: wired so that the tree's ``Set Joint Moving Direction`` bit is needed."""
UNUSED_AXIS: Final = AxisParams(load_inertia=0.0, end_stops=None)
"""A motor with nothing attached (the eyes board's Motor C)."""
EYES_BOARD: Final = (EYE_AXIS, EYE_AXIS, UNUSED_AXIS)
"""Right eye (A), left eye (B), unused (C): the B.5 "Eyes" board."""
ARMAR3_BOARD: Final = (EYE_AXIS, EYE_AXIS, EYE_AXIS)
"""Three eye-like axes, each wired as every ARMAR-III tree expects (its ``Set Joint Moving
Direction`` bit set): the plant of a virtual board whose joints are not known."""


def _adc(volts: float) -> int:
    volts = volts if volts < ADC_FULL_SCALE_V else ADC_FULL_SCALE_V
    return round_half_even((volts if volts > 0.0 else 0.0) / ADC_FULL_SCALE_V * ADC_MAX)


_ADC_ZERO: Final = _adc(0.0)
COAST_CHUNK_US: Final = 10_000.0
"""A plant coasting over a board's dead time (:func:`resume_motors`) is advanced in steps
of this many microseconds until it comes to rest: the rest of the time would change
nothing."""


class _Bound(Protocol):
    """A plant as :func:`resume_motors` moves and binds it."""

    fpga: VirtualFpga
    adc: list[int]

    def advance(self, dt_us: float) -> None: ...


def resume_motors(plant: _Bound, motors: Sequence[MotorAxis], fpga: VirtualFpga,
                  adc: list[int], dead_us: float) -> bool:
    """Bring a board's plant to the start of its program, ``dead_us`` after the last one
    moved it: its joints coast meanwhile, every output stage off (a motor at rest skips
    the time at once).  On the FPGA it was bound to (the board kept power: a DSP reset,
    a program that ended) its counters counted the coasting; on another one (the board
    lost power) nothing was counted, the plant is bound to ``fpga`` and ``adc``, the
    motor encoders count from 0 and the joint sensors (channel 2k) read absolute.
    True when it was bound anew (the caller writes its sensors to the new FPGA)."""
    if plant.fpga is fpga:
        _coast(plant, motors, dead_us)
        return False
    plant.fpga = VirtualFpga(fpga.config, -1)  # neutral: drives nothing, counts nothing
    _coast(plant, motors, dead_us)
    plant.fpga, plant.adc = fpga, adc
    for k, motor in enumerate(motors):
        motor.sense(None, k)  # the edges from here on are the new counters'
        joint = fpga.quad[2 * k]
        joint.absolute = motor.joint_position
        joint.reread()
    return True


def _coast(plant: _Bound, motors: Sequence[MotorAxis], dead_us: float) -> None:
    left = dead_us
    while left > 0.0:
        step = left if left < COAST_CHUNK_US else COAST_CHUNK_US
        before = [(m.angle, m.speed) for m in motors]
        plant.advance(step)
        left -= step
        if all(m.speed == 0.0 for m in motors) and \
                [(m.angle, m.speed) for m in motors] == before:
            return  # at rest, and stays so: the rest of the time changes nothing


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
        self.analog_inputs_v = analog_inputs_v
        self.key = self.key_of(axes, params, analog_inputs_v)
        """What the plant was made of (:meth:`key_of`): a program model reuses a board's
        plant made of the same."""
        adc[6], adc[7] = (_adc(v) for v in analog_inputs_v)
        self._write_current_sense()

    @staticmethod
    def key_of(axes: int, params: AxisParams | Sequence[AxisParams],
               analog_inputs_v: tuple[float, float]) -> tuple[object, ...]:
        """The :attr:`key` of a plant made with these arguments."""
        if isinstance(params, AxisParams):
            params = [params] * axes
        return (axes, tuple(params[:axes]), tuple(analog_inputs_v))

    def resume(self, fpga: VirtualFpga, adc: list[int], dead_us: float) -> None:
        """The board's program starts again (:func:`resume_motors`)."""
        if resume_motors(self, self.axes, fpga, adc, dead_us):
            adc[6], adc[7] = (_adc(v) for v in self.analog_inputs_v)
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
                duty = (pwm - 0x10000 if pwm & 0x8000 else pwm) / _PWM_FULL
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

