"""``armar3.fl.S``: the generic program of every ARMAR-III UCoM (dissertation 5.2.2, B.5).

Three axes (Motor A/B/C), each a cascaded position-velocity controller.  The edges are
exactly those of the B.5 attribute tree, in its order: CI 0-12, SO 13-32, PAR 33-70.  Their
encodings, ranges and units are ours (``man/ucom-protocol.7``, RUN TIME, The armar3
program); every value of the B.5 tree travels exactly.

Units: positions in encoder counts of the joint sensor; velocities in counts per second;
PWM in 1/16000 of the supply (16000 = 100 %); gains as plain numbers with six decimals.
"""

from __future__ import annotations

from ucom_tools.edgelists.model import CiSeed, EdgeKind, EdgeSpec, ProgramSpec, Seed

NAME = "armar3 cascaded PID"
AXES = "ABC"
PWM_FULL = 16000

CI, SO, PAR = EdgeKind.CI, EdgeKind.SO, EdgeKind.PAR


class Command:
    """Values of ``MotorX Command`` (0 is the B.5 default: position control)."""

    POSITION = 0
    """Position control towards Target (clamped to [Min, Max Position])."""
    VELOCITY = 1
    """Velocity control at TargetVel (counts/s), within Max Velocity and the limits."""
    HOMING = 2
    """Drive at Reset PWM until the end stop; the counter then takes Reset Offset."""
    OFF = 3
    """Controller off, PWM 0."""


def _ci() -> list[EdgeSpec]:
    edges = [EdgeSpec(CI, f"Motor{a} Command", minimum=0, maximum=3, axis=k)
             for k, a in enumerate(AXES)]
    edges += [EdgeSpec(CI, f"Motor{a} Target", unit="counts", period=1, axis=k)
              for k, a in enumerate(AXES)]
    edges += [EdgeSpec(CI, f"Motor{a} Reset Offset", unit="counts", axis=k)
              for k, a in enumerate(AXES)]
    edges.append(EdgeSpec(CI, "Send Command via serial", signed=False, minimum=0,
                          maximum=0xFFFF))
    edges += [EdgeSpec(CI, f"Motor{a} TargetVel", unit="counts/s", axis=k)
              for k, a in enumerate(AXES)]
    return edges


def _so() -> list[EdgeSpec]:
    # joint position and velocity every cycle, the rest at 1/100 (10 Hz at 1 ms)
    axes = list(enumerate(AXES))
    edges = [EdgeSpec(SO, f"Encoder {i}", unit="counts", period=100 if i % 2 else 1,
                      axis=i // 2) for i in range(6)]
    edges += [EdgeSpec(SO, f"Voltage {a}", exponent=-3, minimum=0, maximum=3300, unit="V",
                       period=100, axis=k) for k, a in axes]
    edges += [EdgeSpec(SO, f"AD Channel {i}", signed=False, minimum=0, maximum=4095,
                       unit="counts", period=100) for i in (6, 7)]
    edges += [EdgeSpec(SO, f"Motor{a} Reset Answer", minimum=-1, maximum=2, period=100,
                       axis=k) for k, a in axes]
    edges += [EdgeSpec(SO, f"Velocity {a}", unit="counts/s", period=1, axis=k)
              for k, a in axes]
    edges += [EdgeSpec(SO, f"Motor {a} Settled", signed=False, minimum=0, maximum=1,
                       period=100, axis=k) for k, a in axes]
    return edges


def _gain(name: str, axis: int) -> EdgeSpec:
    return EdgeSpec(PAR, name, width=4, exponent=-6, minimum=-1_000_000_000,
                    maximum=1_000_000_000, axis=axis)


def _par() -> list[EdgeSpec]:
    edges = [
        EdgeSpec(PAR, "LoopTime(ms)", exponent=-3, minimum=100, maximum=32000, unit="ms",
                 default=1000),
        EdgeSpec(PAR, "Max PWM", minimum=0, maximum=PWM_FULL, unit="1/16000",
                 default=PWM_FULL),
        EdgeSpec(PAR, "Revert Encoder CountDir(BitMask)", signed=False, minimum=0,
                 maximum=0x3F),
        EdgeSpec(PAR, "Set Joint Moving Direction(BitMask)", signed=False, minimum=0,
                 maximum=0x7),
        EdgeSpec(PAR, "Encoder Prescaler(BitMask)", signed=False, minimum=0, maximum=0xFFF,
                 default=0x111),
    ]
    axes = list(enumerate(AXES))
    for k, a in axes:
        edges += [_gain(f"Motor{a} P", k), _gain(f"Motor{a} I", k), _gain(f"Motor{a} D", k)]
    edges += [EdgeSpec(PAR, f"Reset {a} PWM", minimum=-PWM_FULL, maximum=PWM_FULL,
                       unit="1/16000", axis=k) for k, a in axes]
    edges += [_gain(f"Motor{a} feedforward gain", k) for k, a in axes]
    for k, a in axes:
        edges += [_gain(f"Motor{a} Velocity P", k), _gain(f"Motor{a} Velocity I", k),
                  _gain(f"Motor{a} Velocity D", k),
                  EdgeSpec(PAR, f"Motor{a} Max Velocity (x1000)", minimum=0,
                           unit="1000 counts/s", axis=k)]
    for k, a in axes:
        edges += [EdgeSpec(PAR, f"Motor{a} Max Position", unit="counts", default=32767,
                           axis=k),
                  EdgeSpec(PAR, f"Motor{a} Min Position", unit="counts", default=-32768,
                           axis=k)]
    return edges


def _seeds() -> list[CiSeed]:
    """A rejoining board holds each joint where it stands: the target is its joint sensor
    (counter 2k of axis k), the velocity target 0, a homing command becomes position
    control (not resumed); the other CIs keep the PC's values."""
    out = []
    for k, a in enumerate(AXES):
        out += [CiSeed(f"Motor{a} Target", Seed.SENSOR, sensor=f"Encoder {2 * k}"),
                CiSeed(f"Motor{a} TargetVel", Seed.ZERO),
                CiSeed(f"Motor{a} Command", Seed.KEEP,
                       replace=((Command.HOMING, Command.POSITION),))]
    return out


SPEC = ProgramSpec(NAME, "ARMAR-III cascaded position-velocity control, 3 axes",
                   tuple(_ci() + _so() + _par()),
                   cycle_edge="LoopTime(ms)", seeds=tuple(_seeds()))
