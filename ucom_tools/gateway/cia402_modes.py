"""The modes of operation of a joint's CiA 402 drive (:mod:`ucom_tools.gateway.cia402`):
what the axis is commanded in OPERATION ENABLED, and the statusword bits 10-13 each mode
sets.  IEC 61800-7-201 names in quotes; the armar3 program's Commands in capitals.

Every mode starts anew whenever it is entered (operation enabled, or another mode chosen
while enabled): from rest where the joint stands, no set-point, no homing under way.

Profile position (PP, 1): Command POSITION, Target = the set-point in force, clamped into
the software limits 0x607D and the Target edge's range ("internal limit active", bit 11,
while it is clamped).  The drive has no trajectory generator: the axis's own cascade runs
to the Target at most at its Max Velocity, which 0x6081 "profile velocity" [counts/s]
sets: ``Max Velocity (x1000)`` = 0x6081 / 1000 to the nearest integer, at least 1 for any
speed above 0, at most the edge's 32767 (:func:`max_velocity_raw`); the axis's limit is
then that x 1000 counts/s.  The gateway writes the PAR when the output changes; it is
the axis's one speed limit, in every mode (0x6081's default is the tree's value x 1000).

- "New set-point" (controlword bit 4) 0->1 offers 0x607A "target position": absolute, or
  with bit 6 "abs/rel" relative to the preceding set-point.  With bit 5 "change set
  immediately" it replaces the set-point in force at once ("single set-point"); without,
  it is taken at once when no positioning is under way, else kept in a buffer of one and
  taken when the target is reached ("set of set-points"); with the buffer full the
  drive does not take it until there is room (the master sees no acknowledge).
- "Set-point acknowledge" (bit 12) is 1 from the update that takes a set-point until
  bit 4 goes back to 0: the handshake ros2_canopen and canopen's users drive.
- "Target reached" (bit 10): the joint's position actual has stayed within 0x6067
  "position window" of the (clamped) set-point for 0x6068 "position window time" ms, and
  none waits in the buffer.  Bit 13 (following error) stays 0: without a trajectory there
  is no position demand to follow.

Profile velocity (PV, 3): Command VELOCITY, TargetVel = 0x60FF "target velocity" clamped
into the TargetVel edge's range (bit 11 while clamped, or while the joint stands at a
software limit in the direction asked: the program brakes into its Min/Max Position
itself).  Bit 10 "target reached": |velocity actual - target| <= 0x606D for 0x606E ms;
bit 12 "speed" (is zero): |velocity actual| <= 0x606F for 0x6070 ms; bit 13 (max
slippage) stays 0.

Homing (HM, 6): bit 4 "homing operation start" 0->1 starts the program's homing: Command
HOMING with Reset Offset = 0x607C "home offset" and Reset PWM = the tree's, signed as
0x6098 "homing method" asks: -1 (the default: the end stop Reset PWM's sign points to),
-3 / -4 (canopen's p402 names: on the negative / positive mechanical limit: Reset PWM's
magnitude towards it).  The axis drives at Reset PWM until it stalls at the end stop,
its joint counter then takes Reset Offset and it holds there while Command stays
HOMING.  Another method, a Reset PWM of 0 (an axis that cannot home) or a home offset
outside the Reset Offset edge's range refuse the start: "homing error" at once, the
axis holds.  Progress from the axis's Reset Answer (1 under way, 2 homed, -1 failed),
which it reports only every 100 cycles: a value that was there before the start counts
only once 1 was seen, or after :data:`HOMING_ANSWER_S`.  Bit 4 1->0 while under way,
halt, or another mode "interrupts" it (the axis leaves HOMING: its Reset Answer -1).
Statusword (bits 13, 12, 10): not started or interrupted 0 0 1; under way 0 0 0; homed
0 1 0, then 0 1 1 once the joint stayed within the position window of Reset Offset for
the window time; error 1 0 0 while the joint moves, 1 0 1 at standstill.  Once bit 4 is
0 again the axis leaves HOMING for POSITION where it stands (a new homing needs another
Command first: the armar3 program homes on entering HOMING).

Cyclic synchronous position (CSP, 8): Command POSITION; Target = 0x607A as it is at each
SYNC (:meth:`~ucom_tools.gateway.cia402.Drive402.on_sync`), clamped as in PP (bit 11);
until the first SYNC after the mode was entered the joint holds where it stood.  Bit 12
"drive follows the command value" from that SYNC on (0 while halted); bit 13 "following
error": |clamped target - position actual| > 0x6065 "following error window" for longer
than 0x6066 "following error time out" ms (0x6065 = 0xFFFFFFFF: off); bit 10 only halted
at standstill.

No mode yet (0x6061 = 0): the joint holds where it stood when enabled (POSITION).

Halt (controlword bit 8), in every mode: the axis brakes (:class:`Brake`: VELOCITY 0, the
program's velocity loop is the "slow down ramp") and, once |velocity actual| <=
:data:`STANDSTILL_VELOCITY`, holds where it stopped (POSITION); bit 10 "target reached"
from then on.  Releasing it resumes: PP towards its set-point, PV at 0x60FF, CSP at the
next SYNC (holding meanwhile), HM stays interrupted.  Quick stop brakes the same way.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Final, Protocol

from ucom_tools.edgelists.armar3 import Command
from ucom_tools.gateway.cia402_objects import (
    INT32_MAX,
    INT32_MIN,
    WINDOW_OFF,
    DriveConfig,
    JointReport,
    ObjectValues,
    OperationMode,
)

CW_NEW_SETPOINT: Final = 0x0010
"""Controlword bit 4: PP "new set-point", HM "homing operation start"."""
CW_CHANGE_IMMEDIATELY: Final = 0x0020
"""Controlword bit 5 (PP)."""
CW_RELATIVE: Final = 0x0040
"""Controlword bit 6 (PP): the target is relative."""
CW_HALT: Final = 0x0100
"""Controlword bit 8."""
SW_TARGET_REACHED: Final = 0x0400
SW_INTERNAL_LIMIT: Final = 0x0800
SW_MODE_12: Final = 0x1000
"""Statusword bit 12: PP set-point acknowledge, PV speed, HM homing attained, CSP drive
follows the command value."""
SW_MODE_13: Final = 0x2000
"""Statusword bit 13: CSP following error, HM homing error."""

STANDSTILL_VELOCITY: Final = 50
"""A braking joint stands still at this speed or below [counts/s] (the program's Settled
speed)."""
HOMING_ANSWER_S: Final = 0.3
"""How long a Reset Answer that was there before the start is not taken as the outcome
(three of its 100-cycle periods at 1 ms) [s]."""
_EPSILON_S: Final = 1e-9

UNDER_WAY: Final = 1
HOMED: Final = 2
FAILED: Final = -1
"""Values of the axis's Reset Answer (0: never homed)."""


