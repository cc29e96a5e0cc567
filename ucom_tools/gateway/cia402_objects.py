"""What a CiA 402 drive of one UCoM joint (:mod:`ucom_tools.gateway.cia402`) takes and gives,
in raw integers as the CANopen objects and the armar3 program's edges carry them.

Inputs: :class:`ObjectValues` (the 402 objects the master writes), :class:`JointReport`
(what the joint's board reports), :class:`DriveFault` (a cause of FAULT now present), and the
joint's fixed settings :class:`DriveConfig` (the edges' ranges and the tree's values).
Outputs: :class:`DriveOutputs` (0x6041, 0x6061, 0x603F, 0x1001, the EMCYs to send and
the axis's edges).  The EMCY code of each cause is :data:`EMCY_CODES` (the table is in
:mod:`ucom_tools.gateway.cia402`'s docstring).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import Final

from ucom_tools.edgelists.armar3 import SPEC

INT32_MIN: Final = -(1 << 31)
INT32_MAX: Final = (1 << 31) - 1
UINT32_MAX: Final = (1 << 32) - 1
WINDOW_OFF: Final = UINT32_MAX
"""0x6065 following error window (and 0x6067 position window) at this value: off."""


class State402(IntEnum):
    """The states of the CiA 402 power drive system (IEC 61800-7-201, 6.3.1)."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7

    @property
    def text(self) -> str:
        """The standard's name, as canopen's ``BaseNode402.state`` spells it."""
        return self.name.replace("_", " ")


class OperationMode(IntEnum):
    """Values of 0x6060 modes of operation / 0x6061 modes of operation display that the
    drive takes (every other value is not supported)."""

    NO_MODE = 0
    """Before the master chose one: the drive holds where it stands when enabled."""
    PROFILE_POSITION = 1
    PROFILE_VELOCITY = 3
    HOMING = 6
    CYCLIC_SYNCHRONOUS_POSITION = 8


SUPPORTED_MODES: Final = 0x0001 | 0x0004 | 0x0020 | 0x0080
"""0x6502 supported drive modes: bit 0 PP, bit 2 PV, bit 5 HM, bit 7 CSP."""


class FaultCause(IntEnum):
    """Why a joint's drive goes to FAULT (byte 3 of its EMCY)."""

    MASTER_HEARTBEAT = 1
    """The master's heartbeat (0x1016 consumer) was not heard in time."""
    SYNC_TIMEOUT = 2
    """No SYNC within the SYNC timeout (no heartbeat consumer configured)."""
    BUS_OFF = 3
    """The gateway's CAN controller on the CANopen side was bus-off and recovered."""
    BOARD_LOST = 4
    """The joint's UCoM board is lost (silent: power, reset, bus-off, a cable)."""
    BOARD_LATCHED = 5
    """The board's watchdog latched: its motors are off until it is started again."""
    BOARD_ERROR = 6
    """The board sent an Error (:attr:`DriveFault.code`: its error code byte)."""


EMCY_CODES: Final = {
    FaultCause.MASTER_HEARTBEAT: 0x8130,
    FaultCause.SYNC_TIMEOUT: 0x8100,
    FaultCause.BUS_OFF: 0x8140,
    FaultCause.BOARD_LOST: 0xFF01,
    FaultCause.BOARD_LATCHED: 0xFF02,
    FaultCause.BOARD_ERROR: 0xFF80,
}
"""Each cause's error code (0x603F and the EMCY); a board's Error adds its code byte."""
ERROR_REGISTER_GENERIC: Final = 0x01
ERROR_REGISTER_COMMUNICATION: Final = 0x10
ERROR_REGISTER_MANUFACTURER: Final = 0x80
_EMCY_DATA: Final = struct.Struct("<BI")


