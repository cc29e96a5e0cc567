"""``lauron4.fl.S``: the leg program of every LAURON-IV UCoM (dissertation 5.5.1).

One UCoM@3M per leg (axes alpha, beta, gamma) and one for the camera head (pan, tilt, an
unused third axis), each axis a velocity cascade: a proportional position loop plus the
velocity set point as feed-forward, limited to the velocity limit, then a PI velocity loop
giving the motor current command, limited to current limit x torque limit.  The 56 edges
are those of ``attribute_trees/lauron4/README.md``, in its order: CI 0-10, SO 11-25,
PAR 26-55.  Encodings, ranges and units are ours; every default of the LAURON-IV trees
travels exactly.  The model of the program is :mod:`ucom_tools.virtual.programs.lauron4`.

Units: joint positions in 0.01 deg (what the joint sensor counts, 36000 counts per turn);
velocities in 0.01 deg/s; currents in mA; PWM in 1/16000 of the supply (16000 = 100 %);
foot forces in N with one decimal (X forward, Y outward, Z up: the ground's force on the
foot, in the leg's axes); supply voltage in mV.  ``Position Kp`` is in 1/s (0.01 deg/s of
velocity command per 0.01 deg of position error), ``Velocity Kp`` in mA per 0.01 deg/s of
velocity error, ``Velocity Ki`` in mA per 0.01 deg/s of velocity error and control cycle
(the integral adds Ki x error every cycle, as the DSP does).  ``Leg Status(BitMask)`` has
one nibble per axis (axis 1 bits 0-3, axis 2 bits 4-7, axis 3 bits 8-11):
1 referenced, 2 settled, 4 limit hit, 8 over current.  ``Torque Limit(%)`` acts in every
mode; ``Reference Run`` starts a reference run whenever it grows (the PC counts it up).

The spec's defaults are a left leg's (what a board runs with before its tree's defaults
arrive), except the joint limits: +-180 deg, i.e. none, which the head's unused axis 3
keeps because its tree gives none.
"""

from __future__ import annotations

from enum import IntEnum, IntFlag

from ucom_tools.edgelists.model import CiSeed, EdgeKind, EdgeSpec, ProgramSpec, Seed

NAME = "lauron4 leg"
"""The program name of the ``lauron4.fl.S`` image descriptor."""
AXES = 3
PWM_FULL = 16000
POSITION_SPAN = 18000
"""Set points and joint limits are within +-180 deg (0.01 deg)."""
VELOCITY_SPAN = 30000
"""Velocities within +-300 deg/s (0.01 deg/s)."""
CURRENT_MAX_MA = 5000
"""The 3M board's motor stages give up to 5 A."""
FORCE_SPAN = 5000
"""Foot forces within +-500 N (0.1 N)."""

CI, SO, PAR = EdgeKind.CI, EdgeKind.SO, EdgeKind.PAR


class LegMode(IntEnum):
    """Values of ``Leg Mode`` (``Head Mode`` on the head)."""

    OFF = 0
    """Output stages off, PWM 0, controllers reset."""
    POSITION = 1
    """Position control towards the set points (clamped to the joint limits), the velocity
    set points added as feed-forward."""
    VELOCITY = 2
    """Velocity control at the velocity set points, slowed down towards the joint limits."""
    COMPLIANT = 3
    """Position control without the velocity integral: each joint a spring-damper about
    its set point, giving way when a load exceeds its torque limit."""


class Status(IntFlag):
    """Bits of one axis' nibble in ``Leg Status(BitMask)`` (shifted by 4 x axis index)."""

    REFERENCED = 0x1
    SETTLED = 0x2
    LIMIT_HIT = 0x4
    OVER_CURRENT = 0x8


PERIOD = 5
"""Default period of the cyclic values (cycles): 200 Hz at 1 ms, since the seven boards
share one bus (``man/ucom-protocol.7``, RUN TIME, Bus budget)."""
SLOW = 50
"""Default period of the status values (cycles): 20 Hz at 1 ms."""


def _axes(kind: EdgeKind, pattern: str, *, defaults: tuple[int, ...] = (0, 0, 0),
          signed: bool = True, exponent: int = 0, minimum: int = -32768,
          maximum: int = 32767, unit: str = "", period: int = 0) -> list[EdgeSpec]:
    """One edge per axis, ``pattern`` formatted with the axis number ``n`` = 1..3;
    ``defaults`` gives each axis its raw default."""
    return [EdgeSpec(kind, pattern.format(n=n + 1), signed=signed, exponent=exponent,
                     minimum=minimum, maximum=maximum, unit=unit, default=defaults[n],
                     period=period, axis=n)
            for n in range(AXES)]


