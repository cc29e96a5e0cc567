"""Enumerated field values of the UCoM protocol payloads (see ``man/ucom-protocol.7``)."""

from __future__ import annotations

from enum import IntEnum


class ErrorCode(IntEnum):
    """Byte 0 of an Error message."""

    UNKNOWN_FUNCTION = 0x01
    BAD_LENGTH = 0x02
    BAD_VALUE = 0x03
    NOT_ENABLED = 0x04
    PROTECTED_ADDRESS = 0x05
    UNMAPPED_ADDRESS = 0x06
    NO_PROGRAM = 0x07
    FLASH_FAILURE = 0x08
    SEQUENCE = 0x09
    BUSY = 0x0A
    OVERRUN = 0x0B
    NOT_RUNNING = 0x0C
    RUNNING = 0x0D
    INCOMPATIBLE = 0x0E
    VERSION_MISMATCH = 0x0F
    WATCHDOG = 0x10
    UNKNOWN_EDGE = 0x11
    OUT_OF_RANGE = 0x12
    LATCHED = 0x13
    BAD_MAP = 0x14

    @property
    def text(self) -> str:
        return ERROR_TEXT[self]


ERROR_TEXT = {
    ErrorCode.UNKNOWN_FUNCTION: "function not handled in this state",
    ErrorCode.BAD_LENGTH: "payload length does not fit the function",
    ErrorCode.BAD_VALUE: "a payload field has a reserved or out-of-range value",
    ErrorCode.NOT_ENABLED: "programming is not enabled on this board (SetProgEnable)",
    ErrorCode.PROTECTED_ADDRESS: "address belongs to the bootloader (reset vectors, boot flash, "
                                 "bootloader record)",
    ErrorCode.UNMAPPED_ADDRESS: "address is not programmable memory",
    ErrorCode.NO_PROGRAM: "no complete, verified program in the chosen memory",
    ErrorCode.FLASH_FAILURE: "flash erase or program failed",
    ErrorCode.SEQUENCE: "message out of sequence (e.g. a block without Begin)",
    ErrorCode.BUSY: "board is busy (erasing) and cannot take this command now",
    ErrorCode.OVERRUN: "overrun: frames were lost, or a program cycle ran late",
    ErrorCode.NOT_RUNNING: "no application runs on this board",
    ErrorCode.RUNNING: "a program runs: reset the board into its bootloader first",
    ErrorCode.INCOMPATIBLE: "the DSP program does not fit this board (Board-ID or App-ID); "
                            "the program ended",
    ErrorCode.VERSION_MISMATCH: "the DSP program was built for another FPGA major version; "
                                "the program aborted and the board reset",
    ErrorCode.WATCHDOG: "no MCA Alive within the watchdog time: every motor stopped; "
                        "latched until MCA Start",
    ErrorCode.UNKNOWN_EDGE: "no such edge in this program (the frame was ignored)",
    ErrorCode.OUT_OF_RANGE: "a value outside its edge's range (the frame was ignored)",
    ErrorCode.LATCHED: "controller input refused: the watchdog stopped the board; "
                       "MCA Start releases it",
    ErrorCode.BAD_MAP: "a process-data map that cannot be used (edges, kinds, widths)",
}


class BoardState(IntEnum):
    """State of a board's firmware (the bootloader's state machine)."""

    BOOTLOADER = 0
    ERASING = 1
    RECEIVING = 2
    RUNNING_FLASH = 3
    RUNNING_EXTRAM = 4

    @property
    def text(self) -> str:
        return {
            BoardState.BOOTLOADER: "bootloader",
            BoardState.ERASING: "erasing",
            BoardState.RECEIVING: "receiving",
            BoardState.RUNNING_FLASH: "running (flash)",
            BoardState.RUNNING_EXTRAM: "running (ExtRAM)",
        }[self]


class InitOp(IntEnum):
    """Byte 0 of an Init Request."""

    BEGIN = 0x01
    NEXT = 0x02
    END = 0x03
    PROBE_FIRST = 0x04
    PROBE_LAST = 0x05
    REJOIN = 0x06
    """Give seq ID ``number`` back to the board with ``serial`` (DLC 6), a board that lost
    its number (power loss, reset) while the others keep theirs: no init line is used."""


class InitAckKind(IntEnum):
    """Byte 0 of an Init Ack."""

    ASSIGNED = 0x00
    FIRST = 0x01
    LAST = 0x02


