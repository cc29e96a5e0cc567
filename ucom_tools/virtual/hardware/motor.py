"""One brushed DC motor with its gear and joint: parameters, the integration rule, sensor edges.

The one copy of the motor model both board plants use (:class:`~ucom_tools.virtual.hardware.plant.
ThreeAxisPlant`, the ARMAR-III three-motor board, and the LAURON-IV leg of
:mod:`ucom_tools.virtual.hardware.lauron4_leg`); the physics and the figures are described
in :mod:`ucom_tools.virtual.hardware.plant`.

Integration: a fixed substep of :data:`SUBSTEP_US` = 100 us (the plant shortens the last
one of a call to what remains), semi-implicit in the damping terms (stable for any dt,
same result for the same calls).  A motor at rest before and after a substep (sticking, or
stalled at an end stop) skips the rest of the call's substeps: they would repeat that one
exactly.  No randomness.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

from ucom_tools.virtual.hardware.fpga import QuadratureDecoder

SUPPLY_V: Final = 24.0
"""Motor supply [V] (Tab. 4.3)."""
CURRENT_LIMIT_A: Final = 5.0
"""Current limit of each output stage [A] (Tab. 4.3)."""
SUBSTEP_US: Final = 100.0
"""Integration substep [us]."""
MOTOR_ENCODER_EDGES: Final = 2048
"""Motor encoder edges per motor revolution (512 lines, quadrature x4)."""
JOINT_SENSOR_EDGES: Final = 360_000
"""Joint sensor edges per joint revolution (90 000 lines x4 = 1000 edges/degree)."""

_TWO_PI: Final = 2 * math.pi
_SUBSTEP_S: Final = SUBSTEP_US * 1e-6
SUBSTEP_S: Final = _SUBSTEP_S
"""Integration substep [s]."""


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



class MotorAxis:
    """State of one motor, gear and joint, and the rule that moves it (both boards' plants:
    :class:`~ucom_tools.virtual.hardware.plant.ThreeAxisPlant`, and the LAURON-IV leg, whose joints
    add a torque from outside)."""

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
        self.joint_origin = self.joint_edges
        """The joint sensor's edge count at the start angle: its zero as an absolute sensor
        (:meth:`joint_position`), so that it reads at power-on what the counter did."""
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

    @property
    def velocity(self) -> float:
        """Joint velocity [rad/s]."""
        return self.speed / self.p.gear_ratio

    def integrate(self, volts: float | None, h: float, steps: int = 1,
                  torque: float | None = None, angles: list[float] | None = None) -> None:
        """``steps`` substeps of ``h`` seconds each with ``volts`` at the terminals (None:
        stage off, no current) and, if given, a constant ``torque`` [N m] from outside at
        the joint (the ground, a load), which adds torque / N to the motor's drive;
        ``angles`` (if given) gets the joint angle after every substep.

        A substep: speed = (J speed + h Kt V / R) / (J + h (b + Kt^2 / R)), implicit in the
        viscous and back-EMF damping; where that speed means a current beyond the stage's
        limit, the current is held at the limit instead: speed = (J speed + h Kt i) /
        (J + h b).  Then Coulomb friction takes up to h T_c / (the denominator) off the
        speed (sticking at 0), the joint turns by h speed / N and stops dead at an end stop.
        Without a stage (None) only b, T_c and the outside torque act.

        The current after the call: without an outside torque (``torque`` None, the
        three-axis plant) the current at the final speed, held within the stage's limit;
        with one (the LAURON-IV leg) the stage's limit if the last substep ran at it, else
        the current at the final speed (which an end stop can raise beyond the limit).
        The two models were written with these two rules, and with the limited drive's
        h Kt i + h T / N rounded in two orders ((h Kt) i without a torque, h (Kt i + T / N)
        with one); both are kept so that the recorded traces stay the same bit for bit."""
        terms = self._substep_terms if h == _SUBSTEP_S else self._terms(h)
        if volts is None:
            self._coast(h, steps, terms, torque, angles)
        else:
            self._drive(volts, h, steps, terms, torque, angles)

    # the hot spot, the two loops below: abs() and math.copysign() are written out as
    # comparisons, the products of loop invariants computed once (the same operations on
    # the same operands: the same result), the driven and the undriven substep apart

    def _coast(self, h: float, steps: int, terms: tuple[float, float, float, float, float],
               torque: float | None, angles: list[float] | None) -> None:
        """:meth:`integrate` without a stage: only b, T_c and the outside torque act."""
        inertia, _, _, gear, low, high = self._fixed
        _, _, free, free_coulomb, _ = terms
        push = h * (0.0 if torque is None else torque / gear)
        angle, speed = self.angle, self.speed
        for i in range(steps):
            base = inertia * speed
            speed = (base + push) / free
            if -free_coulomb <= speed <= free_coulomb:
                speed = 0.0  # sticks
            else:
                speed = speed - free_coulomb if speed > 0.0 else speed + free_coulomb
            angle += h * speed / gear
            if angle <= low:
                angle, speed = low, max(speed, 0.0)
            elif angle >= high:
                angle, speed = high, min(speed, 0.0)
            if angles is not None:
                angles.append(angle)
            if speed == 0.0 and base == 0.0:
                # at rest before and after (sticking, or stalled at an end stop), so the
                # angle did not change either: the remaining substeps repeat this one
                # exactly
                if angles is not None:
                    angles.extend([angle] * (steps - 1 - i))
                break
        self.angle, self.speed = angle, speed
        self.current = 0.0

    def _drive(self, volts: float, h: float, steps: int,
               terms: tuple[float, float, float, float, float], torque: float | None,
               angles: list[float] | None) -> None:
        """:meth:`integrate` with ``volts`` at the terminals, and the current after it."""
        inertia, kt, resistance, gear, low, high = self._fixed
        damped, damped_coulomb, free, free_coulomb, limited_push = terms
        limit = CURRENT_LIMIT_A
        if torque is None:
            push = h * (kt * volts / resistance)
            push_high, push_low = limited_push * limit, limited_push * -limit
        else:
            outside = torque / gear
            push = h * (outside + kt * volts / resistance)
            push_high, push_low = h * (kt * limit + outside), h * (kt * -limit + outside)
        angle, speed, current = self.angle, self.speed, 0.0
        low_limit = -limit
        for i in range(steps):
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
            if angles is not None:
                angles.append(angle)
            if speed == 0.0 and base == 0.0:  # as in _coast
                if angles is not None:
                    angles.extend([angle] * (steps - 1 - i))
                break
        self.angle, self.speed = angle, speed
        if torque is None:
            self.current = max(-limit, min(limit, (volts - kt * speed) / resistance))
        elif current >= limit:  # the last substep's current, before the stage limited it
            self.current = limit
        elif current <= -limit:
            self.current = -limit
        else:
            self.current = (volts - kt * speed) / resistance

    def sense(self, counters: list[QuadratureDecoder] | None, k: int) -> None:
        """Feed the edges since the last call to quadrature ``counters`` 2k and 2k+1 (the
        FPGA's; None in its neutral state, or unpowered, which counts nothing)."""
        self.sensed_angle = self.angle
        joint, motor = self._edge_indices()
        joint_before, motor_before = self.joint_edges, self.motor_edges
        self.joint_edges, self.motor_edges = joint, motor  # (an absolute channel reads them)
        if counters is not None:
            if joint != joint_before:
                counters[2 * k].feed(joint - joint_before)
            if motor != motor_before:
                counters[2 * k + 1].feed(motor - motor_before)

    def joint_position(self) -> int:
        """The joint sensor's position in edges as an absolute sensor reads it (from
        :attr:`joint_origin`; as of the last :meth:`sense`)."""
        return self.joint_edges - self.joint_origin
