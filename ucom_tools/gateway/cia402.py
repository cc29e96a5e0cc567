"""The CiA 402 drive of one UCoM joint: a pure state machine (no I/O, no threads, no
clock: time is passed in, in seconds).

The gateway drives it once per cycle and on every write of one of its objects
(:meth:`Drive402.update`), and at every SYNC (:meth:`Drive402.on_sync`).  Each call takes
what the master wrote (:class:`~ucom_tools.gateway.cia402_objects.ObjectValues`), what
the joint reports (:class:`~ucom_tools.gateway.cia402_objects.JointReport`) and the
causes of FAULT present now (:class:`~ucom_tools.gateway.cia402_objects.DriveFault`), and
gives (:class:`~ucom_tools.gateway.cia402_objects.DriveOutputs`) 0x6041 statusword, 0x6061
modes of operation display, 0x603F error code, 0x1001 error register, the EMCYs to send
and the axis's edges of the armar3 program: ``Command``, ``Target``, ``TargetVel``,
``Reset Offset`` (CI) and ``Reset X PWM``, ``Max Velocity (x1000)`` (PAR), raw.  The
modes of operation are :mod:`ucom_tools.gateway.cia402_modes` (its docstring has their
rules).  Names in quotes are IEC 61800-7-201's (CiA 402-2).

State machine ("power drive system", 6.3.1): the states NOT READY TO SWITCH ON, SWITCH
ON DISABLED, READY TO SWITCH ON, SWITCHED ON, OPERATION ENABLED, QUICK STOP ACTIVE,
FAULT REACTION ACTIVE, FAULT.  Controlword commands (bits 7, 3, 2, 1, 0; x: any):
"shutdown" 0 x 1 1 0, "switch on" / "disable operation" 0 0 1 1 1, "enable operation" /
"switch on + enable operation" 0 1 1 1 1, "disable voltage" 0 x x 0 x, "quick stop"
0 x 0 1 x, "fault reset" bit 7 0->1.  With bit 7 set no other command acts.

====  ======================================  ============================================
 #    from -> to                              when
====  ======================================  ============================================
 0    start -> NOT READY TO SWITCH ON         the first update
 1    NOT READY -> SWITCH ON DISABLED         the joint's values are valid (its board runs)
 2    SWITCH ON DISABLED -> READY             shutdown
 3    READY -> SWITCHED ON                    switch on (switch on + enable operation:
                                              3 then 4 in one update)
 4    SWITCHED ON -> OPERATION ENABLED        enable operation, the joint's values valid
 5    OPERATION ENABLED -> SWITCHED ON        disable operation
 6    SWITCHED ON -> READY                    shutdown
 7    READY -> SWITCH ON DISABLED             disable voltage or quick stop
 8    OPERATION ENABLED -> READY              shutdown
 9    OPERATION ENABLED -> SWITCH ON DISABLED disable voltage
10    SWITCHED ON -> SWITCH ON DISABLED       disable voltage or quick stop
11    OPERATION ENABLED -> QUICK STOP ACTIVE  quick stop
12    QUICK STOP ACTIVE -> SWITCH ON DISABLED disable voltage; or the quick stop is
                                              complete with 0x605A 0-4
13    any -> FAULT REACTION ACTIVE            a fault cause is present
14    FAULT REACTION ACTIVE -> FAULT          the next update (the reaction went out)
15    FAULT -> SWITCH ON DISABLED             fault reset, no fault cause present
16    QUICK STOP ACTIVE -> OPERATION ENABLED  enable operation, 0x605A 5-8
====  ======================================  ============================================

The axis: in every state but OPERATION ENABLED and QUICK STOP ACTIVE its Command is OFF
(motor off, Target = position actual, TargetVel 0); in OPERATION ENABLED the mode's
(0x6061).  "Quick stop option code" 0x605A: 0 "disable drive function" (OFF at once,
transitions 11 and 12 in one update); 1-4 "slow down ... and transit into SWITCH ON
DISABLED": the axis brakes (:class:`~ucom_tools.gateway.cia402_modes.Brake`: VELOCITY 0,
then POSITION where it stopped), at standstill transition 12 (OFF; at the earliest in
the update after 11, so that the master sees QUICK STOP ACTIVE); 5-8 "slow down ...
and stay in QUICK STOP ACTIVE": the axis brakes and holds; any other value as 2.  The
UCoM has one ramp, its velocity loop: the ramps' objects are not used.  The "fault
reaction" is OFF (0x605E 0, "disable drive, motor is free to rotate").
:meth:`Drive402.disable_voltage` is the device's own "disable voltage" (the gateway's
answer to NMT stop); a reset node or reset communication makes a new drive.

Modes of operation: 0x6060 takes effect in the next update, in every state, when it is
a supported mode (0x6502 = PP | PV | HM | CSP, 0xA5); another value leaves 0x6061 as it
is.  0x6061 starts at 0 (no mode).  A mode chosen while OPERATION ENABLED is entered at
once, from rest where the joint stands (a homing under way is interrupted).

Statusword 0x6041: bits 0-3, 5, 6 by state ("ready to switch on", "switched on",
"operation enabled", "fault", "quick stop" (0 = active), "switch on disabled"):
0x0000 not ready, 0x0040 switch on disabled, 0x0021 ready, 0x0023 switched on, 0x0027
operation enabled, 0x0007 quick stop active, 0x000F fault reaction active, 0x0008
fault.  Bit 4 "voltage enabled": the joint's values are valid (its board is powered
and runs).  Bit 7 "warning": 0.  Bit 9 "remote": 1 (the controlword is processed).
Bits 10, 12, 13 by mode in OPERATION ENABLED (0 elsewhere).  Bit 11 "internal limit
active": the mode clamped its target (software limits 0x607D), or the joint stands
outside 0x607D.

Faults: a cause present (:class:`~ucom_tools.gateway.cia402_objects.DriveFault`, passed in as
long as it lasts; an event such as the board's Error once) takes any state to FAULT
REACTION ACTIVE (13) and the next update to FAULT (14); FAULT holds until "fault reset"
(0->1 of bit 7) comes while no cause is present (15; a fault reset while one is
present is refused: a new 0->1 is needed).  Each cause newly present sends its EMCY
(also while in FAULT) and sets 0x603F and 0x1001; the fault reset clears both and sends
the EMCY "error reset" (code 0x0000).  EMCY: bytes 0-1 the code, byte 2 0x1001, byte 3
the cause's number, bytes 4-7 its detail (UNSIGNED32, little-endian):

=====================  =======  ======  ==============================================
cause (number)         code     0x1001  meaning
=====================  =======  ======  ==============================================
MASTER_HEARTBEAT (1)   0x8130   0x11    CiA 301 "life guard error or heartbeat error":
                                        the master's heartbeat (0x1016) not heard
SYNC_TIMEOUT (2)       0x8100   0x11    CiA 301 "communication, generic": no SYNC
                                        within the SYNC timeout
BUS_OFF (3)            0x8140   0x11    CiA 301 "recovered from bus off" (CANopen side)
BOARD_LOST (4)         0xFF01   0x81    the joint's UCoM board is lost (silent)
BOARD_LATCHED (5)      0xFF02   0x81    its watchdog latched: motors off until started
BOARD_ERROR (6)        0xFF80   0x81    it sent an Error: the code's low byte is the
                       + code           Error's code (0xFF90: WATCHDOG, 0x10)
=====================  =======  ======  ==============================================
"""

