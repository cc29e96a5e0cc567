"""Bootloader-level messages of the UCoM protocol as frozen dataclasses.

Each class knows its :class:`Function` and encodes/decodes its payload (the CAN data
field).  :func:`decode` turns a raw frame into ``(Address, message)`` and checks the
direction; :func:`encode` does the reverse.  Byte layouts are in ``man/ucom-protocol.7``.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import ClassVar, Protocol, TypeVar

from ucom_tools.errors import FrameError
from ucom_tools.wire.codes import (
    BoardState,
    CheckField,
    ErrorCode,
    FinishedKind,
    InitAckKind,
    InitOp,
    MetaField,
    ProgramOp,
    ReadyReason,
    ReportChannel,
    ResultStatus,
    Space,
    StatusOp,
    Target,
)
from ucom_tools.wire.ids import Address, Direction, Function, decode_id, encode_id

E = TypeVar("E", bound=IntEnum)


class Message(Protocol):
    FUNCTION: ClassVar[Function]

    def encode(self) -> bytes: ...


def _length(name: str, data: bytes, *allowed: int) -> None:
    if len(data) not in allowed:
        want = " or ".join(str(n) for n in allowed)
        raise FrameError(f"{name} payload length", f"expected {want} bytes, got {len(data)}")


def _enum(enum: type[E], field: str, value: int) -> E:
    try:
        return enum(value)
    except ValueError:
        raise FrameError(field, f"reserved value 0x{value:02X}") from None


def _range(field: str, value: int, low: int, high: int) -> None:
    if not low <= value <= high:
        raise FrameError(field, f"must be {low}..{high}, got {value}")


# ----------------------------------------------------------------------------- PC -> board

@dataclass(frozen=True, slots=True)
class Reset:
    """Function 0: warm reset into the bootloader (or the program, with AutoStart)."""

    FUNCTION: ClassVar[Function] = Function.RESET

    def encode(self) -> bytes:
        return b""

    @classmethod
    def decode(cls, data: bytes) -> Reset:
        _length("Reset", data, 0)
        return cls()


@dataclass(frozen=True, slots=True)
class XReset:
    """Function 1: reset that clears the AutoStart flag first."""

    FUNCTION: ClassVar[Function] = Function.XRESET

    def encode(self) -> bytes:
        return b""

    @classmethod
    def decode(cls, data: bytes) -> XReset:
        _length("XReset", data, 0)
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
        _range("SetStatus value", self.value, low, high)

    def encode(self) -> bytes:
        return bytes((self.op, self.value))

    @classmethod
    def decode(cls, data: bytes) -> SetStatus:
        _length("SetStatus", data, 2)
        return cls(_enum(StatusOp, "SetStatus op", data[0]), data[1])


@dataclass(frozen=True, slots=True)
class InfoRequest:
    """Function 8: ask for the Info record (answered by 8 Info frames)."""

    FUNCTION: ClassVar[Function] = Function.INFO_REQUEST

    def encode(self) -> bytes:
        return b""

    @classmethod
    def decode(cls, data: bytes) -> InfoRequest:
        _length("Info Request", data, 0)
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
        _range("Report Request address", self.address, 0, 0xFFFF)
        _range("Report Request count", self.count, 0, 0xFFFF)

    def encode(self) -> bytes:
        return _REPORT_REQ.pack(self.channel, self.space, self.address, self.count)

    @classmethod
    def decode(cls, data: bytes) -> ReportRequest:
        _length("Report Request", data, 6)
        ch, space, addr, count = _REPORT_REQ.unpack(data)
        return cls(_enum(ReportChannel, "Report Request channel", ch),
                   _enum(Space, "Report Request space", space), addr, count)


@dataclass(frozen=True, slots=True)
class InitRequest:
    """Function 10: one step of the init chain (always broadcast)."""

    FUNCTION: ClassVar[Function] = Function.INIT_REQUEST
    op: InitOp
    number: int = 0

    def __post_init__(self) -> None:
        if self.op is InitOp.NEXT:
            _range("Init Request number", self.number, 2, 31)
        elif self.number != 0:
            raise FrameError("Init Request number", f"must be 0 for {self.op.name}")

    def encode(self) -> bytes:
        return bytes((self.op, self.number))

    @classmethod
    def decode(cls, data: bytes) -> InitRequest:
        _length("Init Request", data, 2)
        return cls(_enum(InitOp, "Init Request op", data[0]), data[1])


_BEGIN = struct.Struct(">BBHH")
_META = struct.Struct(">BB4s")
_ERASE = struct.Struct(">BBHH")
_BLOCK = struct.Struct(">BBHBH")


@dataclass(frozen=True, slots=True)
class ProgramBegin:
    """Program control frame: start a transfer of ``blocks`` blocks into ``target``."""

    FUNCTION: ClassVar[Function] = Function.PROGRAM
    target: Target
    blocks: int
    entry: int

    def __post_init__(self) -> None:
        _range("Program Begin blocks", self.blocks, 1, 0xFFFF)
        _range("Program Begin entry", self.entry, 0, 0xFFFF)

    def encode(self) -> bytes:
        return _BEGIN.pack(ProgramOp.BEGIN, self.target, self.blocks, self.entry)


@dataclass(frozen=True, slots=True)
class ProgramMeta:
    """Program control frame: one 4-byte item of the program's metadata."""

    FUNCTION: ClassVar[Function] = Function.PROGRAM
    field: int
    value: bytes

    def __post_init__(self) -> None:
        _range("Program Meta field", self.field, 0, MetaField.NAME_0 + 6)
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
        _range("Program Erase first page", self.first_page, 0, 0xFF)
        _range("Program Erase count", self.count, 1, 0x100)

    def encode(self) -> bytes:
        return _ERASE.pack(ProgramOp.ERASE, self.space, self.first_page, self.count)


