"""CAN identifiers of the UCoM protocol (dissertation B.2.2, Tab. B.3 and B.4).

An 11-bit identifier is ``function (5 bit) | type (1 bit) | board number (5 bit)``.
Function 0 (Reset) has the lowest identifier and so the highest bus priority.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum, IntEnum
from typing import Final

from ucom_tools.errors import FrameError

BROADCAST = 0
"""Board number 0 with type SEQUENTIAL addresses every board of the bus (PC -> board)."""

MAX_BOARD_NUMBER = 31


class Direction(Enum):
    """Who initiates a function (Tab. B.4: "Initiator")."""

    HOST_TO_BOARD = "PC"
    BOARD_TO_HOST = "DSP"
    UNASSIGNED = "-"


class Function(IntEnum):
    """Function codes of Tab. B.4 (bits 10-6 of the identifier)."""

    RESET = 0
    XRESET = 1
    ERROR = 2
    INIT_ACK = 3
    PROGRAM_FINISHED = 4
    INFO = 5
    READY = 6
    SET_STATUS = 7
    INFO_REQUEST = 8
    REPORT_REQUEST = 9
    INIT_REQUEST = 10
    PROGRAM = 11
    START = 12
    MCA_CONTROLLER_INPUT = 13
    MCA_SENSOR_OUTPUT = 14
    MCA_PARAMETER = 15
    REPORT_0 = 16
    REPORT_1 = 17
    REPORT_2 = 18
    REPORT_3 = 19
    MCA_READY = 20
    MCA_START = 21
    MCA_DUMPIO_DESCR_REQUEST = 22
    MCA_DUMPIO_DESCR = 23
    MCA_DUMP_CI = 24
    MCA_ADMIN_DATA = 25
    MCA_ALIVE = 26
    MCA_DSP_CI = 27

    @property
    def direction(self) -> Direction:
        return Direction.BOARD_TO_HOST if self in _FROM_BOARD else Direction.HOST_TO_BOARD

    @property
    def label(self) -> str:
        """The name as printed in Tab. B.4."""
        return _LABELS.get(self, self.name.replace("_", " ").title())

    @classmethod
    def report(cls, channel: int) -> Function:
        """The Report function (100XX) of report channel 0-3."""
        if not 0 <= channel <= 3:
            raise FrameError("report channel", f"must be 0..3, got {channel}")
        return cls(cls.REPORT_0 + channel)


_FROM_BOARD = frozenset({
    Function.ERROR, Function.INIT_ACK, Function.PROGRAM_FINISHED, Function.INFO,
    Function.READY, Function.MCA_SENSOR_OUTPUT, Function.REPORT_0, Function.REPORT_1,
    Function.REPORT_2, Function.REPORT_3, Function.MCA_READY, Function.MCA_DUMPIO_DESCR,
    Function.MCA_DSP_CI,
})

_LABELS = {
    Function.XRESET: "XReset",
    Function.INIT_ACK: "Init Ack",
    Function.SET_STATUS: "SetStatus",
    Function.MCA_DUMPIO_DESCR_REQUEST: "MCA DumpIO Descr Request",
    Function.MCA_DUMPIO_DESCR: "MCA DumpIO Descr",
    Function.MCA_DUMP_CI: "MCA Dump CI",
    Function.MCA_DSP_CI: "MCA DSP CI",
    Function.MCA_CONTROLLER_INPUT: "MCA Controller Input",
    Function.MCA_SENSOR_OUTPUT: "MCA Sensor Output",
    Function.MCA_PARAMETER: "MCA Parameter",
    Function.MCA_READY: "MCA Ready",
    Function.MCA_START: "MCA Start",
    Function.MCA_ADMIN_DATA: "MCA Admin Data",
    Function.MCA_ALIVE: "MCA Alive",
}


def function_direction(code: int) -> Direction:
    """Direction of any 5-bit function code; 28-31 are unassigned."""
    if not 0 <= code <= 31:
        raise FrameError("function", f"must be 0..31, got {code}")
    return Function(code).direction if code <= 27 else Direction.UNASSIGNED


class IdType(IntEnum):
    """Bit 5 of the identifier."""

    SEQUENTIAL = 0
    """Board number assigned by position in the init chain (seq ID)."""
    FIXED = 1
    """Board number fixed in the firmware."""


@dataclass(frozen=True, slots=True)
class Address:
    """Which board a frame is to or from: the identifier's type bit and board number."""

    id_type: IdType
    number: int

    def __post_init__(self) -> None:
        if not 0 <= self.number <= MAX_BOARD_NUMBER:
            raise FrameError("board number", f"must be 0..31, got {self.number}")

    @property
    def is_broadcast(self) -> bool:
        return self.id_type is IdType.SEQUENTIAL and self.number == BROADCAST

    def __str__(self) -> str:
        if self.is_broadcast:
            return "all"
        return f"{self.number}" if self.id_type is IdType.SEQUENTIAL else f"F{self.number}"