@dataclass(frozen=True, slots=True)
class AxisCommand:
    """The axis's CI edges a mode sets: ``MotorX Command``, ``Target``, ``TargetVel``."""

    command: int
    target: int
    target_vel: int = 0


def holding(position: int) -> AxisCommand:
    """POSITION at ``position``."""
    return AxisCommand(Command.POSITION, position)


@dataclass(frozen=True, slots=True)
class Limits:
    """The positions a Target may take: 0x607D within the Target edge's range."""

    low: int
    high: int

    @classmethod
    def of(cls, objects: ObjectValues, config: DriveConfig) -> Limits:
        """0x607D ``min`` > ``max`` turns the software limits off (the edge's range
        only)."""
        low, high = config.target_range
        if objects.min_position_limit <= objects.max_position_limit:
            low = max(low, objects.min_position_limit)
            high = max(low, min(high, objects.max_position_limit))
        return cls(low, high)

    def clamp(self, value: int) -> tuple[int, bool]:
        """``value`` within the limits, and whether it had to be moved there."""
        if value < self.low:
            return self.low, True
        if value > self.high:
            return self.high, True
        return value, False


@dataclass(frozen=True, slots=True)
class Cycle:
    """One update of the drive as a mode sees it."""

    now: float
    objects: ObjectValues
    joint: JointReport
    rising: int
    """The controlword bits that went from 0 to 1 since the last update."""
    sync: bool
    """A SYNC came with this update."""
    limits: Limits
    config: DriveConfig

    def halted(self) -> bool:
        return bool(self.objects.controlword & CW_HALT)

    def hold_here(self) -> int:
        """The joint's position actual within the limits."""
        return self.limits.clamp(self.joint.position)[0]