@dataclass(frozen=True, slots=True)
class ProgramPrepare:
    """Program control frame: the erase list is complete; answer Ready(ERASED) when done."""

    FUNCTION: ClassVar[Function] = Function.PROGRAM

    def encode(self) -> bytes:
        return bytes((ProgramOp.PREPARE,))


@dataclass(frozen=True, slots=True)
class ProgramBlock:
    """Program control frame: ``frames`` data frames for ``space:address`` follow."""

    FUNCTION: ClassVar[Function] = Function.PROGRAM
    space: Space
    address: int
    frames: int
    index: int

    def __post_init__(self) -> None:
        _range("Program Block address", self.address, 0, 0xFFFF)
        _range("Program Block frames", self.frames, 1, 64)
        _range("Program Block index", self.index, 0, 0xFFFF)

    def encode(self) -> bytes:
        return _BLOCK.pack(ProgramOp.BLOCK, self.space, self.address, self.frames, self.index)


@dataclass(frozen=True, slots=True)
class ProgramData:
    """Program data frame: exactly 8 bytes = 4 words, each low byte first."""

    FUNCTION: ClassVar[Function] = Function.PROGRAM
    data: bytes

    def __post_init__(self) -> None:
        if len(self.data) != 8:
            raise FrameError("Program data", f"must be 8 bytes, got {len(self.data)}")

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


def decode_program(data: bytes) -> ProgramFrame:
    """Decode any frame of function Program (DLC 8 = data, else a control frame)."""
    if len(data) == 8:
        return ProgramData(bytes(data))
    if not data:
        raise FrameError("Program payload length", "expected 1..8 bytes, got 0")
    op = _enum(ProgramOp, "Program op", data[0])
    if op is ProgramOp.BEGIN:
        _length("Program Begin", data, _BEGIN.size)
        _, target, blocks, entry = _BEGIN.unpack(data)
        return ProgramBegin(_enum(Target, "Program Begin target", target), blocks, entry)
    if op is ProgramOp.META:
        _length("Program Meta", data, _META.size)
        _, fld, value = _META.unpack(data)
        return ProgramMeta(fld, value)
    if op is ProgramOp.ERASE:
        _length("Program Erase", data, _ERASE.size)
        _, space, first, count = _ERASE.unpack(data)
        return ProgramErase(_enum(Space, "Program Erase space", space), first, count)
    if op is ProgramOp.BLOCK:
        _length("Program Block", data, _BLOCK.size)
        _, space, addr, frames, index = _BLOCK.unpack(data)
        return ProgramBlock(_enum(Space, "Program Block space", space), addr, frames, index)
    _length(f"Program {op.name.title()}", data, 1)
    if op is ProgramOp.PREPARE:
        return ProgramPrepare()
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
        _length("Start", data, 1)
        return cls(_enum(Target, "Start target", data[0]))


