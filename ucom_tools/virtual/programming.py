"""Board side of the programming transfer: the Program frames a virtual UCoM takes.

BEGIN clears the program-valid and AutoStart flags (non-volatile) before anything is
erased; PREPARE erases the listed pages and answers Ready(ERASED); data frames go
through the flow-controlled receive ring of :class:`~ucom_tools.virtual.receiver.Reception`
(Ready PAUSE/RESUME); END verifies the stored words against the ProgID and answers
Program Finished, committing the program only when it verified.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ucom_tools.virtual.nvmem import external_ram
from ucom_tools.virtual.receiver import Reception, RejectedBlock
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import (
    BoardState,
    ErrorCode,
    MetaField,
    ReadyReason,
    ResultStatus,
    Space,
    Target,
)
from ucom_tools.wire.ids import Function
from ucom_tools.wire.transfer import bytes_to_words

if TYPE_CHECKING:
    from ucom_tools.virtual.board import VirtualBoard

_PROGRAM = int(Function.PROGRAM)


class BoardProgramming:
    """The programming part of one virtual board's bootloader."""

    def __init__(self, board: VirtualBoard) -> None:
        self.board = board

    def handle(self, msg: m.BootMessage, t: float) -> None:
        b = self.board
        rx = b.reception
        if isinstance(msg, m.ProgramBegin):
            b.reception = Reception(msg.target, msg.blocks, msg.entry, b.timing)
            b.state = BoardState.BOOTLOADER
            if msg.target is Target.FLASH and b.nv.record.flash_valid:
                # From here on a power loss must leave no startable program behind.
                b.nv.record.flash_valid = False
                b.nv.record.autostart = False
                b.persist(record_only=True)
            return
        if isinstance(msg, m.ProgramAbort):
            b.reception = None
            b.state = BoardState.BOOTLOADER
            return
        if rx is None:
            b.error(t, ErrorCode.SEQUENCE, _PROGRAM)
            return
        if isinstance(msg, m.ProgramMeta):
            rx.meta[msg.field] = msg.value
        elif isinstance(msg, m.ProgramErase):
            if rx.target is Target.FLASH:
                try:
                    rx.add_erase(msg)
                except RejectedBlock as err:
                    b.error(t, err.code, _PROGRAM, err.detail)
        elif isinstance(msg, m.ProgramPrepare):
            b.state = BoardState.ERASING
            if rx.target is Target.EXTRAM:
                rx.extram = external_ram()
            else:
                for space, page in rx.erase_pages:
                    b.nv.erase_page(space, page)
            done = t + rx.erase_time()
            b.bus.at(done, self.erased)
        elif isinstance(msg, m.ProgramBlock):
            if not rx.erased:
                b.error(t, ErrorCode.BUSY, _PROGRAM, msg.index)
                return
            try:
                rx.open_block(msg)
            except RejectedBlock as err:
                b.error(t, err.code, _PROGRAM, err.detail)
        elif isinstance(msg, m.ProgramEnd):
            b.bus.at(max(t, rx.free_at) + rx.size_hint() * b.timing.verify_word_us,
                     self.finish)

    def erased(self, t: float) -> None:
        b = self.board
        rx = b.reception
        if rx is None or not b.powered:
            return
        rx.erased = True
        rx.free_at = t
        b.state = BoardState.RECEIVING
        b.send(t, m.Ready(ReadyReason.ERASED, b.state, b.timing.rx_capacity,
                          int(rx.frame_cost + 0.999)))

    def data(self, data: bytes, t: float) -> None:
        b = self.board
        rx = b.reception
        assert rx is not None
        if not rx.erased:
            rx.overruns += 1
            return
        accepted, payload = rx.take_data(data, t)
        if not accepted:
            b.overruns += 1
        elif payload is not None and rx.current is not None:
            block = rx.current
            rx.current = None
            if not rx.skip_current:
                words = bytes_to_words(payload)
                if rx.target is Target.FLASH:
                    if not b.nv.space(block.space).program(block.address, words):
                        rx.failed_words += 1
                else:
                    rx.extram[block.space].write(block.address, words)
                rx.received[block.index] = (block.space, block.address, len(words))
        if rx.paused or rx.free_at - t < b.timing.high_water * rx.frame_cost:
            return
        backlog = rx.backlog(t)
        if backlog >= b.timing.high_water:
            rx.paused = True
            b.send(t + b.timing.reply_us, m.Ready(ReadyReason.PAUSE, b.state, int(backlog)))
            b.bus.at(rx.free_at - b.timing.low_water * rx.frame_cost, self.maybe_resume)

    def maybe_resume(self, t: float) -> None:
        b = self.board
        rx = b.reception
        if rx is None or not rx.paused or not b.powered:
            return
        if rx.backlog(t) > b.timing.low_water + 1e-6:
            b.bus.at(rx.free_at - b.timing.low_water * rx.frame_cost, self.maybe_resume)
            return
        rx.paused = False
        b.send(t, m.Ready(ReadyReason.RESUME, b.state, int(rx.backlog(t))))

    def finish(self, t: float) -> None:
        b = self.board
        rx = b.reception
        if rx is None or not b.powered:
            return
        memory = rx.extram if rx.target is Target.EXTRAM else {s: b.nv.space(s) for s in Space}
        result, missing = rx.result(memory)
        b.overruns += rx.overruns
        rx.overruns = 0
        if result.status is ResultStatus.VERIFIED:
            self.commit(rx)
        b.send(t, result)
        for run in missing:
            b.send(t, run)

    def commit(self, rx: Reception) -> None:
        b = self.board
        meta = rx.meta
        size = int.from_bytes(meta.get(MetaField.SIZE, bytes(4)), "big")
        date = int.from_bytes(meta.get(MetaField.DATE, bytes(4)), "big")
        name = b"".join(meta.get(MetaField.NAME_0 + i, b"") for i in range(7))
        name_s = name.rstrip(b"\0").decode("latin-1")
        progid = rx.expected_progid()
        if rx.target is Target.FLASH:
            rec = b.nv.record
            rec.flash_valid = True
            rec.progid, rec.size_words, rec.date, rec.name, rec.entry = (progid, size, date,
                                                                         name_s, rx.entry)
            b.persist()
        else:
            b.extram = rx.extram
            b.extram_meta = (progid, size, name_s, rx.entry, date)
        b.reception = None
        b.prog_enable = False
        b.state = BoardState.BOOTLOADER

