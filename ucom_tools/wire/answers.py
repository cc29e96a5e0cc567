"""Messages boards send to the PC (bootloader level), as frozen dataclasses.

Error, Init Ack, Program Finished, Info frames, Ready and the Reports; byte layouts in
``man/ucom-protocol.7``.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import ClassVar

from ucom_tools.errors import FrameError
from ucom_tools.wire.codes import (
    BoardState,
    CheckField,
    ErrorCode,
    FinishedKind,
    InitAckKind,
    ReadyReason,
    ResultStatus,
)
from ucom_tools.wire.fields import check_enum, check_length, check_range
from ucom_tools.wire.ids import Function

_ERROR = struct.Struct(">BBI")


@dataclass(frozen=True, slots=True)
class Error:
    """Function 2: the board could not carry out a message."""

    FUNCTION: ClassVar[Function] = Function.ERROR
    code: ErrorCode
    function: int = 0xFF
    detail: int = 0

    def __post_init__(self) -> None:
        check_range("Error function", self.function, 0, 0xFF)
        check_range("Error detail", self.detail, 0, 0xFFFFFFFF)

    def encode(self) -> bytes:
        return _ERROR.pack(self.code, self.function, self.detail)

    @classmethod
    def decode(cls, data: bytes) -> Error:
        check_length("Error", data, _ERROR.size)
        code, fn, detail = _ERROR.unpack(data)
        return cls(check_enum(ErrorCode, "Error code", code), fn, detail)

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
        check_range("Init Ack seq ID", self.seq_id, 0, 31)
        check_range("Init Ack fixed ID", self.fixed_id, 0, 31)
        check_range("Init Ack bootloader version", self.bootloader_version, 0, 0xFF)
        check_range("Init Ack serial", self.serial, 0, 0xFFFFFFFF)

    def encode(self) -> bytes:
        return _INIT_ACK.pack(self.kind, self.seq_id, self.fixed_id, self.bootloader_version,
                              self.serial)

    @classmethod
    def decode(cls, data: bytes) -> InitAck:
        check_length("Init Ack", data, _INIT_ACK.size)
        kind, sid, fid, blv, serial = _INIT_ACK.unpack(data)
        return cls(check_enum(InitAckKind, "Init Ack kind", kind), sid, fid, blv, serial)


_RESULT = struct.Struct(">BBHI")
_MISSING = struct.Struct(">BHH")
_PARTIAL = struct.Struct(">BHBB")
MAX_REPORTS = 64
"""At most this many MISSING/PARTIAL frames follow one RESULT."""


@dataclass(frozen=True, slots=True)
class ProgramResult:
    """Function 4 (RESULT): outcome of a transfer, the ProgID the board computed, and how
    many MISSING/PARTIAL frames follow (``reports``)."""

    FUNCTION: ClassVar[Function] = Function.PROGRAM_FINISHED
    status: ResultStatus
    reports: int
    progid: int

    def __post_init__(self) -> None:
        check_range("Program Finished reports", self.reports, 0, MAX_REPORTS)
        check_range("Program Finished ProgID", self.progid, 0, 0xFFFFFFFF)

    def encode(self) -> bytes:
        return _RESULT.pack(FinishedKind.RESULT, self.status, self.reports, self.progid)


@dataclass(frozen=True, slots=True)
class ProgramMissing:
    """Function 4 (MISSING): ``count`` blocks from ``first`` of which the board has nothing
    (their BLOCK frame never arrived)."""

    FUNCTION: ClassVar[Function] = Function.PROGRAM_FINISHED
    first: int
    count: int

    def __post_init__(self) -> None:
        check_range("Program Finished first block", self.first, 0, 0xFFFF)
        check_range("Program Finished block count", self.count, 1, 0xFFFF)

    def encode(self) -> bytes:
        return _MISSING.pack(FinishedKind.MISSING, self.first, self.count)


@dataclass(frozen=True, slots=True)
class ProgramPartial:
    """Function 4 (PARTIAL): data frames ``first`` .. ``first + count - 1`` of block
    ``block`` did not arrive."""

    FUNCTION: ClassVar[Function] = Function.PROGRAM_FINISHED
    block: int
    first: int
    count: int

    def __post_init__(self) -> None:
        check_range("Program Finished block", self.block, 0, 0xFFFF)
        check_range("Program Finished first frame", self.first, 0, 63)
        check_range("Program Finished frame count", self.count, 1, 64 - self.first)

    def encode(self) -> bytes:
        return _PARTIAL.pack(FinishedKind.PARTIAL, self.block, self.first, self.count)


def decode_finished(data: bytes) -> ProgramResult | ProgramMissing | ProgramPartial:
    if not data:
        raise FrameError("Program Finished payload length", "expected 5 or 8 bytes, got 0")
    kind = check_enum(FinishedKind, "Program Finished kind", data[0])
    if kind is FinishedKind.RESULT:
        check_length("Program Finished result", data, _RESULT.size)
        _, status, reports, progid = _RESULT.unpack(data)
        return ProgramResult(check_enum(ResultStatus, "Program Finished status", status),
                             reports, progid)
    if kind is FinishedKind.PARTIAL:
        check_length("Program Finished partial", data, _PARTIAL.size)
        _, block, first, count = _PARTIAL.unpack(data)
        return ProgramPartial(block, first, count)
    check_length("Program Finished missing", data, _MISSING.size)
    _, first, count = _MISSING.unpack(data)
    return ProgramMissing(first, count)


@dataclass(frozen=True, slots=True)
class InfoFrame:
    """Function 5: one of the 10 frames of an Info record (see :mod:`ucom_tools.wire.info`)."""

    FUNCTION: ClassVar[Function] = Function.INFO
    index: int
    body: bytes

    def __post_init__(self) -> None:
        check_range("Info index", self.index, 0, 9)
        if len(self.body) != 7:
            raise FrameError("Info body", f"must be 7 bytes, got {len(self.body)}")

    def encode(self) -> bytes:
        return bytes((self.index,)) + self.body

    @classmethod
    def decode(cls, data: bytes) -> InfoFrame:
        check_length("Info", data, 8)
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
        check_range("Ready value16", self.value16, 0, 0xFFFF)
        check_range("Ready value32", self.value32, 0, 0xFFFFFFFF)

    def encode(self) -> bytes:
        return _READY.pack(self.reason, self.state, self.value16, self.value32)

    @classmethod
    def decode(cls, data: bytes) -> Ready:
        check_length("Ready", data, _READY.size)
        reason, state, v16, v32 = _READY.unpack(data)
        return cls(check_enum(ReadyReason, "Ready reason", reason),
                   check_enum(BoardState, "Ready state", state), v16, v32)


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
        check_range("Status pins", self.pins, 0, 0x0F)
        check_range("Status leds", self.leds, 0, 0x0F)
        check_range("Status tec", self.tec, 0, 0xFF)
        check_range("Status rec", self.rec, 0, 0xFF)
        check_range("Status seq ID", self.seq_id, 0, 31)
        check_range("Status overruns", self.overruns, 0, 0xFFFF)

    def encode(self) -> bytes:
        return _STATUS_REPORT.pack(self.state, self.pins, self.leds, self.tec, self.rec,
                                   self.seq_id, self.overruns)

    @classmethod
    def decode(cls, data: bytes) -> StatusReport:
        check_length("Status report", data, _STATUS_REPORT.size)
        st, pins, leds, tec, rec, sid, ovr = _STATUS_REPORT.unpack(data)
        return cls(check_enum(BoardState, "Status state", st), pins, leds, tec, rec, sid, ovr)


MEMORY_REPORT_WORDS = 3
"""Words one Report 1 frame carries."""


def memory_report_frames(count: int) -> int:
    """Report 1 frames that answer a memory Report Request of ``count`` words (3 words a
    frame; a request of 0 words is still answered by one)."""
    return max(1, -(-count // MEMORY_REPORT_WORDS))


@dataclass(frozen=True, slots=True)
class MemoryReport:
    """Report channel 1: up to 3 words read from ``address`` (low byte first)."""

    FUNCTION: ClassVar[Function] = Function.REPORT_1
    address: int
    words: tuple[int, ...]

    def __post_init__(self) -> None:
        check_range("Memory report address", self.address, 0, 0xFFFF)
        check_range("Memory report word count", len(self.words), 1, 3)
        for w in self.words:
            check_range("Memory report word", w, 0, 0xFFFF)

    def encode(self) -> bytes:
        return self.address.to_bytes(2, "big") + b"".join(
            w.to_bytes(2, "little") for w in self.words)

    @classmethod
    def decode(cls, data: bytes) -> MemoryReport:
        check_length("Memory report", data, 4, 6, 8)
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
        check_range("Text report index", self.index, 0, 0x7F)
        check_range("Text report length", len(self.text), 0, 7)

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
