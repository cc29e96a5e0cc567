"""Decoding the programming transfer: the preamble, blocks and their data frames, resends,
END and the boards' results."""

from __future__ import annotations

from ucom_tools.trace.bus import (
    BusState,
)
from ucom_tools.trace.conversation import (
    PC_TO_BOARD,
)
from ucom_tools.trace.state import (
    Transfer,
)
from ucom_tools.trace.text import (
    _meta_fields,
    _meta_text,
    _ranges,
    _to,
)
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import (
    ReadyReason,
    ResultStatus,
)
from ucom_tools.wire.ids import Function


class ProgramDecoding(BusState):
    """Programming as progress (a part of :class:`BusDecoder`)."""

    def _program(self, msg: m.ProgramFrame, target: str | None) -> None:
        """A Program frame (``target``: the board a control frame addressed; None:
        broadcast, as the host normally sends them)."""
        if isinstance(msg, m.ProgramData):
            self._data(msg)
            return
        tr = self.transfer
        t = self.owner.timeouts
        if isinstance(msg, m.ProgramBegin):
            self._end_block()
            text = (f"BEGIN {msg.target.name.lower()}, {msg.blocks} blocks, entry "
                    f"P:{msg.entry:04X}")
            tr = self.transfer = Transfer(self.add("all", "Program", text, {
                "op": "BEGIN", "target": msg.target, "blocks": msg.blocks,
                "entry": msg.entry}, direction=PC_TO_BOARD), msg)
            tr.boards = {b.label for b in self.boards.values() if b.prog_enabled}
            return
        if isinstance(msg, m.ProgramMeta):
            if tr is not None:
                tr.meta[msg.field] = msg.value
                tr.msg.fields.update(_meta_fields(tr.meta))
            self.add("all", "Program", "META " + _meta_text(msg), {
                "op": "META", "field": msg.field, "value": msg.value}, direction=PC_TO_BOARD)
            return
        if isinstance(msg, m.ProgramErase):
            last = msg.first_page + msg.count - 1
            self.add("all", "Program", f"ERASE {msg.space.name}: pages {msg.first_page}-"
                     f"{last} ({msg.count})", {"op": "ERASE", "space": msg.space,
                     "first_page": msg.first_page, "count": msg.count},
                     direction=PC_TO_BOARD)
            return
        if isinstance(msg, m.ProgramPrepare):
            self.add(target or "all", "Program", f"PREPARE ({msg.pages} pages)", {
                "op": "PREPARE", "pages": msg.pages}, direction=PC_TO_BOARD)
            targets = [target] if target else \
                sorted(tr.boards - tr.verified) if tr is not None else []
            for b in targets or [None]:  # type: ignore[list-item]
                self.expect(f"Program PREPARE ({msg.pages} pages)" +
                            _to(b or "all"), Function.PROGRAM, b,
                            t.reply + msg.pages * t.erase_per_page,
                            lambda _b, a: isinstance(a, m.Ready) and
                            a.reason is ReadyReason.ERASED, key=("prepare",))
            return
        if isinstance(msg, m.ProgramBlock):
            self._block(msg)
            return
        if isinstance(msg, m.ProgramEnd):
            self._end_block()
            if tr is None:
                self.add(target or "all", "Program", "END (no transfer begun in the trace)",
                         {"op": "END"}, direction=PC_TO_BOARD)
                self._expect_result(target, t.verify(0x10000))
                return
            if target is not None:
                self.add(target, "Program", "END", {"op": "END"}, direction=PC_TO_BOARD)
                self._expect_result(target, t.verify(tr.words or 0x10000))
                return
            tr.rounds += 1
            self.add("all", "Program", f"END (round {tr.rounds}): {tr.blocks_sent} BLOCK "
                     f"frames, {tr.data_frames} data frames, {tr.resent} resent", {
                         "op": "END", "round": tr.rounds, "blocks_sent": tr.blocks_sent,
                         "data_frames": tr.data_frames, "resent": tr.resent},
                     direction=PC_TO_BOARD)
            words = tr.words if tr.words is not None else 0x10000
            for b in sorted(tr.boards - tr.verified) or [None]:  # type: ignore[list-item]
                self._expect_result(b, t.verify(words))
            return
        # ABORT
        self._end_block()
        self.add(target or "all", "Program", "ABORT", {"op": "ABORT"}, direction=PC_TO_BOARD)
        if target is None:
            self.transfer = None

    def _expect_result(self, board: str | None, board_time: float) -> None:
        tr = self.transfer

        def result(b: str, a: object, _t: float) -> None:
            if isinstance(a, m.ProgramResult):
                if a.status is ResultStatus.VERIFIED and tr is not None:
                    tr.verified.add(b)
                    self.board(b).prog_enabled = False
                for e in self.expects:
                    if e.key == (Function.PROGRAM, b, "end") and not e.done:
                        e.needed = 1 + a.reports

        self.expect("Program END" + (f"{_to(board)}" if board else ""),
                    Function.PROGRAM, board, board_time,
                    lambda _b, a: isinstance(a, m.ProgramResult | m.ProgramMissing
                                             | m.ProgramPartial), key=("end",),
                    answer_fn=Function.PROGRAM_FINISHED, on_answer=result)

    def _block(self, msg: m.ProgramBlock) -> None:
        self._end_block()
        tr = self.transfer
        again = tr is not None and msg.index in tr.seen
        text = (f"BLOCK {msg.index} {msg.space.name}:{msg.address:04X}, {msg.frames} frames, "
                f"CRC 0x{msg.crc:04X}" + (" (again)" if again else ""))
        bmsg = self.add("all", "Program", text, {
            "op": "BLOCK", "index": msg.index, "space": msg.space, "address": msg.address,
            "frames": msg.frames, "crc": msg.crc, "again": again}, direction=PC_TO_BOARD)
        if tr is None:
            return
        tr.block, tr.block_msg, tr.last_slot = msg, bmsg, -1
        tr.block_slots, tr.block_resent = [], 0
        tr.blocks_sent += 1
        tr.seen.setdefault(msg.index, set())

    def _data(self, msg: m.ProgramData) -> None:
        tr = self.transfer
        block = tr.block if tr is not None else None
        if tr is None or block is None:
            self.add("all", "Program", f"data frame, slot {msg.slot}, with no block open",
                     {"op": "DATA", "slot": msg.slot}, direction=PC_TO_BOARD)
            self.violation("data-out-of-sequence", f"data frame at slot {msg.slot} with no "
                           "block open (no BLOCK frame since the transfer began)", "all")
            return
        if msg.slot >= block.frames:
            self.violation("data-out-of-sequence", f"data frame at slot {msg.slot} is outside "
                           f"block {block.index} (its BLOCK frame announced {block.frames} "
                           f"frames, slots 0-{block.frames - 1})", "all")
        elif msg.slot <= tr.last_slot:
            self.violation("data-out-of-sequence", f"data frame at slot {msg.slot} after slot "
                           f"{tr.last_slot} in block {block.index}: slots rise within a block",
                           "all")
        else:
            tr.last_slot = msg.slot
        seen = tr.seen[block.index]
        if msg.slot in seen:
            tr.resent += 1
            tr.block_resent += 1
        seen.add(msg.slot)
        tr.block_slots.append(msg.slot)
        tr.data_frames += 1
        assert tr.block_msg is not None
        tr.block_msg.frames += 1
        tr.block_msg.members.append(self.index)

    def _end_block(self) -> None:
        tr = self.transfer
        if tr is None or tr.block is None or tr.block_msg is None:
            return
        b, bmsg = tr.block, tr.block_msg
        n = len(tr.block_slots)
        missing = b.frames - len(tr.seen[b.index] & set(range(b.frames)))
        text = f": {n} data frame{'' if n == 1 else 's'}" + \
            (f" (slots {_ranges(tr.block_slots)})" if n else "")
        if tr.block_resent:
            text += f", {tr.block_resent} resent"
        if missing:
            text += f", {missing} not sent yet"
        bmsg.text += text
        bmsg.fields.update({"data_frames": n, "slots": _ranges(tr.block_slots),
                            "resent": tr.block_resent, "not_sent": missing})
        tr.block = tr.block_msg = None

    # ------------------------------------------------------------------ run time
