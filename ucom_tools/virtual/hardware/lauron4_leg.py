"""The LAURON-IV leg (or camera head) behind a UCoM@3M, which ``lauron4.fl.S``
(:mod:`ucom_tools.virtual.programs.lauron4`) drives: the drive's and the board's
constants, three joints moved by :class:`~ucom_tools.virtual.hardware.motor.MotorAxis`, the leg's
kinematics, the ground contact and the sensors (:class:`LegPlant`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from typing import Final

from ucom_tools.edgelists.lauron4 import AXES, PWM_FULL
from ucom_tools.virtual.hardware.fpga import VirtualFpga
from ucom_tools.virtual.hardware.motor import SUBSTEP_S as _SUBSTEP_S
from ucom_tools.virtual.hardware.numeric import clamp, round_half_even, signed16
from ucom_tools.virtual.hardware.plant import (
    ADC_FULL_SCALE_V,
    ADC_MAX,
    CURRENT_SENSE_V_PER_A,
    MOTOR_ENCODER_EDGES,
    SUBSTEP_US,
    SUPPLY_V,
    AxisParams,
    MotorAxis,
    resume_motors,
)
from ucom_tools.wire.fpga import Reg

# ---------------------------------------------------------------- the drive and the board
MOTOR_RESISTANCE: Final = 2.0
"""Armature resistance of every joint motor [ohm] (the program's motor model)."""
MOTOR_KE: Final = 0.03
"""Back-EMF constant = torque constant [V s/rad = N m/A]."""
GEAR_RATIO: Final = 180.0
JOINT_PRESCALER: Final = 10
"""1000 joint-sensor edges per degree / 10 = one count per 0.01 deg."""
UNIT_RAD: Final = math.pi / 18000
"""0.01 deg in rad."""
MOTOR_COUNTS_PER_UNIT: Final = MOTOR_ENCODER_EDGES * GEAR_RATIO / 36000
"""Motor-encoder counts per 0.01 deg of the joint (10.24)."""
ADC_MID: Final = 2048
"""ADC reading of 0 N at the foot sensor."""
FORCE_DECI_N_PER_LSB: Final = 2
"""Foot sensor: 0.2 N per LSB."""
SUPPLY_MV_PER_LSB: Final = 10
CURRENT_MA_PER_LSB: Final = ADC_FULL_SCALE_V / ADC_MAX / CURRENT_SENSE_V_PER_A * 1000
"""mA per LSB of the current sense (1.61)."""
ADC_FORCE: Final = (3, 4, 5)
ADC_SUPPLY: Final = 6

_PWM0: Final = int(Reg.PWM0)

# ---------------------------------------------------------------- the leg
COXA: Final = 0.10
FEMUR: Final = 0.20
TIBIA: Final = 0.25
"""Segment lengths [m]: alpha axis to beta axis, beta to gamma, gamma to the foot."""
GROUND_Z: Final = -0.26
"""Ground height below the beta axis [m] (the body held at a fixed height): at alpha =
beta = gamma = 0 the foot is 1 cm above it."""
GROUND_STIFFNESS: Final = 20_000.0
"""Normal stiffness of the ground contact [N/m]."""
GROUND_DAMPING: Final = 150.0
"""Normal damping [N s/m] (only while pressing, the ground never pulls)."""
TANGENT_STIFFNESS: Final = 10_000.0
"""Stiffness of the foot's grip on the ground [N/m]."""
TANGENT_DAMPING: Final = 100.0
FRICTION: Final = 0.6
"""Coulomb friction coefficient: the foot slips when the grip exceeds FRICTION x Fz."""

_DRIVE: Final = AxisParams(resistance=MOTOR_RESISTANCE, torque_constant=MOTOR_KE,
                    rotor_inertia=3.0e-6, viscous_friction=1.0e-5, coulomb_friction=1.0e-3,
                    gear_ratio=GEAR_RATIO)
_DEG: Final = math.pi / 180
LEG_JOINTS: Final = (
    replace(_DRIVE, load_inertia=0.04, end_stops=(-100 * _DEG, 100 * _DEG)),
    replace(_DRIVE, load_inertia=0.03, end_stops=(-70 * _DEG, 130 * _DEG)),
    replace(_DRIVE, load_inertia=0.01, end_stops=(-150 * _DEG, 50 * _DEG)),
)
"""Alpha, beta, gamma of a left leg (joint inertia with the rotor: 0.137, 0.127, 0.107
kg m^2; peak torque at 4 A: 21.6 N m).  A right leg: alpha with ``motor_polarity`` -1."""
HEAD_JOINTS: Final = (
    replace(_DRIVE, load_inertia=0.01, end_stops=(-170 * _DEG, 170 * _DEG)),
    replace(_DRIVE, load_inertia=0.005, end_stops=(-70 * _DEG, 70 * _DEG)),
    replace(_DRIVE, load_inertia=0.0, end_stops=None),
)
"""Pan, tilt, and the unused axis 3 of the camera head."""
_NO_TORQUES: Final = (0.0,) * AXES
"""The ground's torques on the joints out of contact."""


def _foot_z(beta: float, gamma: float) -> float:
    """The foot's height above the beta axis [m], as :meth:`LegPlant.foot` computes it."""
    return FEMUR * math.sin(beta) + TIBIA * math.sin(beta + gamma - math.pi / 2)


def _adc(volts: float) -> int:
    return round_half_even(clamp(volts, 0.0, ADC_FULL_SCALE_V) / ADC_FULL_SCALE_V * ADC_MAX)


class LegPlant:
    """A LAURON-IV leg (or the camera head) behind a UCoM@3M: three coupled joints, the
    foot's three-axis force sensor and the ground; implements
    :class:`~ucom_tools.virtual.programs.base.Plant`.

    The drives follow :class:`~ucom_tools.virtual.hardware.plant.ThreeAxisPlant` (PWM0+k signed
    duty of 16000, OUTPUT_ENABLE, 5 A stages, current sense |i| x 0.5 V/A on ADC k,
    joint sensor 2k, motor encoder 2k+1) with :data:`LEG_JOINTS` or :data:`HEAD_JOINTS`.
    The foot is at the end of :data:`COXA`, :data:`FEMUR`, :data:`TIBIA`: alpha turns the
    leg about the vertical (positive forwards), beta lifts the femur (0 horizontal),
    gamma bends the knee (0: tibia at right angles to the femur, pointing down; negative
    folds it).  Below ``ground_z`` the ground pushes (a spring-damper) and grips (a spring
    anchored where the foot touched down, slipping above :data:`FRICTION` x Fz); the forces
    act back on the joints.  No gravity.  ``load`` adds a torque [N m] per joint.
    Sensors also: foot force (X forwards, Y outwards, Z up) on ADC 3-5 at 0.2 N/LSB about
    2048 (0 when ``foot_sensor`` is False), supply on ADC 6 at 10 mV/LSB, reference
    switch k on digital input k, closed while joint k is at or above ``marks[k]`` [rad]
    (None: no switch).

    Integration as :class:`~ucom_tools.virtual.hardware.plant.ThreeAxisPlant`, 100 us substeps with
    the ground's forces from the start of each; while the foot is off the ground the joints
    do not act on each other, and each is integrated over a whole call on its own (the same
    result, bit for bit).
    """

    def __init__(self, fpga: VirtualFpga, adc: list[int],
                 params: Sequence[AxisParams] = LEG_JOINTS, *,
                 ground_z: float | None = GROUND_Z, foot_sensor: bool = True,
                 marks: Sequence[float | None] = (0.0, 0.0, 0.0),
                 supply_v: float = SUPPLY_V) -> None:
        if len(params) != AXES or len(marks) != AXES:
            raise ValueError(f"a leg has {AXES} joints")
        if len(adc) < 8:
            raise ValueError("the ADC has 8 channels")
        self.fpga = fpga
        self.adc = adc
        self.joints = [MotorAxis(p) for p in params]
        self.ground_z = ground_z
        self.foot_sensor = foot_sensor
        self.marks = tuple(marks)
        self.supply_v = supply_v
        self.load = [0.0] * AXES
        """Torque from outside on each joint [N m] (what a test pushes with)."""
        self.force = (0.0, 0.0, 0.0)
        """The ground's force on the foot [N] (X, Y, Z)."""
        self._anchor: tuple[float, float] | None = None
        self.apart = True
        """Integrate the joints apart while the foot is off the ground (False: always
        together with the ground's forces, the slower way that gives the same result:
        for the test that says so)."""
        self.key = self.key_of(params, ground_z, foot_sensor, marks, supply_v)
        """What the leg was made of (:meth:`key_of`): a program model reuses a board's
        plant made of the same."""
        self._write_sensors()

    @staticmethod
    def key_of(params: Sequence[AxisParams], ground_z: float | None, foot_sensor: bool,
               marks: Sequence[float | None], supply_v: float) -> tuple[object, ...]:
        """The :attr:`key` of a leg made with these arguments (all given: see
        compiled.py)."""
        return (tuple(params), ground_z, foot_sensor, tuple(marks), supply_v)

    def resume(self, fpga: VirtualFpga, adc: list[int], dead_us: float) -> None:
        """The board's program starts again: the joints coast over the dead time (the
        ground still acts), then, after a power loss, the leg is bound to the new FPGA
        with its joint sensors absolute (:func:`~ucom_tools.virtual.hardware.plant.resume_motors`,
        the rule of the three-axis plant)."""
        if resume_motors(self, self.joints, fpga, adc, dead_us):
            self._write_sensors()

    # ------------------------------------------------------------------ Plant protocol
    def advance(self, dt_us: float) -> None:
        if dt_us < 0:
            raise ValueError("time runs forward")
        fpga = self.fpga
        enabled = fpga.outputs_enabled()
        volts: list[float | None] = []
        for k, joint in enumerate(self.joints):
            if enabled >> k & 1:
                duty = clamp(signed16(fpga.registers[_PWM0 + k]) / PWM_FULL, -1.0, 1.0)
                volts.append(joint.p.motor_polarity * duty * self.supply_v)
            else:
                volts.append(None)
        # SUBSTEP_US each, the last one shortened to what remains
        full = int(dt_us // SUBSTEP_US)
        rest = dt_us - full * SUBSTEP_US
        substeps = [(_SUBSTEP_S, full)] if full else []
        if rest > 1e-9:
            substeps.append((rest * 1e-6, 1))
        if not (self.apart and self._advance_apart(volts, substeps)):
            self._advance_coupled(volts, substeps)
        counters = None if fpga.neutral else fpga.quad
        for k, joint in enumerate(self.joints):
            joint.sense(counters, k)
        self._write_sensors()

    def _advance_apart(self, volts: list[float | None],
                       substeps: list[tuple[float, int]]) -> bool:
        """Out of contact with the ground the joints do not act on each other: integrate each
        one over all ``substeps`` ((length [s], how many), in turn) on its own.  Then the
        foot's height at the start of every substep tells whether that held; if the foot
        touched the ground, undo it all and return False."""
        ground_z, joints = self.ground_z, self.joints
        if ground_z is not None and not ground_z - _foot_z(joints[1].angle, joints[2].angle) <= 0:
            return False  # in contact already
        before = [(j.angle, j.speed, j.current) for j in joints]
        watch = ground_z is not None and bool(substeps)
        traces: list[list[float] | None] = [None, [], []] if watch else [None] * AXES
        for joint, v, extra, trace in zip(joints, volts, self.load, traces, strict=True):
            for h, n in substeps:
                joint.integrate(v, h, n, 0.0 + extra, trace)
        if watch:
            assert ground_z is not None and traces[1] is not None and traces[2] is not None
            for beta, gamma in zip(traces[1][:-1], traces[2][:-1], strict=True):
                if not ground_z - _foot_z(beta, gamma) <= 0:
                    for j, (angle, speed, current) in zip(joints, before, strict=True):
                        j.angle, j.speed, j.current = angle, speed, current
                    return False
            self._anchor, self.force = None, (0.0, 0.0, 0.0)
        return True

    def _advance_coupled(self, volts: list[float | None],
                         substeps: list[tuple[float, int]]) -> None:
        """Substep by substep, the ground's forces (:meth:`_ground_torques`) on every joint."""
        drives = list(zip(self.joints, volts, self.load, strict=True))
        for h, n in substeps:
            for _ in range(n):
                torques = self._ground_torques()
                for (joint, v, extra), t in zip(drives, torques, strict=True):
                    joint.integrate(v, h, 1, t + extra)

    # ------------------------------------------------------------------ the foot
    def foot(self) -> tuple[tuple[float, float, float], list[tuple[float, float, float]]]:
        """Foot position (x forwards, y outwards, z up from the beta axis) [m] and its
        derivative by alpha, beta and gamma."""
        alpha, beta, gamma = self.joints
        a, b, g = alpha.angle, beta.angle, gamma.angle
        tibia = b + g - math.pi / 2
        sa, ca, sb, cb = math.sin(a), math.cos(a), math.sin(b), math.cos(b)
        st, ct = math.sin(tibia), math.cos(tibia)
        r = COXA + FEMUR * cb + TIBIA * ct
        z = FEMUR * sb + TIBIA * st
        dr_db, dz_db = -FEMUR * sb - TIBIA * st, FEMUR * cb + TIBIA * ct
        dr_dg, dz_dg = -TIBIA * st, TIBIA * ct
        return (r * sa, r * ca, z), [(r * ca, -r * sa, 0.0), (dr_db * sa, dr_db * ca, dz_db),
                                     (dr_dg * sa, dr_dg * ca, dz_dg)]

    def _ground_torques(self) -> Sequence[float]:
        if self.ground_z is None:
            return _NO_TORQUES
        (x, y, z), jacobian = self.foot()
        depth = self.ground_z - z
        if depth <= 0:
            self._anchor, self.force = None, (0.0, 0.0, 0.0)
            return _NO_TORQUES
        (dx_da, dy_da, dz_da), (dx_db, dy_db, dz_db), (dx_dg, dy_dg, dz_dg) = jacobian
        wa, wb, wg = [j.speed / j.p.gear_ratio for j in self.joints]  # their .velocity
        vx = sum((dx_da * wa, dx_db * wb, dx_dg * wg))
        vy = sum((dy_da * wa, dy_db * wb, dy_dg * wg))
        vz = sum((dz_da * wa, dz_db * wb, dz_dg * wg))
        fz = max(0.0, GROUND_STIFFNESS * depth - GROUND_DAMPING * vz)
        if self._anchor is None:
            self._anchor = (x, y)
        ax, ay = self._anchor
        sx, sy = -TANGENT_STIFFNESS * (x - ax), -TANGENT_STIFFNESS * (y - ay)
        grip = math.hypot(sx, sy)
        if grip > FRICTION * fz:  # slip: the anchor follows the foot
            scale = FRICTION * fz / grip
            sx, sy = sx * scale, sy * scale
            self._anchor = (x + sx / TANGENT_STIFFNESS, y + sy / TANGENT_STIFFNESS)
        fx, fy = sx - TANGENT_DAMPING * vx, sy - TANGENT_DAMPING * vy
        grip = math.hypot(fx, fy)
        if grip > FRICTION * fz:
            fx, fy = fx * FRICTION * fz / grip, fy * FRICTION * fz / grip
        self.force = (fx, fy, fz)
        return (fx * dx_da + fy * dy_da + fz * dz_da, fx * dx_db + fy * dy_db + fz * dz_db,
                fx * dx_dg + fy * dy_dg + fz * dz_dg)

    # ------------------------------------------------------------------ sensors
    def _write_sensors(self) -> None:
        adc = self.adc
        for k, joint in enumerate(self.joints):
            adc[k] = _adc(abs(joint.current) * CURRENT_SENSE_V_PER_A)
        for channel, f in zip(ADC_FORCE, self.force, strict=True):
            reading = ADC_MID + round_half_even(f * 10 / FORCE_DECI_N_PER_LSB)
            adc[channel] = int(clamp(reading, 0, ADC_MAX)) if self.foot_sensor else 0
        adc[ADC_SUPPLY] = int(clamp(round_half_even(self.supply_v * 1000 / SUPPLY_MV_PER_LSB),
                                     0, ADC_MAX))
        inputs = 0
        for k, (joint, mark) in enumerate(zip(self.joints, self.marks, strict=True)):
            if mark is not None and joint.angle >= mark:
                inputs |= 1 << k
        self.fpga.inputs = inputs

    # ------------------------------------------------------------------ for tests
    def joint_angle(self, k: int) -> float:
        """True angle of joint k [rad]."""
        return self.joints[k].angle

    def joint_velocity(self, k: int) -> float:
        """True velocity of joint k [rad/s]."""
        return self.joints[k].velocity

    def motor_current(self, k: int) -> float:
        """Motor current of axis k [A] (signed)."""
        return self.joints[k].current
