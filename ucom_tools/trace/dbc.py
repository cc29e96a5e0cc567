"""The UCoM frames as a DBC database (``ucom dbc``), for SavvyCAN, ``cantools monitor``,
CANalyzer and other tools that read DBC files.

Design.  A DBC message is matched by the whole identifier, and the board number is part
of the UCoM identifier (bits 4-0, with the type bit 5), not of the payload; a DBC
multiplexer selects on a payload field, so it cannot stand for the board.  The database
therefore has **one message per identifier**: for every function and every board number
that can send or receive it (PC -> board: broadcast ``_All``, seq IDs ``_1``..``_31``,
fixed IDs ``_F1``..``_F31``; board -> PC: the seq and fixed IDs, and ``InitAck_Unnumbered``
for a board without a number), each with the same signals.  Within a payload, messages
whose layout depends on a field use plain DBC multiplexing (``SG_ ... M`` / ``mN``,
understood by SavvyCAN and cantools): Program Finished (kind), Info (frame index), Ready
(reason), MCA Admin Data (op).

What a frame is, and so which signals it has, the database says only where a stateless
decoder can tell from the frame itself: a frame is never decoded as something it is not
(``tests/test_dbc_interop.py`` compares cantools' decoding of recorded traces, frame by
frame, with ``ucom decode``'s stateful reading).  A DBC message has one length, and strict
decoding (``cantools decode``, ``decode_message`` by default) takes only frames of that
length (the Python API also longer ones, which the protocol never sends); so every message
has the length of its **longest form**, and the signals of each shorter form are a prefix
of it that stays right for that form: a decoder that allows truncated frames (``cantools
monitor``, SavvyCAN, ``decode_message(..., allow_truncated=True)``) shows the signals that
fit, and they are right.  Where a field tells the forms apart it is the multiplexer
(Program Finished: kind, Info: frame index, Ready: reason, MCA Admin Data: op); where none
does, only what every form shares is described:

- Program (0x2C0-0x2FF) carries data frames (DLC 8: four program words, the slot 0-63 in
  identifier bits 5-0) and control frames (DLC 1-7: [0] op, to the board in bits 5-0).  A
  data frame's first byte is any value, so no payload field tells them apart: the messages
  describe the data frame, as one 64-bit signal of the four words, which no control frame
  fits (strictly undecoded; truncated, no signals).  ``ucom decode`` reads the control
  frames.
- The generic MCA values (Controller Input, Parameter, DSP CI) are raw bytes after the
  index: an edge is 2 or 4 bytes wide, signed or not, as its MCA DumpIO Descr record says,
  which a frame does not carry.  Process data (SO maps 0x3A1-0x3BF, CI maps 0x361-0x37F)
  are raw masked 16-bit words: what a map carries depends on the Admin Data SO_MAP/CI_MAP
  frames sent at run time, and every byte travels XOR 0x55.
- Shorter forms that strict decoding leaves undecoded: Program Finished MISSING and
  PARTIAL (DLC 5), a Report MEMORY of 1 or 2 words, a Text report's last piece, MCA
  DumpIO Descr Request for every edge (DLC 0), an edge record's last segment, Admin Data
  but SO_MAP of four edges, MCA values and maps shorter than 8 bytes.

Byte layouts: ``man/ucom-protocol.7`` and the codecs in :mod:`ucom_tools.wire`.

cantools is an optional dependency (``pip install 'ucom-tools[dbc]'``), imported only
here and only when a database is built.
"""

from __future__ import annotations

import os
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path
from typing import TYPE_CHECKING

from ucom_tools import __version__, fileio
from ucom_tools.errors import InputError, OutputExists
from ucom_tools.wire import mca
from ucom_tools.wire.codes import (
    BoardState,
    ErrorCode,
    FinishedKind,
    InitAckKind,
    InitOp,
    ReadyReason,
    ReportChannel,
    ResultStatus,
    Space,
    StatusOp,
    Target,
)
from ucom_tools.wire.ids import Direction, Function

if TYPE_CHECKING:
    from cantools.database.can import Database

INSTALL_HINT = "pip install 'ucom-tools[dbc]'"
PC, BOARD = "PC", "UCoM"
"""The two nodes of the database."""


