"""Messages the PC sends to boards (bootloader level), as frozen dataclasses.

Reset, XReset, SetStatus, Info Request, Report Request, Init Request, the Program
frames and Start; byte layouts in ``man/ucom-protocol.7``.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import ClassVar

from ucom_tools.errors import FrameError
from ucom_tools.wire.codes import (
    InitOp,
    MetaField,
    ProgramOp,
    ReportChannel,
    Space,
    StatusOp,
    Target,
)
from ucom_tools.wire.fields import check_enum, check_length, check_range
from ucom_tools.wire.ids import DATA_SLOTS, Function


@dataclass(frozen=True, slots=True)
class Reset:
    """Function 0: warm reset into the bootloader (or the program, with AutoStart)."""

    FUNCTION: ClassVar[Function] = Function.RESET

    def encode(self) -> bytes:
        return b""

    @classmethod
    def decode(cls, data: bytes) -> Reset:
        check_length("Reset", data, 0)
        return cls()


@dataclass(frozen=True, slots=True)
class XReset:
    """Function 1: reset that clears the AutoStart flag first."""

    FUNCTION: ClassVar[Function] = Function.XRESET

    def encode(self) -> bytes:
        return b""

    @classmethod
    def decode(cls, data: bytes) -> XReset:
        check_length("XReset", data, 0)
        return cls()


@dataclass(frozen=True, slots=True)
class SetStatus:
    """Function 7: set one status item (ProgEnable, AutoStart, init pins, seq ID)."""

    FUNCTION: ClassVar[Function] = Function.SET_STATUS
    op: StatusOp
    value: int

    def __post_init__(self) -> None:
        high = 31 if self.op is StatusOp.SEQ_ID else 1
        low = 1 if self.op is StatusOp.SEQ_ID else 0
        check_range("SetStatus value", self.value, low, high)

    def encode(self) -> bytes:
        return bytes((self.op, self.value))

    @classmethod
    def decode(cls, data: bytes) -> SetStatus:
        check_length("SetStatus", data, 2)
        return cls(check_enum(StatusOp, "SetStatus op", data[0]), data[1])


@dataclass(frozen=True, slots=True)
class InfoRequest:
    """Function 8: ask for the Info record (answered by 8 Info frames)."""

    FUNCTION: ClassVar[Function] = Function.INFO_REQUEST

    def encode(self) -> bytes:
        return b""

    @classmethod
    def decode(cls, data: bytes) -> InfoRequest:
        check_length("Info Request", data, 0)
        return cls()


_REPORT_REQ = struct.Struct(">BBHH")


@dataclass(frozen=True, slots=True)
class ReportRequest:
    """Function 9: ask for a Report on a channel; MEMORY reads ``count`` words."""

    FUNCTION: ClassVar[Function] = Function.REPORT_REQUEST
    channel: ReportChannel
    space: Space = Space.P
    address: int = 0
    count: int = 0

    def __post_init__(self) -> None:
        check_range("Report Request address", self.address, 0, 0xFFFF)
        check_range("Report Request count", self.count, 0, 0xFFFF)

    def encode(self) -> bytes:
        return _REPORT_REQ.pack(self.channel, self.space, self.address, self.count)

    @classmethod
    def decode(cls, data: bytes) -> ReportRequest:
        check_length("Report Request", data, 6)
        ch, space, addr, count = _REPORT_REQ.unpack(data)
        return cls(check_enum(ReportChannel, "Report Request channel", ch),
                   check_enum(Space, "Report Request space", space), addr, count)


@dataclass(frozen=True, slots=True)
class InitRequest:
    """Function 10: one step of the init chain (always broadcast); REJOIN gives seq ID
    ``number`` back to the board whose serial number is ``serial`` (DLC 6, the only op
    with a serial)."""

    FUNCTION: ClassVar[Function] = Function.INIT_REQUEST
    op: InitOp
    number: int = 0
    serial: int = 0

    def __post_init__(self) -> None:
        if self.op is InitOp.NEXT:
            check_range("Init Request number", self.number, 2, 31)
        elif self.op is InitOp.REJOIN:
            check_range("Init Request number", self.number, 1, 31)
        elif self.number != 0:
            raise FrameError("Init Request number", f"must be 0 for {self.op.name}")
        if self.op is InitOp.REJOIN:
            check_range("Init Request serial", self.serial, 0, 0xFFFFFFFF)
        elif self.serial != 0:
            raise FrameError("Init Request serial", f"only REJOIN carries one, not "
                                                    f"{self.op.name}")

    def encode(self) -> bytes:
        if self.op is InitOp.REJOIN:
            return _REJOIN.pack(self.op, self.number, self.serial)
        return bytes((self.op, self.number))

    @classmethod
    def decode(cls, data: bytes) -> InitRequest:
        if data and data[0] == InitOp.REJOIN:
            check_length("Init Request REJOIN", data, _REJOIN.size)
            _, number, serial = _REJOIN.unpack(data)
            return cls(InitOp.REJOIN, number, serial)
        check_length("Init Request", data, 2)
        return cls(check_enum(InitOp, "Init Request op", data[0]), data[1])


_REJOIN = struct.Struct(">BBI")
"""Init Request REJOIN: op, the seq ID to take, the board's serial number."""
_BEGIN = struct.Struct(">BBHH")
_META = struct.Struct(">BB4s")
_ERASE = struct.Struct(">BBHH")
_BLOCK = struct.Struct(">BBHBH")
"""op, space << 7 | frames, word address, block index, CRC-16 of the block's data."""
MAX_BLOCKS = 256