from __future__ import annotations

from collections.abc import Iterable
from enum import Enum
from typing import Final

from ucom_tools.edgelists.armar3 import Command
from ucom_tools.gateway.cia402_modes import (
    SW_INTERNAL_LIMIT,
    AxisCommand,
    Brake,
    Cycle,
    Limits,
    Mode,
    make_mode,
    max_velocity_raw,
    reset_pwm_for,
)
from ucom_tools.gateway.cia402_objects import (
    ERROR_RESET,
    DriveConfig,
    DriveFault,
    DriveOutputs,
    Emcy,
    JointReport,
    ObjectValues,
    OperationMode,
    State402,
)

S = State402
CW_FAULT_RESET: Final = 0x0080
SW_VOLTAGE_ENABLED: Final = 0x0010
SW_REMOTE: Final = 0x0200
STATE_BITS: Final = {
    S.NOT_READY_TO_SWITCH_ON: 0x0000, S.SWITCH_ON_DISABLED: 0x0040,
    S.READY_TO_SWITCH_ON: 0x0021, S.SWITCHED_ON: 0x0023, S.OPERATION_ENABLED: 0x0027,
    S.QUICK_STOP_ACTIVE: 0x0007, S.FAULT_REACTION_ACTIVE: 0x000F, S.FAULT: 0x0008,
}
"""Statusword bits 0-3, 5, 6 of each state."""
MODES: Final = frozenset({OperationMode.PROFILE_POSITION, OperationMode.PROFILE_VELOCITY,
                          OperationMode.HOMING, OperationMode.CYCLIC_SYNCHRONOUS_POSITION})