class ReadyReason(IntEnum):
    """Byte 0 of a Ready message."""

    BOOT = 0x00
    ERASED = 0x01
    PAUSE = 0x02
    RESUME = 0x03
    STARTED = 0x04
    STATUS = 0x05


class StatusOp(IntEnum):
    """Byte 0 of a SetStatus message."""

    PROG_ENABLE = 0x01
    AUTOSTART = 0x02
    INIT_IN = 0x03
    INIT_OUT = 0x04
    SEQ_ID = 0x05


class Target(IntEnum):
    """Where a program is stored or started from."""

    FLASH = 0
    EXTRAM = 1


class Space(IntEnum):
    """DSP56F803 memory space (Harvard architecture)."""

    P = 0
    X = 1


class ProgramOp(IntEnum):
    """Byte 0 of a Program control frame (DLC < 8); DLC 8 frames are data."""

    BEGIN = 0x01
    META = 0x02
    ERASE = 0x03
    PREPARE = 0x04
    BLOCK = 0x05
    END = 0x06
    ABORT = 0x07


class MetaField(IntEnum):
    """Byte 1 of a Program META frame."""

    PROGID = 0
    SIZE = 1
    DATE = 2
    NAME_0 = 3  # NAME_0 .. NAME_0+6: program name, 4 characters each (28 in all)


NAME_CHUNKS = 7
NAME_LENGTH = 4 * NAME_CHUNKS


class ResultStatus(IntEnum):
    """Byte 1 of a Program Finished RESULT frame."""

    VERIFIED = 0
    MISSING = 1
    PROGID_MISMATCH = 2
    FLASH_FAILURE = 3
    NO_TRANSFER = 4

    @property
    def text(self) -> str:
        return {
            ResultStatus.VERIFIED: "verified",
            ResultStatus.MISSING: "blocks missing",
            ResultStatus.PROGID_MISMATCH: "ProgID mismatch",
            ResultStatus.FLASH_FAILURE: "flash failure",
            ResultStatus.NO_TRANSFER: "no transfer in progress",
        }[self]


class FinishedKind(IntEnum):
    """Byte 0 of a Program Finished frame."""

    RESULT = 0x00
    MISSING = 0x01
    PARTIAL = 0x02


class PrepareLack(IntEnum):
    """What a board lacks of the preamble, said by the Error SEQUENCE it answers PREPARE
    (or END) with (ucom-protocol(7), PROGRAMMING: "says what it lacks"): bits 31-24 of its
    detail; bits 15-0 say more (:func:`prepare_lack`)."""

    NO_BEGIN = 1
    """No transfer: BEGIN did not arrive (or the board finished it)."""
    META_INCOMPLETE = 2
    """A META frame is missing."""
    ERASE_INCOMPLETE = 3
    """The ERASE frames name fewer pages than PREPARE announces."""


def prepare_lack(lack: PrepareLack, info: int = 0) -> int:
    """The Error detail for a PREPARE that cannot be carried out: ``lack`` in bits
    31-24; ``info`` in bits 15-0: the META fields lacking (bit i = field i) for
    META_INCOMPLETE, the pages the board holds in its erase list for ERASE_INCOMPLETE."""
    return (int(lack) << 24) | (info & 0xFFFF)


def split_prepare_lack(detail: int) -> tuple[PrepareLack | None, int]:
    try:
        return PrepareLack(detail >> 24), detail & 0xFFFF
    except ValueError:
        return None, detail & 0xFFFF


class CheckField(IntEnum):
    """What an INCOMPATIBLE / VERSION_MISMATCH error is about (its detail's top byte)."""

    FPGA_BOARD_ID = 1
    PLUG_BOARD_ID = 2
    APP_ID = 3
    FPGA_MAJOR = 4
    FPGA_MINOR = 5

    @property
    def text(self) -> str:
        return {
            CheckField.FPGA_BOARD_ID: "FPGA Board-ID",
            CheckField.PLUG_BOARD_ID: "plug-on Board-ID",
            CheckField.APP_ID: "App-ID",
            CheckField.FPGA_MAJOR: "FPGA major version",
            CheckField.FPGA_MINOR: "FPGA minor version",
        }[self]


class ReportChannel(IntEnum):
    """Report functions 16-19 (100XX): XX is the channel."""

    STATUS = 0
    MEMORY = 1
    TEXT = 2
    APPLICATION = 3