@dataclass(frozen=True, slots=True)
class ModeResult:
    """What a mode gives for one update: the axis's command and statusword bits 10-13."""

    axis: AxisCommand
    bits: int = 0


class Dwell:
    """A condition that must hold for a time ("... for 0x6068 ms"): since when it holds."""

    __slots__ = ("since",)

    def __init__(self) -> None:
        self.since: float | None = None

    def holds(self, now: float, condition: bool, ms: int) -> bool:
        """Whether ``condition`` has held (at every update) for ``ms`` milliseconds."""
        if not condition:
            self.since = None
            return False
        if self.since is None:
            self.since = now
        return now - self.since >= ms / 1000 - _EPSILON_S

    def reset(self) -> None:
        self.since = None


class Brake:
    """Halt and quick stop: VELOCITY 0 until the joint stands still, then POSITION where
    it stopped."""

    __slots__ = ("hold",)

    def __init__(self) -> None:
        self.hold: int | None = None

    @property
    def standstill(self) -> bool:
        return self.hold is not None

    def step(self, c: Cycle) -> AxisCommand:
        joint = c.joint
        if self.hold is None and joint.valid and abs(joint.velocity) <= STANDSTILL_VELOCITY:
            self.hold = c.hold_here()
        if self.hold is None:
            return AxisCommand(Command.VELOCITY, c.hold_here(), 0)
        return holding(self.hold)


class Mode(Protocol):
    """One mode of operation while OPERATION ENABLED (made anew on entering it)."""

    def step(self, c: Cycle) -> ModeResult:
        """The axis's command and the statusword bits of this update."""


def _in_window(c: Cycle, goal: int) -> bool:
    window = c.objects.position_window
    return c.joint.valid and (window == WINDOW_OFF or abs(c.joint.position - goal) <= window)


class HoldMode:
    """No mode chosen yet: hold where the joint stood when enabled."""

    def __init__(self, c: Cycle) -> None:
        self.hold = c.hold_here()
        self.brake: Brake | None = None

    def step(self, c: Cycle) -> ModeResult:
        if c.halted():
            self.brake = self.brake or Brake()
            axis = self.brake.step(c)
            return ModeResult(axis, SW_TARGET_REACHED if self.brake.standstill else 0)
        if self.brake is not None:
            self.hold, self.brake = self.brake.hold or c.hold_here(), None
        return ModeResult(holding(self.hold))


class ProfilePosition:
    """PP: the set-point handshake, a buffer of one, target reached by window and time."""

    def __init__(self, c: Cycle) -> None:
        self.target = c.hold_here()
        """The set-point in force (as given: INTEGER32)."""
        self.pending: int | None = None
        self.moving = False
        """A positioning is under way: a set-point taken whose target is not reached."""
        self.request = False
        """Bit 4 rose and its set-point is not taken yet."""
        self.ack = False
        self.done = Dwell()
        self.brake: Brake | None = None

    def step(self, c: Cycle) -> ModeResult:
        cw = c.objects.controlword
        if c.rising & CW_NEW_SETPOINT:
            self.request = True
        if not cw & CW_NEW_SETPOINT:
            self.request = self.ack = False
        halted = c.halted()
        reached = not halted and self.done.holds(
            c.now, _in_window(c, c.limits.clamp(self.target)[0]),
            c.objects.position_window_time)
        if halted:
            self.done.reset()
        if reached:
            self.moving = False
        if self.pending is not None and not self.moving:
            self._begin(self.pending)
        if self.request and not self.ack:
            self._take(c.objects)
        reached = reached and not self.moving
        goal, limited = c.limits.clamp(self.target)
        bits = (SW_MODE_12 if self.ack else 0) | (SW_INTERNAL_LIMIT if limited else 0)
        if halted:
            self.brake = self.brake or Brake()
            axis = self.brake.step(c)
            return ModeResult(axis, bits | (SW_TARGET_REACHED if self.brake.standstill else 0))
        self.brake = None
        return ModeResult(holding(goal), bits | (SW_TARGET_REACHED if reached else 0))

    def _begin(self, target: int) -> None:
        self.target, self.pending, self.moving = target, None, True
        self.done.reset()

    def _take(self, objects: ObjectValues) -> None:
        """Take the offered set-point if there is room (else it waits: no acknowledge)."""
        value = objects.target_position
        if objects.controlword & CW_RELATIVE:
            base = self.target if self.pending is None else self.pending
            value = min(INT32_MAX, max(INT32_MIN, base + value))
        if objects.controlword & CW_CHANGE_IMMEDIATELY or not self.moving:
            self._begin(value)
        elif self.pending is None:
            self.pending = value
        else:
            return  # the buffer is full
        self.ack, self.request = True, False