# ============================================================================ layouts
@dataclass(frozen=True)
class Field:
    """One signal: ``bits`` bits whose least significant bit is bit ``lsb`` of the
    ``size``-byte big-endian integer at byte ``byte`` (or little-endian, for program
    words); ``mux``: the multiplexer value it belongs to."""

    name: str
    byte: int
    bits: int = 8
    lsb: int = 0
    size: int = 0
    """Bytes of the integer that holds the field (default: as many as ``bits`` need)."""
    little: bool = False
    signed: bool = False
    choices: Mapping[int, str] | None = None
    unit: str = ""
    scale: float = 1
    comment: str = ""
    mux: int | None = None
    is_mux: bool = False

    def start(self) -> int:
        """The DBC start bit: the least significant bit (Intel) or the most significant
        bit in DBC's sawtooth numbering (Motorola)."""
        size = self.size or max(1, (self.lsb + self.bits + 7) // 8)
        if self.little:
            return self.byte * 8 + self.lsb
        msb = self.lsb + self.bits - 1
        return (self.byte + size - 1 - msb // 8) * 8 + msb % 8


@dataclass(frozen=True)
class Layout:
    """The payload of one function (``length``: its longest DLC) and what it is."""

    function: Function
    stem: str
    length: int
    fields: tuple[Field, ...]
    comment: str


def _choices(enum: type[IntEnum]) -> dict[int, str]:
    return {int(v): v.name for v in enum}


FUNCTION_CHOICES = {int(f): f.label for f in Function} | {
    0xFF: "none", mca.PROCESS_DATA | Function.MCA_CONTROLLER_INPUT: "CI map frame"}
_FUNC_COMMENT = "function code of the frame it is about (0xFF: none, 0x8D: a CI map frame)"


def _bit(name: str, byte: int, bit: int, comment: str = "", mux: int | None = None) -> Field:
    return Field(name, byte, 1, bit, 1, comment=comment, mux=mux)


def _words(prefix: str, first_byte: int, count: int, *, little: bool = False,
           comment: str = "") -> tuple[Field, ...]:
    return tuple(Field(f"{prefix}{i}", first_byte + 2 * i, 16, little=little,
                       comment=comment) for i in range(count))


def _bytes(prefix: str, first_byte: int, count: int, *, offset: int = 0,
           mux: int | None = None, comment: str = "") -> tuple[Field, ...]:
    return tuple(Field(f"{prefix}{offset + i}", first_byte + i, mux=mux, comment=comment)
                 for i in range(count))


_VALUES_COMMENT = ("a raw byte of the values (big endian, each edge 2 or 4 bytes wide: its "
                   "width, sign and exponent are in its MCA DumpIO Descr record)")

LAYOUTS: tuple[Layout, ...] = (
    # ------------------------------------------------------------------ PC -> board
    Layout(Function.RESET, "Reset", 0, (), "Reset (0, PC -> board, DLC 0): warm reset; "
           "answered with Ready BOOT by a board that has a number."),
    Layout(Function.XRESET, "XReset", 0, (), "XReset (1, PC -> board, DLC 0): clear "
           "AutoStart, then reset."),
    Layout(Function.SET_STATUS, "SetStatus", 2, (
        Field("Op", 0, choices=_choices(StatusOp)),
        Field("Value", 1, comment="0/1; for SEQ_ID the new seq ID 1-31"),
    ), "SetStatus (7, PC -> board, DLC 2): answered with Ready STATUS."),
    Layout(Function.INFO_REQUEST, "InfoRequest", 0, (), "Info Request (8, PC -> board, "
           "DLC 0): answered with the 10 Info frames."),
    Layout(Function.REPORT_REQUEST, "ReportRequest", 6, (
        Field("Channel", 0, choices=_choices(ReportChannel)),
        Field("Space", 1, choices=_choices(Space)),
        Field("Address", 2, 16, comment="word address"),
        Field("Count", 4, 16, comment="words (MEMORY)"),
    ), "Report Request (9, PC -> board, DLC 6)."),
    Layout(Function.INIT_REQUEST, "InitRequest", 2, (
        Field("Op", 0, choices=_choices(InitOp)),
        Field("Number", 1, comment="NEXT: the seq ID searched (2-31); REJOIN: the seq ID "
                                   "given back (1-31)"),
    ), "Init Request (10, PC -> every board, DLC 2): one step of the init chain.  REJOIN "
       "(DLC 6) carries the serial number of the board it numbers in bytes 2-5, beyond this "
       "message: its Op and Number decode, the serial is not described."),
    Layout(Function.PROGRAM, "Program", 8, (
        Field("Words", 0, 64, little=True,
              comment="four program words, low byte first: word n is bits 16n+15..16n "
                      "(bytes 2n, 2n+1)"),
    ), "Program (11, PC -> boards).  Described: the data frame (DLC 8), four program "
       "words low byte first, at the slot given by identifier bits 5-0 (0x2C0 + slot) of "
       "the block the last BLOCK frame opened.  Not described: the control frames (DLC "
       "1-7: [0] op BEGIN, META, ERASE, PREPARE, BLOCK, END, ABORT, to the board in bits "
       "5-0).  A data frame's first byte is any value, so no payload field tells the two "
       "apart, and a DBC message has one length: strict decoding leaves a control frame "
       "undecoded, and the single 64-bit signal does not fit one, so a decoder that "
       "allows truncated frames shows it with no signals (ucom decode reads both)."),
    Layout(Function.START, "Start", 1, (Field("Target", 0, choices=_choices(Target)),),
           "Start (12, PC -> board, DLC 1): answered with Ready STARTED; a program then "
           "announces itself with a text report and an unsolicited MCA Ready."),
    # ------------------------------------------------------------------ board -> PC
    Layout(Function.ERROR, "Error", 6, (
        Field("Code", 0, choices=_choices(ErrorCode)),
        Field("Function", 1, choices=FUNCTION_CHOICES, comment=_FUNC_COMMENT),
        Field("Detail", 2, 32),
    ), "Error (2, board -> PC, DLC 6)."),
    Layout(Function.INIT_ACK, "InitAck", 8, (
        Field("Kind", 0, choices=_choices(InitAckKind)),
        Field("SeqID", 1, comment="0: none"),
        Field("FixedID", 2, comment="0: none"),
        Field("BootloaderMajor", 3, 4, 4),
        Field("BootloaderMinor", 3, 4, 0),
        Field("Serial", 4, 32),
    ), "Init Ack (3, board -> PC, DLC 8)."),
    Layout(Function.PROGRAM_FINISHED, "ProgramFinished", 8, (
        Field("Kind", 0, is_mux=True, choices=_choices(FinishedKind)),
        Field("Result_Status", 1, mux=FinishedKind.RESULT, choices=_choices(ResultStatus)),
        Field("Result_Reports", 2, 16, mux=FinishedKind.RESULT,
              comment="MISSING/PARTIAL frames that follow"),
        Field("Result_ProgID", 4, 32, mux=FinishedKind.RESULT),
        Field("Missing_FirstBlock", 1, 16, mux=FinishedKind.MISSING),
        Field("Missing_Count", 3, 16, mux=FinishedKind.MISSING),
        Field("Partial_Block", 1, 16, mux=FinishedKind.PARTIAL),
        Field("Partial_FirstSlot", 3, mux=FinishedKind.PARTIAL),
        Field("Partial_Count", 4, mux=FinishedKind.PARTIAL),
    ), "Program Finished (4, board -> PC): RESULT (DLC 8), MISSING and PARTIAL (DLC 5)."),
    Layout(Function.INFO, "Info", 8, (
        Field("Index", 0, is_mux=True, comment="frame 0-9 of the record"),
        Field("State", 1, mux=0, choices=_choices(BoardState)),
        _bit("AutoStart", 2, 0, mux=0), _bit("ProgEnable", 2, 1, mux=0),
        _bit("FlashValid", 2, 2, mux=0), _bit("ExtRamLoaded", 2, 3, mux=0),
        _bit("InitDone", 2, 4, mux=0),
        Field("SeqID", 3, mux=0), Field("FixedID", 4, mux=0),
        Field("BootloaderMajor", 5, mux=0), Field("BootloaderMinor", 6, mux=0),
        Field("ProgID", 1, 32, mux=1), Field("SizeWords", 5, 24, mux=1),
        Field("Year", 1, 16, mux=2, comment="programming date, UTC; 0: never programmed"),
        Field("Month", 3, mux=2), Field("Day", 4, mux=2), Field("Hour", 5, mux=2),
        Field("Minute", 6, mux=2), Field("Second", 7, mux=2),
        Field("Serial", 1, 32, mux=3), Field("Entry", 5, 16, mux=3),
        Field("Target", 7, mux=3, choices=_choices(Target)),
        *(f for i in range(4) for f in _bytes("NameChar", 1, 7, offset=7 * i, mux=4 + i,
                                               comment="program name, Latin-1")),
        Field("FpgaBoardID", 1, 4, 0, 2, mux=8, comment="version register 1, bits 3-0"),
        Field("FpgaAppID", 1, 7, 7, 2, mux=8, comment="version register 1, bits 13-7"),
        Field("FpgaMajor", 3, 6, 10, 2, mux=8, comment="version register 2, bits 15-10"),
        Field("FpgaMinor", 3, 6, 4, 2, mux=8, comment="version register 2, bits 9-4"),
        Field("MeasuredBoardID", 5, mux=8, comment="the plug-on board's; 15: none"),
        _bit("FpgaNeutral", 6, 0, mux=8),
        _bit("DescriptorPresent", 1, 0, mux=9), _bit("DescriptorCorrupt", 1, 1, mux=9),
        Field("DescBoardID", 2, mux=9), Field("DescAppID", 3, mux=9),
        Field("DescFpgaMajor", 4, mux=9), Field("DescFpgaMinor", 5, mux=9),
        Field("DescVersionMajor", 6, mux=9), Field("DescVersionMinor", 7, mux=9),
    ), "Info (5, board -> PC, DLC 8): one of the ten frames of the Info record, [0] its "
       "index (the multiplexer)."),
    Layout(Function.READY, "Ready", 8, (
        Field("Reason", 0, is_mux=True, choices=_choices(ReadyReason)),
        Field("State", 1, choices=_choices(BoardState)),
        Field("Boot_Serial", 4, 32, mux=ReadyReason.BOOT),
        Field("Erased_RingFrames", 2, 16, mux=ReadyReason.ERASED),
        Field("Erased_UsPerFrame", 4, 32, mux=ReadyReason.ERASED, unit="us"),
        Field("Pause_Buffered", 2, 16, mux=ReadyReason.PAUSE),
        Field("Resume_Buffered", 2, 16, mux=ReadyReason.RESUME),
        Field("Started_Target", 2, 16, mux=ReadyReason.STARTED, choices=_choices(Target)),
        Field("Status_Op", 2, mux=ReadyReason.STATUS, choices=_choices(StatusOp)),
        Field("Status_Value", 3, mux=ReadyReason.STATUS),
    ), "Ready (6, board -> PC, DLC 8): [0] reason (the multiplexer), [1] state, [2..3] "
       "value16, [4..7] value32."),
    Layout(Function.REPORT_0, "ReportStatus", 8, (
        Field("State", 0, choices=_choices(BoardState)),
        _bit("InitInDriven", 1, 0), _bit("InitInSet", 1, 1), _bit("InitOutDriven", 1, 2),
        _bit("InitOutSet", 1, 3),
        _bit("LedRed", 2, 0), _bit("LedYellow", 2, 1), _bit("LedGreen", 2, 2),
        _bit("LedGreenBlinks", 2, 3),
        Field("TxErrors", 3), Field("RxErrors", 4), Field("SeqID", 5),
        Field("Overruns", 6, 16),
    ), "Report 0 STATUS (16, board -> PC, DLC 8)."),
    Layout(Function.REPORT_1, "ReportMemory", 8, (
        Field("Address", 0, 16, comment="word address of Word0"),
        *_words("Word", 2, 3, little=True, comment="a memory word, low byte first"),
    ), "Report 1 MEMORY (17, board -> PC, DLC 4, 6 or 8): 1-3 words."),
    Layout(Function.REPORT_2, "ReportText", 8, (
        Field("Piece", 0, 7, 0), _bit("Last", 0, 7, "the message's last piece"),
        *_bytes("Char", 1, 7, comment="Latin-1"),
    ), "Report 2 TEXT (18, board -> PC, DLC 1-8): a piece of a text message."),
    Layout(Function.REPORT_3, "ReportApplication", 8, (
        Field("RunState", 0, choices=_choices(mca.RunState)),
        Field("Load", 1, 16, scale=0.1, unit="%"),
        Field("CycleTime", 3, 16, unit="us"),
        Field("Overruns", 5, 16),
        _bit("Overrun", 7, 0, "a cycle overran since the previous MCA Ready"),
        _bit("LatchedByWatchdog", 7, 1),
    ), "Report 3 APPLICATION (19, board -> PC, DLC 8): a running program's state and "
       "load."),
    # ------------------------------------------------------------------ run time
    Layout(Function.MCA_CONTROLLER_INPUT, "McaControllerInput", 8, (
        Field("FirstIndex", 0, comment="per-kind index of the first CI edge"),
        *_bytes("Data", 1, 7, offset=1, comment=_VALUES_COMMENT),
    ), "MCA Controller Input (13, generic: PC -> board, DLC 3-8): values of consecutive CI "
       "edges from FirstIndex; answered with MCA Ready."),
    Layout(Function.MCA_PARAMETER, "McaParameter", 8, (
        Field("FirstIndex", 0, comment="per-kind index of the first PAR edge"),
        *_bytes("Data", 1, 7, offset=1, comment=_VALUES_COMMENT),
    ), "MCA Parameter (15, PC -> board, DLC 3-8): values of consecutive PAR edges from "
       "FirstIndex; answered with MCA Ready."),
    Layout(Function.MCA_READY, "McaReady", 8, (
        Field("State", 0, choices=_choices(mca.RunState)),
        Field("Answers", 1, choices=FUNCTION_CHOICES,
              comment="the function acknowledged; 20: unsolicited, the program is up"),
        Field("Echo0", 2), Field("Echo1", 3),
        Field("CountCI", 4), Field("CountSO", 5), Field("CountPAR", 6),
        _bit("Overrun", 7, 0), _bit("LatchedByWatchdog", 7, 1),
    ), "MCA Ready (20, board -> PC, DLC 8)."),
    Layout(Function.MCA_START, "McaStart", 1, (
        Field("Op", 0, choices=_choices(mca.StartOp)),
    ), "MCA Start (21, PC -> board, DLC 1): answered with MCA Ready."),
    Layout(Function.MCA_DUMPIO_DESCR_REQUEST, "McaDescrRequest", 2, (
        Field("Kind", 0, choices=_choices(mca.Kind)), Field("Index", 1),
    ), "MCA DumpIO Descr Request (22, PC -> board, DLC 0: every edge, or 2: one)."),
    Layout(Function.MCA_DUMPIO_DESCR, "McaDescr", 8, (
        Field("Kind", 0, 2, 6, choices=_choices(mca.Kind)),
        _bit("Last", 0, 5, "the record's last segment"),
        Field("Segment", 0, 5, 0), Field("Index", 1),
        *_bytes("RecordByte", 2, 6, comment="record bytes 6 * Segment + n"),
    ), "MCA DumpIO Descr (23, board -> PC, DLC 3-8): a segment of an edge's record "
       "(format, exponent, range, name, unit)."),
    Layout(Function.MCA_DUMP_CI, "McaDumpCI", 3, (
        Field("Kind", 0, choices=_choices(mca.Kind)), Field("FirstIndex", 1),
        Field("Count", 2),
    ), "MCA Dump CI (24, PC -> board, DLC 3): answered with MCA DSP CI frames."),
    Layout(Function.MCA_ADMIN_DATA, "McaAdminData", 8, (
        Field("Op", 0, is_mux=True, choices=_choices(mca.AdminOp)),
        Field("Alive_TimeoutMs", 1, 16, mux=mca.AdminOp.ALIVE, unit="ms"),
        Field("SoMap_Map", 1, mux=mca.AdminOp.SO_MAP),
        Field("SoMap_Period", 2, 16, mux=mca.AdminOp.SO_MAP, unit="cycles",
              comment="0 deletes the map"),
        *_bytes("SoMap_Edge", 4, 4, mux=mca.AdminOp.SO_MAP,
                comment="SO edge index; 0xFF: none"),
        Field("CiMap_Map", 1, mux=mca.AdminOp.CI_MAP),
        *_bytes("CiMap_Slot", 2, 4, mux=mca.AdminOp.CI_MAP,
                comment="CI edge index this slot feeds on this board; 0xFF: not this "
                        "board's"),
    ), "MCA Admin Data (25, PC -> board, DLC 1-8): [0] op (the multiplexer); answered "
       "with MCA Ready."),
    Layout(Function.MCA_ALIVE, "McaAlive", 0, (), "MCA Alive (26, PC -> board or every "
           "board, DLC 0): restarts the boards' watchdog."),
    Layout(Function.MCA_DSP_CI, "McaDspCI", 8, (
        Field("Kind", 0, choices=_choices(mca.Kind)), Field("FirstIndex", 1),
        *_bytes("Data", 2, 6, offset=2, comment=_VALUES_COMMENT),
    ), "MCA DSP CI (27, board -> PC, DLC 4-8): values of consecutive edges from "
       "FirstIndex."),
)
"""Every generic message of the protocol, by function."""

_MASKED = "four 16-bit words as they travel: every byte XOR 0x55 (value = word XOR 0x5555)"
PROCESS_DATA = (
    Layout(Function.MCA_CONTROLLER_INPUT, "CiMap", 8, _words("MaskedSlot", 0, 4,
                                                             comment=_MASKED),
           "CI map (13, process data: identifier type 1 and the map number; PC -> boards, "
           "DLC 2-8): slot i (bytes 2i, 2i+1) feeds the CI edge a board's Admin Data "
           "CI_MAP gave it.  Raw: what a map carries depends on the CI_MAP frames sent at "
           "run time, and every byte travels XOR 0x55."),
    Layout(Function.MCA_SENSOR_OUTPUT, "SoMap", 8, _words("MaskedWord", 0, 4,
                                                          comment=_MASKED),
           "SO map (14, process data: identifier type 1 and the map number; one board -> "
           "PC, DLC 2-8): the values of the SO edges its Admin Data SO_MAP named, in that "
           "order.  Raw: what a map carries depends on the SO_MAP frame sent at run time, "
           "and every byte travels XOR 0x55."),
)
"""The process-data maps (raw)."""


# ============================================================================ messages
@dataclass(frozen=True)
class Entry:
    """One DBC message: an identifier, its name and its layout."""

    frame_id: int
    name: str
    layout: Layout
    sender: str
    who: str
    """'every board', 'seq ID 3', 'fixed ID 5', 'map 4', ..."""


def entries() -> list[Entry]:
    """Every message of the database, in identifier order."""
    out: list[Entry] = []
    generic = {Function.MCA_CONTROLLER_INPUT, Function.MCA_PARAMETER, Function.MCA_START,
               Function.MCA_DUMPIO_DESCR_REQUEST, Function.MCA_DUMP_CI,
               Function.MCA_ADMIN_DATA, Function.MCA_ALIVE, Function.MCA_READY,
               Function.MCA_DUMPIO_DESCR, Function.MCA_DSP_CI}
    for layout in LAYOUTS:
        fn = layout.function
        from_pc = fn.direction is Direction.HOST_TO_BOARD
        sender = PC if from_pc else BOARD
        base = int(fn) << 6
        if fn is Function.PROGRAM:
            for low in range(64):
                who = ("every ProgEnabled board" if low == 0 else
                       f"seq ID {low}" if low < 32 else f"fixed ID {low - 32}")
                out.append(Entry(base | low, f"Program_Slot{low}", layout, sender,
                                 f"control frames to {who}; data frames at slot {low}"))
            continue
        if from_pc:
            out.append(Entry(base, f"{layout.stem}_All", layout, sender, "every board"))
        elif fn is Function.INIT_ACK:
            out.append(Entry(base, f"{layout.stem}_Unnumbered", layout, sender,
                             "a board without a number"))
        for n in range(1, 32):
            out.append(Entry(base | n, f"{layout.stem}_{n}", layout, sender, f"seq ID {n}"))
        if fn in generic:  # the run time addresses boards by seq ID only
            continue
        for n in range(1, 32):
            out.append(Entry(base | 0x20 | n, f"{layout.stem}_F{n}", layout, sender,
                             f"fixed ID {n}"))
    for layout in PROCESS_DATA:
        sender = PC if layout.function is Function.MCA_CONTROLLER_INPUT else BOARD
        for n in range(1, 32):
            out.append(Entry((int(layout.function) << 6) | 0x20 | n, f"{layout.stem}_{n}",
                             layout, sender, f"map {n}"))
    return sorted(out, key=lambda e: e.frame_id)


def _need_cantools() -> None:
    try:
        import cantools  # noqa: F401
    except ImportError:
        raise InputError("the DBC export needs cantools: " + INSTALL_HINT) from None


def build() -> Database:
    """The database of every UCoM message (see the module docstring)."""
    _need_cantools()
    from cantools.database.can import Database, Message, Node, Signal
    from cantools.database.conversion import BaseConversion
    from cantools.database.namedsignalvalue import NamedSignalValue

    messages = []
    for entry in entries():
        layout = entry.layout
        receiver = BOARD if entry.sender == PC else PC
        mux_name = next((f.name for f in layout.fields if f.is_mux), None)
        signals = []
        for f in layout.fields:
            choices: OrderedDict[int, str | NamedSignalValue] | None = \
                OrderedDict(sorted(f.choices.items())) if f.choices else None
            conversion = BaseConversion.factory(scale=f.scale, offset=0, choices=choices,
                                                is_float=False)
            signals.append(Signal(
                f.name, f.start(), f.bits, "little_endian" if f.little else "big_endian",
                f.signed, conversion=conversion, unit=f.unit or None,
                comment=f.comment or None, receivers=[receiver],
                is_multiplexer=f.is_mux,
                multiplexer_ids=[int(f.mux)] if f.mux is not None else None,
                multiplexer_signal=mux_name if f.mux is not None else None,
                minimum=None, maximum=None))
        comment = f"{layout.comment}  Identifier 0x{entry.frame_id:03X}: {entry.who}."
        messages.append(Message(entry.frame_id, entry.name, layout.length, signals,
                                comment=comment, senders=[entry.sender],
                                is_extended_frame=False, strict=True))
    nodes = [Node(PC, comment="the host: ucom, dsp_console2can"),
             Node(BOARD, comment="a UCoM board (bootloader or running program)")]
    return Database(messages, nodes, version=f"ucom-tools {__version__}")


def dumps() -> str:
    """The database as DBC text."""
    db = build()
    text: str = db.as_dbc_string()
    return text


def write(path: str | os.PathLike[str], *, force: bool = False) -> int:
    """Write the DBC file by the rules of ``ucom(1)``, FILES (a regular file atomically,
    a device or FIFO written through, ``-`` standard output); an existing regular file
    only with ``force``.  Returns the number of messages."""
    target = Path(path)
    if os.fspath(path) == fileio.STDOUT:
        fileio.write_text(fileio.STDOUT, dumps(), encoding="cp1252", newline=None,
                          allow_stdout=True)
        return len(entries())
    if target.is_dir():
        raise InputError(f"{os.fspath(target)} is a directory", key="dbc_file")
    if not target.parent.is_dir():
        raise InputError(f"{os.fspath(target)}: directory {os.fspath(target.parent)} does "
                         "not exist", key="dbc_file")
    if target.is_file() and not force:
        raise OutputExists([os.fspath(target)], key="dbc_file")
    text = dumps()
    fileio.write_text(target, text, encoding="cp1252", newline=None, key="dbc_file",
                      allow_stdout=True)
    return len(entries())


def layout_of(function: Function) -> Layout:
    for layout in LAYOUTS:
        if layout.function is function:
            return layout
    raise KeyError(function)


def summary(layouts: Sequence[Layout] = LAYOUTS) -> list[str]:
    """One line per function: stem, length and signals (for documentation)."""
    return [f"{lay.stem} ({int(lay.function)}): {', '.join(f.name for f in lay.fields)}"
            for lay in layouts]


__all__ = ["INSTALL_HINT", "LAYOUTS", "PROCESS_DATA", "Entry", "Field", "Layout", "build",
           "dumps", "entries", "layout_of", "summary", "write"]
