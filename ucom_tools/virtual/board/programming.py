"""Board side of the programming transfer: the Program frames a virtual UCoM takes.

BEGIN clears the program-valid and AutoStart flags (non-volatile) before anything is
erased; PREPARE checks that the preamble is complete, erases the listed pages one after
the other and answers Ready(ERASED) (a repeated PREPARE asks again); data frames go
through the flow-controlled receive ring of :class:`~ucom_tools.virtual.board.receiver.Reception`
(Ready PAUSE/RESUME) into the block their slot names; END verifies the stored words
against the ProgID and answers Program Finished with what is missing, committing the
program only when it verified.  ABORT, or ProgEnable cleared, ends a transfer at any step;
during the erase the erase stops after its page (``man/ucom-protocol.7``, PROGRAMMING,
Abort).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Final

from ucom_tools.virtual.board import mutants
from ucom_tools.virtual.board.nvmem import ExtRamProgram, NonVolatile, external_ram
from ucom_tools.virtual.board.port import BoardPort
from ucom_tools.virtual.board.receiver import BlockState, Reception, RejectedBlock
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import (
    BoardState,
    ErrorCode,
    MetaField,
    PrepareLack,
    ReadyReason,
    ResultStatus,
    Space,
    Target,
    prepare_lack,
)
from ucom_tools.wire.ids import Function
from ucom_tools.wire.transfer import bytes_to_words

_PROGRAM: Final = int(Function.PROGRAM)


class BoardProgramming:
    """The programming part of one virtual board's bootloader."""

    def __init__(self, port: BoardPort, nv: NonVolatile, *, defect: str | None = None) -> None:
        self.port = port
        self.nv = nv
        self.defect = defect
        """The board's defect (:mod:`~ucom_tools.virtual.board.mutants`), None if it conforms."""
        self.enabled = False
        """ProgEnable (SetStatus): broadcast Program frames are taken only when set."""
        self.reception: Reception | None = None
        self.finished: m.ProgramResult | None = None
        """The RESULT of the last verified transfer, repeated for an addressed END."""
        self.extram: ExtRamProgram | None = None
        self.overruns = 0

    # ------------------------------------------------------------------ state
    def drop(self, t: float | None = None) -> None:
        """Reset or power loss at board time ``t``: the transfer, ProgEnable and ExtRAM are
        gone; an erase under way ends after the page it was erasing."""
        rx = self.reception
        if rx is not None and rx.prepared and not rx.erased and t is not None:
            self._erase_pages(rx, t)
        self.enabled = False
        self.reception = None
        self.finished = None
        self.extram = None

    def state(self) -> BoardState | None:
        """ERASING or RECEIVING while a transfer is under way, else None."""
        rx = self.reception
        if rx is None or not rx.prepared:
            return None
        return BoardState.RECEIVING if rx.erased else BoardState.ERASING

    @property
    def busy(self) -> bool:
        return self.reception is not None

    # ------------------------------------------------------------------ frames
    def handle(self, msg: m.BootMessage, t: float, *, addressed: bool, via_fixed: bool) -> None:
        """A Program control frame for this board (broadcast or addressed to it)."""
        port = self.port
        if not self.enabled:
            if isinstance(msg, m.ProgramEnd) and addressed and self.finished is not None:
                port.send(t + port.timing.reply_us, self.finished, via_fixed=via_fixed)
            elif addressed:
                port.error(t, ErrorCode.NOT_ENABLED, _PROGRAM, via_fixed=via_fixed)
            return
        rx = self.reception
        if isinstance(msg, m.ProgramBegin):
            self._begin(msg, t)
            return
        if isinstance(msg, m.ProgramAbort):
            self.abort(t)
            return
        if rx is None:
            if isinstance(msg, m.ProgramPrepare | m.ProgramEnd):
                port.error(t, ErrorCode.SEQUENCE, _PROGRAM, prepare_lack(PrepareLack.NO_BEGIN),
                           via_fixed)
            return  # the rest of a preamble whose BEGIN was lost
        if isinstance(msg, m.ProgramMeta):
            rx.meta[msg.field] = msg.value
        elif isinstance(msg, m.ProgramErase):
            if rx.target is Target.FLASH and not rx.prepared:
                try:
                    rx.add_erase(msg)
                except RejectedBlock as err:
                    port.error(t, err.code, _PROGRAM, err.detail, via_fixed)
        elif isinstance(msg, m.ProgramPrepare):
            self._prepare(rx, msg, t, via_fixed)
        elif isinstance(msg, m.ProgramBlock):
            if not rx.erased:
                port.error(t, ErrorCode.BUSY, _PROGRAM, msg.index, via_fixed)
                return
            try:
                rx.open_block(msg)
            except RejectedBlock as err:
                port.error(t, err.code, _PROGRAM, err.detail, via_fixed)
        elif isinstance(msg, m.ProgramEnd):
            port.at(max(t, rx.free_at) + rx.stored_words() * port.timing.verify_word_us,
                    self._finish(rx, via_fixed))

    def other_block(self) -> None:
        """A BLOCK frame addressed to another board: its data frames are not ours."""
        if self.reception is not None:
            self.reception.current = None

    def data(self, slot: int, data: bytes, t: float) -> None:
        """A data frame (slot from the identifier) while a transfer is under way."""
        rx = self.reception
        assert rx is not None
        if not rx.erased:
            rx.overruns += 1
            return
        before = rx.overruns
        block = rx.take_data(slot, data, t)
        if rx.overruns != before:
            self.overruns += 1
        elif block is not None:
            self._store(rx, block)
        if not rx.paused and rx.free_at - t >= rx.pause_time:
            self._pace(rx, t)

    def abort(self, t: float) -> None:
        """ABORT, or ProgEnable cleared, at board time ``t``: the transfer ends, whatever
        its step.  An erase under way stops after the page it is erasing (a page erase
        cannot be cut); the program-valid flag BEGIN cleared stays cleared."""
        rx = self.reception
        if rx is None:
            return
        self.reception = None
        if rx.prepared and not rx.erased:
            self._erase_pages(rx, t)

    # ------------------------------------------------------------------ steps
    def _begin(self, msg: m.ProgramBegin, t: float) -> None:
        old = self.reception
        if old is not None and old.prepared and not old.erased:
            self._erase_pages(old, t)  # the erase under way ends after its page
        self.reception = Reception(msg.target, msg.blocks, msg.entry, self.port.timing)
        self.finished = None
        rec = self.nv.record
        if msg.target is Target.FLASH and (rec.flash_valid or rec.autostart):
            # From here on a power loss must leave no startable program behind.
            rec.flash_valid = False
            rec.autostart = False
            self.port.persist(record_only=True)

    def _prepare(self, rx: Reception, msg: m.ProgramPrepare, t: float, via_fixed: bool) -> None:
        port = self.port
        if rx.erased:
            self._send_erased(rx, t + port.timing.reply_us)
            return
        if rx.prepared:
            return  # still erasing: Ready(ERASED) follows when done
        detail = None
        if not rx.meta_complete():
            detail = prepare_lack(PrepareLack.META_INCOMPLETE, rx.meta_lacking())
        elif rx.target is Target.FLASH and len(rx.erase_pages) != msg.pages:
            detail = prepare_lack(PrepareLack.ERASE_INCOMPLETE, len(rx.erase_pages))
        if detail is not None:
            port.error(t, ErrorCode.SEQUENCE, _PROGRAM, detail, via_fixed)
            return
        rx.prepared = True
        if rx.target is Target.EXTRAM:
            rx.extram = external_ram()
        else:
            rx.erase_start = t  # the pages are erased one after the other from now
        port.at(t + rx.erase_time(), self._erased(rx))

    def _erase_pages(self, rx: Reception, t: float | None) -> None:
        """Erase the pages of ``rx``'s list the erase has begun by board time ``t`` (None:
        all of them, the erase is done) and not erased yet."""
        if rx.target is not Target.FLASH:
            return
        upto = len(rx.erase_pages) if t is None else rx.pages_begun(t)
        if upto <= rx.pages_erased:
            return
        for space, page in rx.erase_pages[rx.pages_erased:upto]:
            self.nv.erase_page(space, page)
        rx.pages_erased = upto
        if t is not None:  # cut short: what was erased stays so
            self.port.persist()

    def _erased(self, rx: Reception) -> Callable[[float], None]:
        def erased(t: float) -> None:
            if self.reception is not rx or not self.port.powered:
                return  # aborted, begun again or reset meanwhile
            self._erase_pages(rx, None)
            rx.erased = True
            rx.free_at = t
            self._send_erased(rx, t)
        return erased

    def _send_erased(self, rx: Reception, t: float) -> None:
        self.port.send(t, m.Ready(ReadyReason.ERASED, BoardState.RECEIVING,
                                  self.port.timing.rx_capacity, int(rx.frame_cost + 0.999)))

    def _store(self, rx: Reception, block: BlockState) -> None:
        h = block.header
        words = bytes_to_words(bytes(block.data))
        if rx.target is Target.FLASH:
            if not self.nv.space(h.space).program(h.address, words):
                rx.failed_words += 1
        else:
            rx.extram[h.space].write(h.address, words)
        block.stored = True
        if rx.current is block:
            rx.current = None

    def _pace(self, rx: Reception, t: float) -> None:
        timing = self.port.timing
        backlog = rx.backlog(t)
        if backlog >= timing.high_water:
            rx.paused = True
            self.port.send(t + timing.reply_us, m.Ready(ReadyReason.PAUSE, BoardState.RECEIVING,
                                                        int(backlog)))
            self.port.at(rx.free_at - timing.low_water * rx.frame_cost, self._maybe_resume)

    def _maybe_resume(self, t: float) -> None:
        rx = self.reception
        timing = self.port.timing
        if rx is None or not rx.paused or not self.port.powered:
            return
        if rx.backlog(t) > timing.low_water + 1e-6:
            self.port.at(rx.free_at - timing.low_water * rx.frame_cost, self._maybe_resume)
            return
        rx.paused = False
        self.port.send(t, m.Ready(ReadyReason.RESUME, BoardState.RECEIVING, int(rx.backlog(t))))

    def _finish(self, rx: Reception, via_fixed: bool) -> Callable[[float], None]:
        def finish(t: float) -> None:
            if self.reception is not rx or not self.port.powered:
                return  # aborted, begun again or reset meanwhile
            memory = rx.extram if rx.target is Target.EXTRAM else {
                s: self.nv.space(s) for s in Space}
            result, reports = rx.result(memory)
            self.overruns += rx.overruns
            rx.overruns = 0
            if self.defect == mutants.WRONG_PROGID and result.status is ResultStatus.VERIFIED:
                result = replace(result, progid=(result.progid + 1) & 0xFFFFFFFF)
            if result.status is ResultStatus.VERIFIED or (
                    self.defect == mutants.ACCEPT_BAD_PROGID
                    and result.status is ResultStatus.PROGID_MISMATCH):
                self._commit(rx)
                self.finished = result
            self.port.send(t, result, via_fixed=via_fixed)
            for report in reports:
                self.port.send(t, report, via_fixed=via_fixed)
        return finish

    def _commit(self, rx: Reception) -> None:
        meta = rx.meta
        size = int.from_bytes(meta.get(MetaField.SIZE, bytes(4)), "big")
        date = int.from_bytes(meta.get(MetaField.DATE, bytes(4)), "big")
        name = b"".join(meta.get(MetaField.NAME_0 + i, b"") for i in range(7))
        name_s = name.rstrip(b"\0").decode("latin-1")
        progid = rx.expected_progid()
        if self.defect == mutants.WRONG_PROGID:
            progid = (progid + 1) & 0xFFFFFFFF
        if rx.target is Target.FLASH:
            rec = self.nv.record
            rec.flash_valid = True
            rec.progid, rec.size_words, rec.date, rec.name, rec.entry = (progid, size, date,
                                                                         name_s, rx.entry)
            self.port.persist()
        else:
            self.extram = ExtRamProgram(rx.extram, progid, size, name_s, rx.entry, date)
        self.reception = None
        self.enabled = False