class ProfileVelocity:
    """PV: TargetVel = 0x60FF; target reached and speed by window and time."""

    def __init__(self, c: Cycle) -> None:
        self.reached = Dwell()
        self.still = Dwell()
        self.brake: Brake | None = None

    def step(self, c: Cycle) -> ModeResult:
        objects, joint = c.objects, c.joint
        low, high = c.config.target_vel_range
        velocity = min(high, max(low, objects.target_velocity))
        limited = velocity != objects.target_velocity or (
            joint.valid and ((velocity > 0 and joint.position >= c.limits.high)
                             or (velocity < 0 and joint.position <= c.limits.low)))
        still = self.still.holds(c.now, joint.valid and abs(joint.velocity) <=
                                 objects.velocity_threshold, objects.velocity_threshold_time)
        bits = (SW_MODE_12 if still else 0) | (SW_INTERNAL_LIMIT if limited else 0)
        if c.halted():
            self.reached.reset()
            self.brake = self.brake or Brake()
            axis = self.brake.step(c)
            return ModeResult(axis, bits | (SW_TARGET_REACHED if self.brake.standstill else 0))
        self.brake = None
        if self.reached.holds(c.now, joint.valid and abs(joint.velocity - velocity) <=
                              objects.velocity_window, objects.velocity_window_time):
            bits |= SW_TARGET_REACHED
        return ModeResult(AxisCommand(Command.VELOCITY, c.hold_here(), velocity), bits)


class CyclicPosition:
    """CSP: Target = 0x607A at every SYNC; following error by window and time."""

    def __init__(self, c: Cycle) -> None:
        self.target = c.hold_here()
        self.following = False
        self.lag = Dwell()
        self.brake: Brake | None = None

    def step(self, c: Cycle) -> ModeResult:
        objects = c.objects
        if c.halted():
            self.following = False
            self.lag.reset()
            self.brake = self.brake or Brake()
            axis = self.brake.step(c)
            return ModeResult(axis, SW_TARGET_REACHED if self.brake.standstill else 0)
        if self.brake is not None:
            self.target, self.brake = self.brake.hold or c.hold_here(), None
        if c.sync:
            self.target, self.following = objects.target_position, True
        goal, limited = c.limits.clamp(self.target)
        bits = (SW_MODE_12 if self.following else 0) | (SW_INTERNAL_LIMIT if limited else 0)
        window = objects.following_error_window
        lagging = window != WINDOW_OFF and c.joint.valid and abs(goal - c.joint.position) > window
        if self.lag.holds(c.now, lagging, objects.following_error_time_out):
            bits |= SW_MODE_13
        return ModeResult(holding(goal), bits)


class _Phase(Enum):
    NOT_STARTED = "not started"
    RUNNING = "under way"
    HOMED = "homed"
    FAILED = "failed"
    REFUSED = "refused"
    INTERRUPTED = "interrupted"


def reset_pwm_for(method: int, reset_pwm: int) -> int | None:
    """The Reset PWM homing method ``method`` asks of an axis whose tree gives
    ``reset_pwm``; None for a method the drive does not have."""
    if method == -1:
        return reset_pwm
    if method == -3:
        return -abs(reset_pwm)
    if method == -4:
        return abs(reset_pwm)
    return None