# ----------------------------------------------------------------------------- board -> PC

_ERROR = struct.Struct(">BBI")


@dataclass(frozen=True, slots=True)
class Error:
    """Function 2: the board could not carry out a message."""

    FUNCTION: ClassVar[Function] = Function.ERROR
    code: ErrorCode
    function: int = 0xFF
    detail: int = 0

    def __post_init__(self) -> None:
        _range("Error function", self.function, 0, 0xFF)
        _range("Error detail", self.detail, 0, 0xFFFFFFFF)

    def encode(self) -> bytes:
        return _ERROR.pack(self.code, self.function, self.detail)

    @classmethod
    def decode(cls, data: bytes) -> Error:
        _length("Error", data, _ERROR.size)
        code, fn, detail = _ERROR.unpack(data)
        return cls(_enum(ErrorCode, "Error code", code), fn, detail)

    def describe(self) -> str:
        if self.code in (ErrorCode.INCOMPATIBLE, ErrorCode.VERSION_MISMATCH):
            field, expected, found = self.detail >> 16, (self.detail >> 8) & 0xFF, \
                self.detail & 0xFF
            try:
                name = CheckField(field).text
            except ValueError:
                return self.code.text
            return (f"{self.code.text}: {name}: program built for {expected}, "
                    f"board has {found}")
        what = self.code.text
        if self.function <= 31:
            what += f" (in reply to function {self.function})"
        if self.detail:
            what += f" [detail 0x{self.detail:X}]"
        return what


_INIT_ACK = struct.Struct(">BBBBI")


@dataclass(frozen=True, slots=True)
class InitAck:
    """Function 3: a board took a seq ID, or answers an init-line probe."""

    FUNCTION: ClassVar[Function] = Function.INIT_ACK
    kind: InitAckKind
    seq_id: int
    fixed_id: int
    bootloader_version: int
    serial: int

    def __post_init__(self) -> None:
        _range("Init Ack seq ID", self.seq_id, 0, 31)
        _range("Init Ack fixed ID", self.fixed_id, 0, 31)
        _range("Init Ack bootloader version", self.bootloader_version, 0, 0xFF)
        _range("Init Ack serial", self.serial, 0, 0xFFFFFFFF)

    def encode(self) -> bytes:
        return _INIT_ACK.pack(self.kind, self.seq_id, self.fixed_id, self.bootloader_version,
                              self.serial)

    @classmethod
    def decode(cls, data: bytes) -> InitAck:
        _length("Init Ack", data, _INIT_ACK.size)
        kind, sid, fid, blv, serial = _INIT_ACK.unpack(data)
        return cls(_enum(InitAckKind, "Init Ack kind", kind), sid, fid, blv, serial)


_RESULT = struct.Struct(">BBHI")
_MISSING = struct.Struct(">BHH")


@dataclass(frozen=True, slots=True)
class ProgramResult:
    """Function 4 (RESULT): outcome of a transfer and the ProgID the board computed."""

    FUNCTION: ClassVar[Function] = Function.PROGRAM_FINISHED
    status: ResultStatus
    missing: int
    progid: int

    def __post_init__(self) -> None:
        _range("Program Finished missing", self.missing, 0, 0xFFFF)
        _range("Program Finished ProgID", self.progid, 0, 0xFFFFFFFF)

    def encode(self) -> bytes:
        return _RESULT.pack(FinishedKind.RESULT, self.status, self.missing, self.progid)


@dataclass(frozen=True, slots=True)
class ProgramMissing:
    """Function 4 (MISSING): a run of ``count`` blocks from ``first`` that the board lacks."""

    FUNCTION: ClassVar[Function] = Function.PROGRAM_FINISHED
    first: int
    count: int

    def __post_init__(self) -> None:
        _range("Program Finished first block", self.first, 0, 0xFFFF)
        _range("Program Finished block count", self.count, 1, 0xFFFF)

    def encode(self) -> bytes:
        return _MISSING.pack(FinishedKind.MISSING, self.first, self.count)


def decode_finished(data: bytes) -> ProgramResult | ProgramMissing:
    if not data:
        raise FrameError("Program Finished payload length", "expected 5 or 8 bytes, got 0")
    kind = _enum(FinishedKind, "Program Finished kind", data[0])
    if kind is FinishedKind.RESULT:
        _length("Program Finished result", data, _RESULT.size)
        _, status, missing, progid = _RESULT.unpack(data)
        return ProgramResult(_enum(ResultStatus, "Program Finished status", status), missing,
                             progid)
    _length("Program Finished missing", data, _MISSING.size)
    _, first, count = _MISSING.unpack(data)
    return ProgramMissing(first, count)