class DeviceCommand(Enum):
    """The device control commands of the controlword (bits 7, 3, 2, 1, 0)."""

    SHUTDOWN = "shutdown"
    SWITCH_ON = "switch on"
    """Also "disable operation" (the same pattern)."""
    ENABLE_OPERATION = "enable operation"
    """Also "switch on + enable operation"."""
    DISABLE_VOLTAGE = "disable voltage"
    QUICK_STOP = "quick stop"


def device_command(controlword: int) -> DeviceCommand | None:
    """The command a controlword gives (None: bit 7 is set, only a fault reset)."""
    if controlword & CW_FAULT_RESET:
        return None
    if not controlword & 0x02:
        return DeviceCommand.DISABLE_VOLTAGE
    if not controlword & 0x04:
        return DeviceCommand.QUICK_STOP
    if not controlword & 0x01:
        return DeviceCommand.SHUTDOWN
    if not controlword & 0x08:
        return DeviceCommand.SWITCH_ON
    return DeviceCommand.ENABLE_OPERATION


C = DeviceCommand
TRANSITIONS: Final[dict[tuple[State402, DeviceCommand], tuple[int, ...]]] = {
    (S.SWITCH_ON_DISABLED, C.SHUTDOWN): (2,),
    (S.READY_TO_SWITCH_ON, C.SWITCH_ON): (3,),
    (S.READY_TO_SWITCH_ON, C.ENABLE_OPERATION): (3, 4),
    (S.READY_TO_SWITCH_ON, C.DISABLE_VOLTAGE): (7,),
    (S.READY_TO_SWITCH_ON, C.QUICK_STOP): (7,),
    (S.SWITCHED_ON, C.ENABLE_OPERATION): (4,),
    (S.SWITCHED_ON, C.SHUTDOWN): (6,),
    (S.SWITCHED_ON, C.DISABLE_VOLTAGE): (10,),
    (S.SWITCHED_ON, C.QUICK_STOP): (10,),
    (S.OPERATION_ENABLED, C.SWITCH_ON): (5,),
    (S.OPERATION_ENABLED, C.SHUTDOWN): (8,),
    (S.OPERATION_ENABLED, C.DISABLE_VOLTAGE): (9,),
    (S.OPERATION_ENABLED, C.QUICK_STOP): (11,),
    (S.QUICK_STOP_ACTIVE, C.DISABLE_VOLTAGE): (12,),
    (S.QUICK_STOP_ACTIVE, C.ENABLE_OPERATION): (16,),
}
"""The transitions each command takes from each state (the rest: none)."""
ENDS: Final = {0: S.NOT_READY_TO_SWITCH_ON, 1: S.SWITCH_ON_DISABLED,
               2: S.READY_TO_SWITCH_ON, 3: S.SWITCHED_ON, 4: S.OPERATION_ENABLED,
               5: S.SWITCHED_ON, 6: S.READY_TO_SWITCH_ON, 7: S.SWITCH_ON_DISABLED,
               8: S.READY_TO_SWITCH_ON, 9: S.SWITCH_ON_DISABLED, 10: S.SWITCH_ON_DISABLED,
               11: S.QUICK_STOP_ACTIVE, 12: S.SWITCH_ON_DISABLED,
               13: S.FAULT_REACTION_ACTIVE, 14: S.FAULT, 15: S.SWITCH_ON_DISABLED,
               16: S.OPERATION_ENABLED}