class Homing:
    """HM: the program's HOMING started by bit 4, followed by its Reset Answer."""

    def __init__(self, c: Cycle) -> None:
        self.phase = _Phase.NOT_STARTED
        self.hold = c.hold_here()
        self.homing = False
        """Command HOMING is out."""
        self.started_s = 0.0
        self.answer_before = 0
        self.seen_under_way = False
        self.offset = 0
        self.done = Dwell()
        self.completed = False
        self.brake: Brake | None = None

    def step(self, c: Cycle) -> ModeResult:
        cw = c.objects.controlword
        halted = c.halted()
        if c.rising & CW_NEW_SETPOINT and not halted:
            self._start(c)
        elif self.phase is _Phase.RUNNING and (halted or not cw & CW_NEW_SETPOINT):
            self.phase = _Phase.INTERRUPTED
        if self.phase is _Phase.RUNNING:
            self._follow(c)
        if self.phase is _Phase.HOMED and not self.completed:
            self.completed = self.done.holds(c.now, _in_window(c, self.offset),
                                             c.objects.position_window_time)
        return ModeResult(self._axis(c, halted), self._bits(c))

    def _axis(self, c: Cycle, halted: bool) -> AxisCommand:
        homing = (not halted and bool(c.objects.controlword & CW_NEW_SETPOINT)
                  and self.phase in (_Phase.RUNNING, _Phase.HOMED, _Phase.FAILED))
        if halted:
            self.homing = False
            self.brake = self.brake or Brake()
            return self.brake.step(c)
        if self.brake is not None:
            self.hold, self.brake = self.brake.hold or c.hold_here(), None
        if homing:
            self.homing = True
            return AxisCommand(Command.HOMING, c.hold_here())
        if self.homing:  # leaving HOMING: hold where it stands now
            self.homing, self.hold = False, c.hold_here()
        return holding(self.hold)

    def _bits(self, c: Cycle) -> int:
        phase = self.phase
        if phase is _Phase.RUNNING:
            return 0
        if phase is _Phase.HOMED:
            return SW_MODE_12 | (SW_TARGET_REACHED if self.completed else 0)
        if phase in (_Phase.FAILED, _Phase.REFUSED):
            still = c.joint.valid and abs(c.joint.velocity) <= STANDSTILL_VELOCITY
            return SW_MODE_13 | (SW_TARGET_REACHED if still else 0)
        return SW_TARGET_REACHED  # not started, or interrupted

    def _start(self, c: Cycle) -> None:
        objects, config = c.objects, c.config
        pwm = reset_pwm_for(objects.homing_method, config.reset_pwm)
        low, high = config.reset_offset_range
        if not pwm or not low <= objects.home_offset <= high:
            self.phase = _Phase.REFUSED
            return
        self.phase = _Phase.RUNNING
        self.started_s, self.answer_before = c.now, c.joint.reset_answer
        self.seen_under_way, self.completed = False, False
        self.offset = objects.home_offset
        self.done.reset()

    def _follow(self, c: Cycle) -> None:
        """The outcome from the axis's Reset Answer, once it is the run's own."""
        answer = c.joint.reset_answer
        if not c.joint.valid:
            return
        if answer == UNDER_WAY:
            self.seen_under_way = True
            return
        late = c.now - self.started_s >= HOMING_ANSWER_S - _EPSILON_S
        fresh = self.seen_under_way or answer != self.answer_before or late
        if answer == HOMED and fresh:
            self.phase = _Phase.HOMED
        elif (answer == FAILED and fresh) or late:
            self.phase = _Phase.FAILED


def make_mode(mode: int, c: Cycle) -> Mode:
    """The mode ``mode`` (0x6061), entered now."""
    if mode == OperationMode.PROFILE_POSITION:
        return ProfilePosition(c)
    if mode == OperationMode.PROFILE_VELOCITY:
        return ProfileVelocity(c)
    if mode == OperationMode.HOMING:
        return Homing(c)
    if mode == OperationMode.CYCLIC_SYNCHRONOUS_POSITION:
        return CyclicPosition(c)
    return HoldMode(c)


def max_velocity_raw(profile_velocity: int, config: DriveConfig) -> int:
    """``Max Velocity (x1000)`` for 0x6081 ``profile_velocity`` [counts/s]: to the nearest
    1000 counts/s, at least 1 (1000 counts/s) for any speed above 0, 0 for 0; within the
    edge's range."""
    if profile_velocity <= 0:
        raw = 0
    else:
        raw = max(1, (profile_velocity + 500) // 1000)
    low, high = config.max_velocity_range
    return min(high, max(low, raw))