@dataclass(frozen=True, slots=True)
class InfoFrame:
    """Function 5: one of the 10 frames of an Info record (see :mod:`ucom_tools.wire.info`)."""

    FUNCTION: ClassVar[Function] = Function.INFO
    index: int
    body: bytes

    def __post_init__(self) -> None:
        _range("Info index", self.index, 0, 9)
        if len(self.body) != 7:
            raise FrameError("Info body", f"must be 7 bytes, got {len(self.body)}")

    def encode(self) -> bytes:
        return bytes((self.index,)) + self.body

    @classmethod
    def decode(cls, data: bytes) -> InfoFrame:
        _length("Info", data, 8)
        return cls(data[0], bytes(data[1:]))


_READY = struct.Struct(">BBHI")


@dataclass(frozen=True, slots=True)
class Ready:
    """Function 6: the board is ready (after reset, erase, SetStatus, start) or paces a
    transfer (PAUSE/RESUME).  ``value16``/``value32`` depend on ``reason``."""

    FUNCTION: ClassVar[Function] = Function.READY
    reason: ReadyReason
    state: BoardState
    value16: int = 0
    value32: int = 0

    def __post_init__(self) -> None:
        _range("Ready value16", self.value16, 0, 0xFFFF)
        _range("Ready value32", self.value32, 0, 0xFFFFFFFF)

    def encode(self) -> bytes:
        return _READY.pack(self.reason, self.state, self.value16, self.value32)

    @classmethod
    def decode(cls, data: bytes) -> Ready:
        _length("Ready", data, _READY.size)
        reason, state, v16, v32 = _READY.unpack(data)
        return cls(_enum(ReadyReason, "Ready reason", reason),
                   _enum(BoardState, "Ready state", state), v16, v32)


_STATUS_REPORT = struct.Struct(">BBBBBBH")


@dataclass(frozen=True, slots=True)
class StatusReport:
    """Report channel 0: state, init pins, LEDs and CAN error counters.

    ``pins`` bits: 0 init-in driven, 1 init-in measured set, 2 init-out driven,
    3 init-out measured set.  ``leds`` bits: 0 red, 1 yellow, 2 green, 3 green blinks."""

    FUNCTION: ClassVar[Function] = Function.REPORT_0
    state: BoardState
    pins: int
    leds: int
    tec: int
    rec: int
    seq_id: int
    overruns: int

    def __post_init__(self) -> None:
        _range("Status pins", self.pins, 0, 0x0F)
        _range("Status leds", self.leds, 0, 0x0F)
        _range("Status tec", self.tec, 0, 0xFF)
        _range("Status rec", self.rec, 0, 0xFF)
        _range("Status seq ID", self.seq_id, 0, 31)
        _range("Status overruns", self.overruns, 0, 0xFFFF)

    def encode(self) -> bytes:
        return _STATUS_REPORT.pack(self.state, self.pins, self.leds, self.tec, self.rec,
                                   self.seq_id, self.overruns)

    @classmethod
    def decode(cls, data: bytes) -> StatusReport:
        _length("Status report", data, _STATUS_REPORT.size)
        st, pins, leds, tec, rec, sid, ovr = _STATUS_REPORT.unpack(data)
        return cls(_enum(BoardState, "Status state", st), pins, leds, tec, rec, sid, ovr)


@dataclass(frozen=True, slots=True)
class MemoryReport:
    """Report channel 1: up to 3 words read from ``address`` (low byte first)."""

    FUNCTION: ClassVar[Function] = Function.REPORT_1
    address: int
    words: tuple[int, ...]

    def __post_init__(self) -> None:
        _range("Memory report address", self.address, 0, 0xFFFF)
        _range("Memory report word count", len(self.words), 1, 3)
        for w in self.words:
            _range("Memory report word", w, 0, 0xFFFF)

    def encode(self) -> bytes:
        return self.address.to_bytes(2, "big") + b"".join(
            w.to_bytes(2, "little") for w in self.words)

    @classmethod
    def decode(cls, data: bytes) -> MemoryReport:
        _length("Memory report", data, 4, 6, 8)
        words = tuple(int.from_bytes(data[i:i + 2], "little") for i in range(2, len(data), 2))
        return cls(int.from_bytes(data[:2], "big"), words)