ALL = Address(IdType.SEQUENTIAL, BROADCAST)

_ADDRESSES: Final = tuple(Address(IdType(low >> 5), low & 0x1F) for low in range(64))
"""Every address, by the identifier's low six bits (decoding a frame makes none)."""


def seq(number: int) -> Address:
    """Address of the board with sequential ID ``number``."""
    return Address(IdType.SEQUENTIAL, number)


def fixed(number: int) -> Address:
    """Address of the board with fixed ID ``number``."""
    return Address(IdType.FIXED, number)


def encode_id(function: int, address: Address) -> int:
    """The 11-bit identifier of ``function`` sent to or from ``address``."""
    if not 0 <= function <= 31:
        raise FrameError("function", f"must be 0..31, got {function}")
    return (function << 6) | (int(address.id_type) << 5) | address.number


def decode_id(arbitration_id: int) -> tuple[int, Address]:
    """Split an 11-bit identifier into (function code, address)."""
    if not 0 <= arbitration_id <= 0x7FF:
        raise FrameError("identifier", f"must be an 11-bit value, got 0x{arbitration_id:X}")
    return arbitration_id >> 6, _ADDRESSES[arbitration_id & 0x3F]


DATA_SLOTS = 64
"""Program data frames carry their position in the block (0-63) in identifier bits 5-0."""


def data_frame_id(slot: int) -> int:
    """Identifier of a Program data frame at position ``slot`` of its block.

    Data frames carry no board address: bits 5-0 (type bit and board number elsewhere) are
    the frame's index in the block opened by the last BLOCK frame, and the boards that BLOCK
    frame addressed store it (``man/ucom-protocol.7``, PROGRAMMING)."""
    if not 0 <= slot < DATA_SLOTS:
        raise FrameError("data frame slot", f"must be 0..{DATA_SLOTS - 1}, got {slot}")
    return (int(Function.PROGRAM) << 6) | slot


ANSWER: dict[int, int] = {
    Function.RESET: Function.READY, Function.XRESET: Function.READY,
    Function.SET_STATUS: Function.READY, Function.START: Function.READY,
    Function.INFO_REQUEST: Function.INFO, Function.INIT_REQUEST: Function.INIT_ACK,
    Function.REPORT_REQUEST: Function.REPORT_3, Function.PROGRAM: Function.READY,
    Function.MCA_CONTROLLER_INPUT: Function.MCA_READY, Function.MCA_PARAMETER:
    Function.MCA_READY, Function.MCA_START: Function.MCA_READY,
    Function.MCA_ADMIN_DATA: Function.MCA_READY,
    Function.MCA_DUMPIO_DESCR_REQUEST: Function.MCA_DUMPIO_DESCR,
    Function.MCA_DUMP_CI: Function.MCA_DSP_CI,
}
"""The function that answers each request (Program: PREPARE's; END waits for Program
Finished, a Report Request for the Report of its channel)."""