"""The state each transition ends in."""
_FAULT_STATES: Final = (S.FAULT_REACTION_ACTIVE, S.FAULT)


def quick_stop_kind(option: int) -> int:
    """0x605A as the drive takes it: 0 (off at once), 2 (brake, then SWITCH ON
    DISABLED) or 6 (brake and stay); 1-4 act as 2, 5-8 as 6, any other value as 2."""
    if option == 0:
        return 0
    return 6 if 5 <= option <= 8 else 2


class Drive402:
    """One joint's CiA 402 drive (see the module docstring)."""

    def __init__(self, config: DriveConfig | None = None) -> None:
        self.config = config or DriveConfig()
        """The joint's settings (may be replaced between updates, e.g. when the tree's
        Reset PWM changed)."""
        self._state = S.NOT_READY_TO_SWITCH_ON
        self._started = False
        self._mode_display = int(OperationMode.NO_MODE)
        self._mode: Mode | None = None
        self._brake: Brake | None = None
        self._controlword = 0
        self._causes: frozenset[DriveFault] = frozenset()
        self._error: DriveFault | None = None
        self._disable = False

    @property
    def state(self) -> State402:
        return self._state

    @property
    def mode_display(self) -> int:
        return self._mode_display

    def disable_voltage(self) -> None:
        """The device's own "disable voltage" at the next update (NMT stop): transitions
        7, 9, 10 or 12 as the controlword's would take them."""
        self._disable = True

    def on_sync(self, now: float, objects: ObjectValues, joint: JointReport,
                faults: Iterable[DriveFault] = ()) -> DriveOutputs:
        """An update at a SYNC: CSP takes 0x607A."""
        return self.update(now, objects, joint, faults, sync=True)

    def update(self, now: float, objects: ObjectValues, joint: JointReport,
               faults: Iterable[DriveFault] = (), *, sync: bool = False) -> DriveOutputs:
        """One update at time ``now`` [s]; ``faults``: the causes present now."""
        rising = objects.controlword & ~self._controlword & 0xFFFF
        self._controlword = objects.controlword
        c = Cycle(now, objects, joint, rising, sync, Limits.of(objects, self.config),
                  self.config)
        steps: list[int] = []
        if not self._started:
            self._started = True
            steps.append(0)
        emcys = self._faults(c, tuple(dict.fromkeys(faults)), steps)
        self._select_mode(c)
        forced, self._disable = self._disable, False
        if self._state not in _FAULT_STATES:
            self._device_control(c, steps, forced)
        axis, bits = self._axis(c, steps)
        return self._outputs(c, axis, bits, emcys, steps)

    def _go(self, transitions: Iterable[int], steps: list[int]) -> None:
        for t in transitions:
            self._state = ENDS[t]
            steps.append(t)

    def _faults(self, c: Cycle, faults: tuple[DriveFault, ...], steps: list[int]) -> list[Emcy]:
        """Transitions 13, 14 and 15, and the EMCYs of the causes newly present."""
        emcys = []
        if self._state is S.FAULT_REACTION_ACTIVE:
            self._go((14,), steps)
        for fault in faults:
            if fault not in self._causes:
                emcys.append(fault.emcy())
                self._error = fault
        self._causes = frozenset(faults)
        if faults and self._state not in _FAULT_STATES:
            self._go((13,), steps)
            self._mode = self._brake = None
        elif self._state is S.FAULT and c.rising & CW_FAULT_RESET and not faults:
            self._go((15,), steps)
            self._error = None
            emcys.append(ERROR_RESET)
        return emcys

    def _select_mode(self, c: Cycle) -> None:
        asked = c.objects.modes_of_operation
        if asked == self._mode_display or asked not in MODES:
            return
        self._mode_display = asked
        if self._state is S.OPERATION_ENABLED:
            self._mode = make_mode(asked, c)

    def _device_control(self, c: Cycle, steps: list[int], forced: bool) -> None:
        """Transitions 1-12 and 16 by the controlword's command (``forced``: by disable
        voltage, :meth:`disable_voltage`)."""
        state = self._state
        if state is S.NOT_READY_TO_SWITCH_ON:
            if c.joint.valid:
                self._go((1,), steps)
            return
        command = (DeviceCommand.DISABLE_VOLTAGE if forced
                   else device_command(c.objects.controlword))
        if command is None:
            return
        transitions = TRANSITIONS.get((state, command), ())
        if 4 in transitions or 16 in transitions:
            if 16 in transitions and quick_stop_kind(c.objects.quick_stop_option) != 6:
                return
            if not c.joint.valid:  # nothing to hold: stay below OPERATION ENABLED
                transitions = transitions[:-1]
        self._go(transitions, steps)
        if self._state is S.OPERATION_ENABLED and state is not S.OPERATION_ENABLED:
            self._mode = make_mode(self._mode_display, c)
        elif self._state is not S.OPERATION_ENABLED:
            self._mode = None
        if self._state is S.QUICK_STOP_ACTIVE and state is not S.QUICK_STOP_ACTIVE:
            self._brake = Brake()
            if quick_stop_kind(c.objects.quick_stop_option) == 0:
                self._go((12,), steps)
        if self._state is not S.QUICK_STOP_ACTIVE:
            self._brake = None

    def _axis(self, c: Cycle, steps: list[int]) -> tuple[AxisCommand, int]:
        """The axis's command and the mode's statusword bits (10-13) in this state."""
        off = AxisCommand(Command.OFF, c.hold_here())
        if self._state is S.OPERATION_ENABLED and self._mode is not None:
            result = self._mode.step(c)
            return result.axis, result.bits
        if self._state is S.QUICK_STOP_ACTIVE and self._brake is not None:
            axis = self._brake.step(c)
            if self._brake.standstill and 11 not in steps \
                    and quick_stop_kind(c.objects.quick_stop_option) == 2:
                self._go((12,), steps)
                self._brake = None
                return off, 0
            return axis, 0
        return off, 0

    def _outputs(self, c: Cycle, axis: AxisCommand, bits: int, emcys: list[Emcy],
                 steps: list[int]) -> DriveOutputs:
        joint, objects, config = c.joint, c.objects, c.config
        status = STATE_BITS[self._state] | SW_REMOTE | bits
        if joint.valid:
            status |= SW_VOLTAGE_ENABLED
            if not objects.min_position_limit <= joint.position <= objects.max_position_limit \
                    and objects.min_position_limit <= objects.max_position_limit:
                status |= SW_INTERNAL_LIMIT
        fault = self._error if self._state in _FAULT_STATES else None
        pwm = reset_pwm_for(objects.homing_method, config.reset_pwm)
        low, high = config.reset_pwm_range
        offset_low, offset_high = config.reset_offset_range
        return DriveOutputs(
            state=self._state, statusword=status, mode_display=self._mode_display,
            error_code=fault.error_code if fault else 0,
            error_register=fault.error_register if fault else 0,
            emcys=tuple(emcys), transitions=tuple(steps),
            command=axis.command, target=axis.target, target_vel=axis.target_vel,
            reset_offset=min(offset_high, max(offset_low, objects.home_offset)),
            reset_pwm=min(high, max(low, config.reset_pwm if pwm is None else pwm)),
            max_velocity=max_velocity_raw(objects.profile_velocity, config))