@dataclass(frozen=True, slots=True)
class TextReport:
    """Report channel 2: a piece of a text message; bit 7 of ``index`` marks the last."""

    FUNCTION: ClassVar[Function] = Function.REPORT_2
    index: int
    last: bool
    text: bytes

    def __post_init__(self) -> None:
        _range("Text report index", self.index, 0, 0x7F)
        _range("Text report length", len(self.text), 0, 7)

    def encode(self) -> bytes:
        return bytes((self.index | (0x80 if self.last else 0),)) + self.text

    @classmethod
    def decode(cls, data: bytes) -> TextReport:
        if not 1 <= len(data) <= 8:
            raise FrameError("Text report payload length", f"expected 1..8 bytes, got {len(data)}")
        return cls(data[0] & 0x7F, bool(data[0] & 0x80), bytes(data[1:]))


@dataclass(frozen=True, slots=True)
class AppReport:
    """Report channel 3: application-defined bytes."""

    FUNCTION: ClassVar[Function] = Function.REPORT_3
    data: bytes

    def encode(self) -> bytes:
        return self.data

    @classmethod
    def decode(cls, data: bytes) -> AppReport:
        return cls(bytes(data))


def text_reports(text: str) -> list[TextReport]:
    """Cut a message into Text report frames (latin-1, at most 127*7 characters)."""
    raw = text.encode("latin-1", "replace")[: 127 * 7]
    chunks = [raw[i:i + 7] for i in range(0, len(raw), 7)] or [b""]
    return [TextReport(i, i == len(chunks) - 1, c) for i, c in enumerate(chunks)]


# ----------------------------------------------------------------------------- dispatch

BootMessage = (Reset | XReset | SetStatus | InfoRequest | ReportRequest | InitRequest
               | ProgramFrame | Start | Error | InitAck | ProgramResult | ProgramMissing
               | InfoFrame | Ready | StatusReport | MemoryReport | TextReport | AppReport)

_DECODERS: dict[Function, Callable[[bytes], BootMessage]] = {
    Function.RESET: Reset.decode,
    Function.XRESET: XReset.decode,
    Function.ERROR: Error.decode,
    Function.INIT_ACK: InitAck.decode,
    Function.PROGRAM_FINISHED: decode_finished,
    Function.INFO: InfoFrame.decode,
    Function.READY: Ready.decode,
    Function.SET_STATUS: SetStatus.decode,
    Function.INFO_REQUEST: InfoRequest.decode,
    Function.REPORT_REQUEST: ReportRequest.decode,
    Function.INIT_REQUEST: InitRequest.decode,
    Function.PROGRAM: decode_program,
    Function.START: Start.decode,
    Function.REPORT_0: StatusReport.decode,
    Function.REPORT_1: MemoryReport.decode,
    Function.REPORT_2: TextReport.decode,
    Function.REPORT_3: AppReport.decode,
}

BOOTLOADER_FUNCTIONS = frozenset(_DECODERS)


def encode(message: BootMessage, address: Address) -> tuple[int, bytes]:
    """The (identifier, payload) of ``message`` to or from ``address``."""
    return encode_id(message.FUNCTION, address), message.encode()


def decode(arbitration_id: int, data: bytes, *,
           sender: Direction | None = None) -> tuple[Address, BootMessage]:
    """Decode a bootloader-level frame.

    ``sender`` is who is expected to have sent it; a frame of the other direction raises
    :class:`FrameError` naming the function.  MCA functions (13-15, 20-27) and the
    unassigned codes 28-31 raise :class:`FrameError` too: they are not bootloader messages.
    """
    code, address = decode_id(arbitration_id)
    if code > 27:
        raise FrameError("function", f"code {code} is unassigned")
    function = Function(code)
    decoder = _DECODERS.get(function)
    if decoder is None:
        raise FrameError("function", f"{function.label} is a run-time (MCA) message")
    if sender is not None and function.direction is not sender:
        raise FrameError("function", f"{function.label} is sent by the "
                         f"{function.direction.value}, not by the {sender.value}")
    if function is Function.PROGRAM and len(data) == 8:
        return address, ProgramData(bytes(data))
    return address, decoder(bytes(data))