@dataclass(frozen=True, slots=True)
class DriveFault:
    """A cause of FAULT present now (a level: passed in as long as it lasts; an event such
    as a board's Error is passed in once).  FAULT is CiA 402's word for the drive's state;
    an injected fault of the virtual fleet may be one's cause, a mutant board's defect is
    none of this."""

    cause: FaultCause
    code: int = 0
    """BOARD_ERROR: the Error's error code byte (1-127, ``ErrorCode``); else 0."""
    detail: int = 0
    """Carried in the EMCY's manufacturer-specific bytes 4-7 (UNSIGNED32), e.g. an Error's
    detail or the milliseconds since the board's last MCA Alive."""

    def __post_init__(self) -> None:
        if not 0 <= self.code <= 0x7F:
            raise ValueError(f"a fault's code is 0..127, not {self.code}")
        if not 0 <= self.detail <= UINT32_MAX:
            raise ValueError(f"a fault's detail is UNSIGNED32, not {self.detail}")

    @property
    def error_code(self) -> int:
        """Its 0x603F error code and EMCY code (:data:`EMCY_CODES`)."""
        return EMCY_CODES[self.cause] | (self.code if self.cause is FaultCause.BOARD_ERROR
                                         else 0)

    @property
    def error_register(self) -> int:
        """0x1001 error register while it is the fault: generic, and communication
        (0x81xx) or manufacturer specific (0xFFxx)."""
        kind = (ERROR_REGISTER_COMMUNICATION if self.error_code >> 8 == 0x81
                else ERROR_REGISTER_MANUFACTURER)
        return ERROR_REGISTER_GENERIC | kind

    def emcy(self) -> Emcy:
        """The EMCY that reports it."""
        return Emcy(self.error_code, self.error_register,
                    _EMCY_DATA.pack(int(self.cause), self.detail))


@dataclass(frozen=True, slots=True)
class Emcy:
    """One emergency message to send (canopen's ``EmcyProducer.send(code, register,
    data)``): bytes 0-1 the error code, byte 2 the error register, bytes 3-7 ``data``."""

    code: int
    register: int
    data: bytes = bytes(5)


ERROR_RESET: Final = Emcy(0x0000, 0x00)
"""The EMCY "error reset or no error" (CiA 301), sent when a fault reset clears FAULT."""


@dataclass(frozen=True, slots=True)
class ObjectValues:
    """The CiA 402 objects the master writes, raw (their defaults here are the drive's;
    :meth:`DriveConfig.defaults` gives a joint's, with its tree's values)."""

    controlword: int = 0
    """0x6040 (UNSIGNED16)."""
    modes_of_operation: int = 0
    """0x6060 (INTEGER8)."""
    target_position: int = 0
    """0x607A (INTEGER32) [counts of the joint sensor]."""
    target_velocity: int = 0
    """0x60FF (INTEGER32) [counts/s]."""
    profile_velocity: int = 0
    """0x6081 (UNSIGNED32) [counts/s]: the axis's Max Velocity (x1000) x 1000."""
    position_window: int = 5
    """0x6067 (UNSIGNED32) [counts]; :data:`WINDOW_OFF`: every position is in it."""
    position_window_time: int = 20
    """0x6068 (UNSIGNED16) [ms]."""
    velocity_window: int = 50
    """0x606D (UNSIGNED16) [counts/s]."""
    velocity_window_time: int = 20
    """0x606E (UNSIGNED16) [ms]."""
    velocity_threshold: int = 50
    """0x606F (UNSIGNED16) [counts/s]."""
    velocity_threshold_time: int = 20
    """0x6070 (UNSIGNED16) [ms]."""
    following_error_window: int = WINDOW_OFF
    """0x6065 (UNSIGNED32) [counts]; :data:`WINDOW_OFF`: following control off."""
    following_error_time_out: int = 20
    """0x6066 (UNSIGNED16) [ms]."""
    quick_stop_option: int = 2
    """0x605A (INTEGER16)."""
    homing_method: int = -1
    """0x6098 (INTEGER8)."""
    home_offset: int = 0
    """0x607C (INTEGER32) [counts]: the axis's Reset Offset."""
    min_position_limit: int = -32768
    """0x607D sub 1 (INTEGER32) [counts]: the axis's Min Position."""
    max_position_limit: int = 32767
    """0x607D sub 2 (INTEGER32) [counts]: the axis's Max Position."""