def _ci() -> list[EdgeSpec]:
    edges = [EdgeSpec(CI, "Leg Mode", signed=False, minimum=0, maximum=3)]
    edges += _axes(CI, "Axis{n} Position Setpoint", minimum=-POSITION_SPAN,
                   maximum=POSITION_SPAN, unit="0.01 deg", period=PERIOD)
    edges += _axes(CI, "Axis{n} Velocity Setpoint", minimum=-VELOCITY_SPAN,
                   maximum=VELOCITY_SPAN, unit="0.01 deg/s")
    edges += _axes(CI, "Axis{n} Torque Limit(%)", signed=False, minimum=0, maximum=100,
                   unit="%", defaults=(100, 100, 100))
    edges.append(EdgeSpec(CI, "Reference Run", signed=False, minimum=0, maximum=0xFFFF))
    return edges


def _so() -> list[EdgeSpec]:
    edges = _axes(SO, "Axis{n} Position", unit="0.01 deg", period=PERIOD)
    edges += _axes(SO, "Axis{n} Velocity", unit="0.01 deg/s", period=PERIOD)
    edges += _axes(SO, "Axis{n} Motor Current", minimum=-10000, maximum=10000, unit="mA",
                   period=SLOW)
    edges += [EdgeSpec(SO, f"Foot Force {a}", exponent=-1, minimum=-FORCE_SPAN,
                       maximum=FORCE_SPAN, unit="N", period=PERIOD) for a in "XYZ"]
    edges += [
        EdgeSpec(SO, "Ground Contact", signed=False, minimum=0, maximum=1, period=PERIOD),
        EdgeSpec(SO, "Leg Status(BitMask)", signed=False, minimum=0, maximum=0xFFF,
                 period=SLOW),
        EdgeSpec(SO, "Supply Voltage(mV)", signed=False, minimum=0, maximum=40950,
                 unit="mV", period=SLOW),
    ]
    return edges


def _par() -> list[EdgeSpec]:
    edges = [
        EdgeSpec(PAR, "Cycle Time(us)", signed=False, minimum=100, maximum=32000, unit="us",
                 default=1000),
        EdgeSpec(PAR, "PWM Limit", signed=False, minimum=0, maximum=PWM_FULL,
                 unit="1/16000", default=12000),
        EdgeSpec(PAR, "Encoder Direction(BitMask)", signed=False, minimum=0, maximum=0x3F),
        EdgeSpec(PAR, "Motor Direction(BitMask)", signed=False, minimum=0, maximum=0x7),
    ]
    edges += _axes(PAR, "Axis{n} Position Kp", signed=False, exponent=-2, minimum=0,
                   maximum=30000, unit="1/s", defaults=(800, 800, 800))
    edges += _axes(PAR, "Axis{n} Velocity Kp", signed=False, exponent=-3, minimum=0,
                   maximum=50000, unit="mA/(0.01 deg/s)", defaults=(2500, 2500, 2500))
    edges += _axes(PAR, "Axis{n} Velocity Ki", signed=False, exponent=-4, minimum=0,
                   maximum=50000, unit="mA/(0.01 deg/s)/cycle", defaults=(200, 200, 200))
    edges += _axes(PAR, "Axis{n} Velocity Limit", signed=False, minimum=0,
                   maximum=VELOCITY_SPAN, unit="0.01 deg/s", defaults=(6000, 6000, 6000))
    edges += _axes(PAR, "Axis{n} Current Limit(mA)", signed=False, minimum=0,
                   maximum=CURRENT_MAX_MA, unit="mA", defaults=(4000, 4000, 4000))
    span = (POSITION_SPAN,) * AXES
    edges += _axes(PAR, "Axis{n} Upper Limit", minimum=-POSITION_SPAN, maximum=POSITION_SPAN,
                   unit="0.01 deg", defaults=span)
    edges += _axes(PAR, "Axis{n} Lower Limit", minimum=-POSITION_SPAN, maximum=POSITION_SPAN,
                   unit="0.01 deg", defaults=tuple(-s for s in span))
    edges += _axes(PAR, "Axis{n} Reference Offset", minimum=-POSITION_SPAN,
                   maximum=POSITION_SPAN, unit="0.01 deg")
    edges += [
        EdgeSpec(PAR, "Ground Contact Threshold(N)", signed=False, exponent=-1, minimum=0,
                 maximum=FORCE_SPAN, unit="N", default=150),
        EdgeSpec(PAR, "Foot Force Filter(ms)", signed=False, minimum=0, maximum=1000,
                 unit="ms", default=5),
    ]
    return edges


def _seeds() -> list[CiSeed]:
    """A rejoining leg holds each joint where it stands: the position set point is the
    joint's position, the velocity set point 0, and Reference Run the board's own value
    (after a power cycle 0: the PC's larger one would start a reference run)."""
    out = []
    for n in range(1, AXES + 1):
        out += [CiSeed(f"Axis{n} Position Setpoint", Seed.SENSOR, sensor=f"Axis{n} Position"),
                CiSeed(f"Axis{n} Velocity Setpoint", Seed.ZERO)]
    out.append(CiSeed("Reference Run", Seed.BOARD))
    return out


SPEC = ProgramSpec(NAME, "LAURON-IV leg: velocity cascade per joint, 3 axes, foot force",
                   tuple(_ci() + _so() + _par()),
                   cycle_edge="Cycle Time(us)", seeds=tuple(_seeds()))
