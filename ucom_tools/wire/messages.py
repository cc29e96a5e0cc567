"""Bootloader-level messages of the UCoM protocol: one namespace and the frame dispatch.

The message classes live in :mod:`ucom_tools.wire.requests` (PC -> board) and
:mod:`ucom_tools.wire.answers` (board -> PC) and are re-exported here.  :func:`decode`
turns a raw frame into ``(Address, message)`` and checks the direction; :func:`encode`
does the reverse.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar, Protocol

from ucom_tools.errors import FrameError
from ucom_tools.wire.answers import (
    AppReport,
    Error,
    InfoFrame,
    InitAck,
    MemoryReport,
    ProgramMissing,
    ProgramPartial,
    ProgramResult,
    Ready,
    StatusReport,
    TextReport,
    decode_finished,
    memory_report_frames,
    text_reports,
)
from ucom_tools.wire.ids import Address, Direction, Function, data_frame_id, decode_id, encode_id
from ucom_tools.wire.requests import (
    InfoRequest,
    InitRequest,
    ProgramAbort,
    ProgramBegin,
    ProgramBlock,
    ProgramData,
    ProgramEnd,
    ProgramErase,
    ProgramFrame,
    ProgramMeta,
    ProgramPrepare,
    ReportRequest,
    Reset,
    SetStatus,
    Start,
    XReset,
    decode_program,
)

__all__ = [
    "BOOTLOADER_FUNCTIONS",
    "AppReport",
    "BootMessage",
    "Error",
    "InfoFrame",
    "InfoRequest",
    "InitAck",
    "InitRequest",
    "MemoryReport",
    "Message",
    "ProgramAbort",
    "ProgramBegin",
    "ProgramBlock",
    "ProgramData",
    "ProgramEnd",
    "ProgramErase",
    "ProgramFrame",
    "ProgramMeta",
    "ProgramMissing",
    "ProgramPartial",
    "ProgramPrepare",
    "ProgramResult",
    "Ready",
    "ReportRequest",
    "Reset",
    "SetStatus",
    "Start",
    "StatusReport",
    "TextReport",
    "XReset",
    "decode",
    "decode_finished",
    "decode_program",
    "encode",
    "memory_report_frames",
    "text_reports",
]


class Message(Protocol):
    FUNCTION: ClassVar[Function]

    def encode(self) -> bytes: ...


BootMessage = (Reset | XReset | SetStatus | InfoRequest | ReportRequest | InitRequest
               | ProgramFrame | Start | Error | InitAck | ProgramResult | ProgramMissing
               | ProgramPartial | InfoFrame | Ready | StatusReport | MemoryReport | TextReport
               | AppReport)

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
    """The (identifier, payload) of ``message`` to or from ``address``; a Program data
    frame has no address: its identifier carries its slot."""
    if isinstance(message, ProgramData):
        return data_frame_id(message.slot), message.data
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
        return address, ProgramData(bytes(data), arbitration_id & 0x3F)
    return address, decoder(bytes(data))