@dataclass(frozen=True, slots=True)
class JointReport:
    """What the joint's board reports, raw (its SO edges)."""

    position: int = 0
    """Joint Sensor (``Encoder 2k``) [counts]: 0x6064 position actual value."""
    velocity: int = 0
    """Velocity (``Velocity X``) [counts/s]: 0x606C velocity actual value."""
    valid: bool = False
    """The values are current (the board runs its program and is not lost)."""
    reset_answer: int = 0
    """Reset Answer: 0 never homed, 1 homing, 2 homed, -1 failed."""


def _range(name: str) -> tuple[int, int]:
    """The raw range of the armar3 program's edge ``name`` (axis A's: every axis's is
    the same)."""
    edge = next(e for e in SPEC.edges if e.name == name)
    return edge.minimum, edge.maximum


@dataclass(frozen=True, slots=True)
class DriveConfig:
    """One joint's fixed settings: its edges' ranges (the armar3 program's by default) and
    the values its tree gives (the defaults of the objects that stand for them)."""

    max_velocity: int = 1
    """The tree's ``Max Velocity (x1000)`` [1000 counts/s]."""
    min_position: int = -32768
    """The tree's ``Min Position`` [counts]."""
    max_position: int = 32767
    """The tree's ``Max Position`` [counts]."""
    reset_offset: int = 0
    """The tree's ``Reset Offset`` [counts]."""
    reset_pwm: int = 0
    """The tree's ``Reset X PWM`` [1/16000]: its sign points to the end stop; 0: the axis
    cannot home."""
    target_range: tuple[int, int] = _range("MotorA Target")
    target_vel_range: tuple[int, int] = _range("MotorA TargetVel")
    reset_offset_range: tuple[int, int] = _range("MotorA Reset Offset")
    max_velocity_range: tuple[int, int] = _range("MotorA Max Velocity (x1000)")
    reset_pwm_range: tuple[int, int] = _range("Reset A PWM")

    def defaults(self) -> ObjectValues:
        """The objects as the joint starts: 0x6081 = Max Velocity x 1000, 0x607D = Min /
        Max Position, 0x607C = Reset Offset; the rest the drive's defaults."""
        return ObjectValues(profile_velocity=self.max_velocity * 1000,
                            min_position_limit=self.min_position,
                            max_position_limit=self.max_position,
                            home_offset=self.reset_offset)


@dataclass(frozen=True, slots=True)
class DriveOutputs:
    """What one update of the drive gives: the objects it owns and the axis's edges."""

    state: State402
    statusword: int
    """0x6041."""
    mode_display: int
    """0x6061 modes of operation display."""
    error_code: int
    """0x603F: the last fault's code while in the fault states, else 0."""
    error_register: int
    """0x1001: the fault's register bits while in the fault states, else 0."""
    emcys: tuple[Emcy, ...]
    """The EMCYs to send now, in order."""
    transitions: tuple[int, ...]
    """The state transitions (0-16) this update took, in order."""
    command: int
    """``MotorX Command`` (:class:`~ucom_tools.edgelists.armar3.Command`: OFF below
    OPERATION ENABLED)."""
    target: int
    """``MotorX Target`` [counts]."""
    target_vel: int
    """``MotorX TargetVel`` [counts/s]."""
    reset_offset: int
    """``MotorX Reset Offset`` [counts] (0x607C in the edge's range)."""
    reset_pwm: int
    """``Reset X PWM`` [1/16000] (the tree's, with the sign 0x6098 asks for)."""
    max_velocity: int
    """``MotorX Max Velocity (x1000)`` from 0x6081
    (:func:`~ucom_tools.gateway.cia402_modes.max_velocity_raw`)."""