@dataclass(frozen=True, slots=True)
class ProgramBegin:
    """Program control frame: start a transfer of ``blocks`` blocks into ``target``."""

    FUNCTION: ClassVar[Function] = Function.PROGRAM
    target: Target
    blocks: int
    entry: int

    def __post_init__(self) -> None:
        check_range("Program Begin blocks", self.blocks, 1, MAX_BLOCKS)
        check_range("Program Begin entry", self.entry, 0, 0xFFFF)

    def encode(self) -> bytes:
        return _BEGIN.pack(ProgramOp.BEGIN, self.target, self.blocks, self.entry)


@dataclass(frozen=True, slots=True)
class ProgramMeta:
    """Program control frame: one 4-byte item of the program's metadata."""

    FUNCTION: ClassVar[Function] = Function.PROGRAM
    field: int
    value: bytes

    def __post_init__(self) -> None:
        check_range("Program Meta field", self.field, 0, MetaField.NAME_0 + 6)
        if len(self.value) != 4:
            raise FrameError("Program Meta value", f"must be 4 bytes, got {len(self.value)}")

    def encode(self) -> bytes:
        return _META.pack(ProgramOp.META, self.field, self.value)


@dataclass(frozen=True, slots=True)
class ProgramErase:
    """Program control frame: erase ``count`` 256-word pages from ``first_page``."""

    FUNCTION: ClassVar[Function] = Function.PROGRAM
    space: Space
    first_page: int
    count: int

    def __post_init__(self) -> None:
        check_range("Program Erase first page", self.first_page, 0, 0xFF)
        check_range("Program Erase count", self.count, 1, 0x100)

    def encode(self) -> bytes:
        return _ERASE.pack(ProgramOp.ERASE, self.space, self.first_page, self.count)


_PREPARE = struct.Struct(">BH")


@dataclass(frozen=True, slots=True)
class ProgramPrepare:
    """Program control frame: the preamble is complete (``pages`` pages were listed in ERASE
    frames); erase, then answer Ready(ERASED).  Repeated, it asks for Ready(ERASED) again."""

    FUNCTION: ClassVar[Function] = Function.PROGRAM
    pages: int = 0

    def __post_init__(self) -> None:
        check_range("Program Prepare pages", self.pages, 0, 0xFFFF)

    def encode(self) -> bytes:
        return _PREPARE.pack(ProgramOp.PREPARE, self.pages)


