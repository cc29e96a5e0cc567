"""The bootloader's services of a virtual UCoM besides the programming transfer and Start
(``man/ucom-protocol.7``): the init chain (numbering the boards one after the other
along their init pins, the probes for the first and the last board, Rejoin), Set Status,
and what the board says of itself (Info, and the status, application and memory report
channels).

A part of :class:`~ucom_tools.virtual.board.ucom.VirtualBoard`, which routes those
requests here and hands itself over as a
:class:`~ucom_tools.virtual.board.port.BootloaderHost`; the board keeps its pins and its
seq ID (the bus reads the pins, everyone the seq ID), this part the state of the chain.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Final

from ucom_tools.errors import FrameError
from ucom_tools.virtual.board import mutants
from ucom_tools.virtual.board.nvmem import NonVolatile
from ucom_tools.virtual.board.port import BootloaderHost
from ucom_tools.virtual.board.programming import BoardProgramming
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import (
    BoardState,
    ErrorCode,
    InitAckKind,
    InitOp,
    ReadyReason,
    ReportChannel,
    StatusOp,
    Target,
)
from ucom_tools.wire.fpga import Reg
from ucom_tools.wire.ids import Address, Function, IdType
from ucom_tools.wire.info import BoardInfo
from ucom_tools.wire.transfer import decode_date

BOOTLOADER_VERSION: Final = (1, 0)


class Bootloader:
    """The init chain, Set Status, Info and the reports of one virtual board."""

    def __init__(self, board: BootloaderHost, nv: NonVolatile, programming: BoardProgramming,
                 *, defect: str | None = None) -> None:
        self.board = board
        self.nv = nv
        self.programming = programming
        self.defect = defect
        """The board's defect (:mod:`~ucom_tools.virtual.board.mutants`), None if it conforms."""
        self.chain_active = False
        """An init chain is under way (from BEGIN to END, a reset or a program's start)."""
        self.claimed = False
        """seq-from-zero: the board took a number in this chain (its seq ID is one less)."""

    # ================================================================= init chain
    def init(self, msg: m.InitRequest, t: float) -> None:
        board = self.board
        settle = t + board.timing.settle_us
        if msg.op is InitOp.BEGIN:
            board.seq_id = 0
            self.claimed = False
            self.chain_active = True
            board.in_drive = False
            board.out_drive = True
            board.bus.at(settle, self._claim_if_first(1))
        elif msg.op is InitOp.NEXT:
            held = self._chain_number()
            if held == msg.number - 1 and self.chain_active:
                board.out_drive = False
            if self.chain_active and held == msg.number:
                self._init_ack(InitAckKind.ASSIGNED, settle)  # asked again: its ack was lost
            if self.chain_active and not held:
                board.bus.at(settle, self._claim_if_first(msg.number))
        elif msg.op is InitOp.END:
            self.chain_active = False
            board.in_drive = board.out_drive = False
        elif msg.op in (InitOp.PROBE_FIRST, InitOp.PROBE_LAST):
            first = msg.op is InitOp.PROBE_FIRST
            saved = (board.in_drive, board.out_drive)
            # first: drive the output, look at the input; last: the other way round
            board.in_drive, board.out_drive = not first, first
            board.bus.at(settle, self._probe(InitAckKind.FIRST if first else InitAckKind.LAST))
            board.bus.at(settle + 1.0, self._restore_pins(saved))
        elif msg.op is InitOp.REJOIN and msg.serial == board.identity.serial:
            # only the board it names takes it, in any state; no pin moves
            board.seq_id = msg.number
            self.claimed = False
            ack = m.InitAck(InitAckKind.ASSIGNED, msg.number, board.identity.fixed_id,
                            BOOTLOADER_VERSION[0] << 4 | BOOTLOADER_VERSION[1],
                            board.identity.serial)
            board.send(t + board.timing.reply_us, ack)

    def _claim_if_first(self, number: int) -> Callable[[float], None]:
        board = self.board

        def sample(t: float) -> None:
            if not board.powered or not self.chain_active or self._chain_number():
                return
            if board.bus.init_in_set(board.identity.position):
                return
            board.seq_id = number
            if self.defect == mutants.SEQ_FROM_ZERO:
                board.seq_id, self.claimed = number - 1, True
            self._init_ack(InitAckKind.ASSIGNED, t)
        return sample

    def _chain_number(self) -> int:
        """The number this board holds in the init chain: its seq ID (seq-from-zero:
        one more, once it has claimed one)."""
        if self.defect == mutants.SEQ_FROM_ZERO and self.claimed:
            return self.board.seq_id + 1
        return self.board.seq_id

    def _probe(self, kind: InitAckKind) -> Callable[[float], None]:
        board = self.board

        def sample(t: float) -> None:
            if not board.powered:
                return
            pos = board.identity.position
            free = (not board.bus.init_in_set(pos) if kind is InitAckKind.FIRST
                    else not board.bus.init_out_set(pos))
            if free:
                self._init_ack(kind, t)
        return sample

    def _restore_pins(self, saved: tuple[bool, bool]) -> Callable[[float], None]:
        board = self.board

        def restore(t: float) -> None:
            board.in_drive, board.out_drive = saved
        return restore

    def _init_ack(self, kind: InitAckKind, t: float) -> None:
        board = self.board
        ack = m.InitAck(kind, board.seq_id, board.identity.fixed_id, BOOTLOADER_VERSION[0] << 4
                        | BOOTLOADER_VERSION[1], board.identity.serial)
        addr = board.reply_address() or Address(IdType.SEQUENTIAL, 0)
        board.send(t + board.stagger_us, ack, address=addr)
        if self.defect == mutants.INIT_TWICE and kind is InitAckKind.ASSIGNED:
            board.send(t + board.stagger_us, ack, address=addr)

    # ================================================================= status
    def set_status(self, msg: m.SetStatus, t: float, via_fixed: bool) -> None:
        board = self.board
        op, value = msg.op, msg.value
        now = t
        if self.defect == mutants.LATE_ANSWER:
            t += mutants.LATE_US  # done at once, answered late (t only times the answers)
        if op is StatusOp.PROG_ENABLE:
            if board.runs_program:
                board.error(t, ErrorCode.RUNNING, Function.SET_STATUS, op, via_fixed)
                return
            if not value:
                self.programming.abort(now)  # cleared: a transfer under way ends as by ABORT
            self.programming.enabled = bool(value)
        elif op is StatusOp.AUTOSTART:
            if value and not self.nv.record.flash_valid:
                board.error(t, ErrorCode.NO_PROGRAM, Function.SET_STATUS, op, via_fixed)
                return
            self.nv.record.autostart = bool(value)
            board.persist(record_only=True)
        elif op is StatusOp.INIT_IN:
            board.in_drive = bool(value)
        elif op is StatusOp.INIT_OUT:
            if self.defect != mutants.IGNORE_INITOUT:
                board.out_drive = bool(value)
        elif op is StatusOp.SEQ_ID:
            board.seq_id = value
        board.send(t + board.timing.reply_us, m.Ready(ReadyReason.STATUS, board.state,
                                                      (op << 8) | value), via_fixed=via_fixed)

    # ================================================================= Info and reports
    def answer_info(self, t: float, via_fixed: bool) -> None:
        """Info Request: the Info record, sent at ``t`` (the board's reply time)."""
        info = self.info()
        if self.defect == mutants.INFO_SWAPPED:
            info = replace(info, serial=info.progid, progid=info.serial)
        if self.defect == mutants.LATE_ANSWER:
            t += mutants.LATE_US
        for frame in info.to_frames():
            self.board.send(t, frame, via_fixed=via_fixed)

    def report(self, msg: m.ReportRequest, t: float, via_fixed: bool) -> None:
        board, channel = self.board, msg.channel
        if channel is ReportChannel.STATUS:
            board.send(t, self.status_report(), via_fixed=via_fixed)
            return
        if channel is ReportChannel.APPLICATION:
            application = board.application_report()
            if application is not None:
                board.send(t, application, via_fixed=via_fixed)
                return
        elif channel is ReportChannel.MEMORY:
            words = board.read_memory(msg.space, msg.address, msg.count)
            if words is None:
                board.error(t, ErrorCode.UNMAPPED_ADDRESS, Function.REPORT_REQUEST,
                            (msg.space << 16) | msg.address, via_fixed)
                return
            for i in range(0, len(words), 3):
                board.send(t, m.MemoryReport(msg.address + i, tuple(words[i:i + 3])),
                           via_fixed=via_fixed)
            return
        board.error(t, ErrorCode.BAD_VALUE, Function.REPORT_REQUEST, channel, via_fixed)

    def status_report(self) -> m.StatusReport:
        board = self.board
        pins = board.pins()
        leds = board.leds()
        pin_bits = (pins["in_driven"] | pins["in_set"] << 1 | pins["out_driven"] << 2
                    | pins["out_set"] << 3)
        led_bits = ((leds["red"] == "on") | (leds["yellow"] == "on") << 1
                    | (leds["green"] != "off") << 2 | (leds["green"] == "blink") << 3)
        return m.StatusReport(board.state, pin_bits, led_bits, 0, min(board.can_errors, 0xFF),
                              board.seq_id, min(self.programming.overruns, 0xFFFF))

    def info(self) -> BoardInfo:
        board = self.board
        rec = self.nv.record
        ext = self.programming.extram
        # the running program, else a loaded ExtRAM program, else the flash program
        if ext is not None and board.state is not BoardState.RUNNING_FLASH:
            progid, size, name, entry, date = (ext.progid, ext.size_words, ext.name, ext.entry,
                                               ext.date)
            target = Target.EXTRAM
        else:
            progid, size, name, entry, date = (rec.progid, rec.size_words, rec.name, rec.entry,
                                               rec.date)
            target = Target.FLASH
        try:
            desc, corrupt = board.descriptor(target), False
        except FrameError:
            desc, corrupt = None, True
        if desc is not None:
            desc = replace(desc, name="")  # the name does not travel in Info
        fpga = board.fpga
        return BoardInfo(board.state, rec.autostart, self.programming.enabled, rec.flash_valid,
                         ext is not None, board.seq_id, board.identity.fixed_id,
                         BOOTLOADER_VERSION, progid, size, decode_date(date) if date else None,
                         board.identity.serial, entry, target, name,
                         fpga.read(Reg.VERSION1), fpga.read(Reg.VERSION2),
                         fpga.read(Reg.BOARD_ID), fpga.neutral, desc, corrupt)