@dataclass(frozen=True, slots=True)
class ProgramBlock:
    """Program control frame: the data frames of block ``index`` (``frames`` of them, for
    ``space:address``) follow; ``crc`` is the CRC-16/CCITT-FALSE of the block's data bytes,
    which the board checks before it programs the block."""

    FUNCTION: ClassVar[Function] = Function.PROGRAM
    space: Space
    address: int
    frames: int
    index: int
    crc: int = 0

    def __post_init__(self) -> None:
        check_range("Program Block address", self.address, 0, 0xFFFF)
        check_range("Program Block frames", self.frames, 1, 64)
        check_range("Program Block index", self.index, 0, MAX_BLOCKS - 1)
        check_range("Program Block CRC", self.crc, 0, 0xFFFF)

    def encode(self) -> bytes:
        return _BLOCK.pack(ProgramOp.BLOCK, (self.space << 7) | self.frames, self.address,
                           self.index, self.crc)


@dataclass(frozen=True, slots=True)
class ProgramData:
    """Program data frame: exactly 8 bytes = 4 words, each low byte first, at position
    ``slot`` (0-63) of the current block; the slot travels in identifier bits 5-0."""

    FUNCTION: ClassVar[Function] = Function.PROGRAM
    data: bytes
    slot: int = 0

    def __post_init__(self) -> None:
        if len(self.data) != 8:
            raise FrameError("Program data", f"must be 8 bytes, got {len(self.data)}")
        check_range("Program data slot", self.slot, 0, DATA_SLOTS - 1)

    def encode(self) -> bytes:
        return self.data


@dataclass(frozen=True, slots=True)
class ProgramEnd:
    """Program control frame: transfer complete; verify and answer Program Finished."""

    FUNCTION: ClassVar[Function] = Function.PROGRAM

    def encode(self) -> bytes:
        return bytes((ProgramOp.END,))


@dataclass(frozen=True, slots=True)
class ProgramAbort:
    """Program control frame: drop the transfer; the program stays invalid."""

    FUNCTION: ClassVar[Function] = Function.PROGRAM

    def encode(self) -> bytes:
        return bytes((ProgramOp.ABORT,))


ProgramFrame = (ProgramBegin | ProgramMeta | ProgramErase | ProgramPrepare | ProgramBlock
                | ProgramData | ProgramEnd | ProgramAbort)


def decode_program(data: bytes, slot: int = 0) -> ProgramFrame:
    """Decode any frame of function Program (DLC 8 = data at ``slot``, else a control
    frame)."""
    if len(data) == 8:
        return ProgramData(bytes(data), slot)
    if not data:
        raise FrameError("Program payload length", "expected 1..8 bytes, got 0")
    op = check_enum(ProgramOp, "Program op", data[0])
    if op is ProgramOp.BEGIN:
        check_length("Program Begin", data, _BEGIN.size)
        _, target, blocks, entry = _BEGIN.unpack(data)
        return ProgramBegin(check_enum(Target, "Program Begin target", target), blocks, entry)
    if op is ProgramOp.META:
        check_length("Program Meta", data, _META.size)
        _, fld, value = _META.unpack(data)
        return ProgramMeta(fld, value)
    if op is ProgramOp.ERASE:
        check_length("Program Erase", data, _ERASE.size)
        _, space, first, count = _ERASE.unpack(data)
        return ProgramErase(check_enum(Space, "Program Erase space", space), first, count)
    if op is ProgramOp.BLOCK:
        check_length("Program Block", data, _BLOCK.size)
        _, packed, addr, index, crc = _BLOCK.unpack(data)
        return ProgramBlock(Space(packed >> 7), addr, packed & 0x7F, index, crc)
    if op is ProgramOp.PREPARE:
        check_length("Program Prepare", data, _PREPARE.size)
        return ProgramPrepare(_PREPARE.unpack(data)[1])
    check_length(f"Program {op.name.title()}", data, 1)
    return ProgramEnd() if op is ProgramOp.END else ProgramAbort()


@dataclass(frozen=True, slots=True)
class Start:
    """Function 12: start the program stored in ``target``."""

    FUNCTION: ClassVar[Function] = Function.START
    target: Target = Target.FLASH

    def encode(self) -> bytes:
        return bytes((self.target,))

    @classmethod
    def decode(cls, data: bytes) -> Start:
        check_length("Start", data, 1)
        return cls(check_enum(Target, "Start target", data[0]))
