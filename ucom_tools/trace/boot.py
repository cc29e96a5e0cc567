"""Decoding the bootloader's dialogue: reset, status, reports, the init chain, start,
and what the boards answer (Ready, Error, Init Ack, Info records, texts)."""

from __future__ import annotations

from typing import Any

from ucom_tools.errors import FrameError
from ucom_tools.trace.bus import (
    BusState,
)
from ucom_tools.trace.conversation import (
    BOARD_TO_PC,
    PC_TO_BOARD,
)
from ucom_tools.trace.state import (
    Expect,
    TracedBoard,
)
from ucom_tools.trace.text import (
    _info_fields,
    _info_text,
    _ranges,
    _ready_text,
    _to,
    jsonable,
)
from ucom_tools.wire import mca
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import (
    ErrorCode,
    InitAckKind,
    InitOp,
    ReadyReason,
    ReportChannel,
    StatusOp,
)
from ucom_tools.wire.digest import DescrDigest
from ucom_tools.wire.ids import Function
from ucom_tools.wire.info import INFO_FRAMES, BoardInfo


class BootDecoding(BusState):
    """The bootloader's requests and the boards' answers (a part of :class:`BusDecoder`)."""

    def _reset(self, target: str | None) -> None:
        for b in self.boards.values():
            if target is None or b.label == target:
                b.running = False
                self._stop_exchange(b, self.t)
                b.prog_enabled = False
                for e in self.expects:  # a reset board answers nothing it was asked
                    if not e.done and e.target == b.label and \
                            e.function not in (Function.RESET, Function.XRESET):
                        self.close(e, "the board was reset")

    def _set_status(self, board: str, target: str | None, msg: m.SetStatus) -> None:
        self.add(board, "SetStatus", f"{msg.op.name} {msg.value}",
                 {"op": msg.op, "value": msg.value}, direction=PC_TO_BOARD)
        answerer = str(msg.value) if msg.op is StatusOp.SEQ_ID and target is not None \
            else target
        want = (int(msg.op) << 8) | msg.value

        def done(b: str, _a: object, _t: float) -> None:
            if msg.op is StatusOp.PROG_ENABLE:
                self.board(b).prog_enabled = bool(msg.value)

        self.expect(f"SetStatus {msg.op.name}{_to(board)}", Function.SET_STATUS,
                    answerer, self.owner.timeouts.reply,
                    lambda _b, a: isinstance(a, m.Ready) and a.reason is ReadyReason.STATUS
                    and a.value16 == want, key=(msg.op, msg.value), on_answer=done)

    def _report_request(self, board: str, target: str | None, msg: m.ReportRequest) -> None:
        text = msg.channel.name
        needed = 1
        if msg.channel is ReportChannel.MEMORY:
            text += f" {msg.space.name}:{msg.address:04X}, {msg.count} words"
            needed = m.memory_report_frames(msg.count)
        self.add(board, "Report Request", text, {"channel": msg.channel, "space": msg.space,
                 "address": msg.address, "count": msg.count}, direction=PC_TO_BOARD)
        function = Function.report(msg.channel) if msg.channel <= 3 else None
        self.expect(f"Report Request {msg.channel.name}{_to(board)}",
                    Function.REPORT_REQUEST, target, self.owner.timeouts.reply,
                    lambda _b, a: function is not None and
                    getattr(a, "FUNCTION", None) is function, needed=needed,
                    key=(msg.channel, msg.address),
                    answer_fn=function if function is not None else Function.ERROR)

    def _init_request(self, msg: m.InitRequest) -> None:
        text = msg.op.name + (f" {msg.number}" if msg.op is InitOp.NEXT else "")
        if msg.op is InitOp.REJOIN:
            text += f" {msg.number} to serial 0x{msg.serial:08X}"
        fields_: dict[str, Any] = {"op": msg.op, "number": msg.number}
        if msg.op is InitOp.REJOIN:
            fields_["serial"] = msg.serial
        if msg.op is InitOp.BEGIN:
            self.chain = []
        elif msg.op is InitOp.END:
            text += (f": the chain has seq IDs {_ranges(self.chain)}" if self.chain else
                     ": no board answered")
            fields_["chain"] = list(self.chain)
        self.add("all", "Init Request", text, fields_, direction=PC_TO_BOARD)
        t = self.owner.timeouts
        if msg.op in (InitOp.BEGIN, InitOp.NEXT):
            n = 1 if msg.op is InitOp.BEGIN else msg.number
            self.expect(f"Init Request {text} (seq ID {n})", Function.INIT_REQUEST, None,
                        t.init_step, lambda _b, a: isinstance(a, m.InitAck) and
                        a.kind is InitAckKind.ASSIGNED and a.seq_id == n, optional=False,
                        key=(n,), init_number=n)
        elif msg.op is InitOp.REJOIN:  # answered only once the board is back: optional
            n, serial = msg.number, msg.serial
            self.expect(f"Init Request {text}", Function.INIT_REQUEST, None, t.init_step,
                        lambda _b, a: isinstance(a, m.InitAck) and
                        a.kind is InitAckKind.ASSIGNED and a.seq_id == n and
                        a.serial == serial, needed=None, key=("rejoin", n))
        elif msg.op is InitOp.END:
            # the questions nobody answered were the chain's end, not lost answers
            for e in self.expects:
                if e.init_number is not None and not e.done:
                    self.close(e, "the chain ended")
            self.init_missed.clear()
        elif msg.op in (InitOp.PROBE_FIRST, InitOp.PROBE_LAST):
            kind = InitAckKind.FIRST if msg.op is InitOp.PROBE_FIRST else InitAckKind.LAST
            self.expect(f"Init Request {text}", Function.INIT_REQUEST, None, t.probe,
                        lambda _b, a: isinstance(a, m.InitAck) and a.kind is kind,
                        needed=None, key=(kind,))

    def _start(self, board: str, target: str | None, msg: m.Start) -> None:
        self.add(board, "Start", msg.target.name.lower(), {"target": msg.target},
                 direction=PC_TO_BOARD)
        reply = self.owner.timeouts.reply
        was_stopped = {b.label for b in self.boards.values()
                       if (target is None or b.label == target) and b.running is False}
        start_t, start_index, start_pos, start_base = self.t, self.index, self.pos, self.horizon

        def started(b: str, a: object, _t: float) -> None:
            if not isinstance(a, m.Ready):
                return
            bd = self.board(b)
            if b in was_stopped:  # a program comes up: it announces itself (RUN TIME)
                startup = reply + self.owner.timeouts.startup
                e = Expect(start_index, start_t, start_pos, start_base, startup,
                            f"program start on board {b} (its unsolicited MCA Ready)",
                            Function.START, b, lambda _x, y: isinstance(y, mca.McaReady)
                            and y.answers == Function.MCA_READY, key=(Function.START, b, "up"),
                            answer_fn=Function.MCA_READY)
                self.expects.append(e)
            bd.running = True
            bd.records.clear()
            bd.edges.clear()

        self.expect(f"Start{_to(board)}", Function.START, target, reply,
                    lambda _b, a: isinstance(a, m.Ready) and a.reason is ReadyReason.STARTED,
                    key=(msg.target,), on_answer=started)

    # ------------------------------------------------------------------ programming

    def _state_of(self, bd: TracedBoard, message: object) -> None:
        if isinstance(message, m.Ready):
            if message.reason is ReadyReason.BOOT:
                bd.running = False
                bd.prog_enabled = False
                self._stop_exchange(bd, self.t)
                bd.resets_itself = False
        elif isinstance(message, mca.McaReady):
            bd.running = True
            bd.counts = (message.ci, message.so, message.par)
            if message.state is mca.RunState.RUNNING:
                self._run_exchange(bd, bd.exchange_since or self.t)
            else:
                self._stop_exchange(bd, self.t)

    def _error(self, bd: TracedBoard, err: m.Error) -> None:
        about = {0xFF: "no frame", mca.PROCESS_DATA | Function.MCA_CONTROLLER_INPUT:
                 "a CI map frame"}.get(err.function)
        if about is None and err.function <= 31:
            about = f"{Function(err.function).label}" if err.function <= 27 else \
                f"function {err.function}"
        text = f"{err.code.name}: {err.describe()}"
        if about:
            text += f" [about: {about}]"
        self.add(bd.label, "Error", text, {"code": err.code, "function": err.function,
                 "detail": err.detail}, direction=BOARD_TO_PC)
        if err.code is ErrorCode.WATCHDOG:
            self._stop_exchange(bd, self.t)
        elif err.code in (ErrorCode.INCOMPATIBLE, ErrorCode.VERSION_MISMATCH):
            bd.running = False
            bd.resets_itself = err.code is ErrorCode.VERSION_MISMATCH
            for e in self.expects:  # the program is not up: it announces nothing
                if not e.done and e.key == (Function.START, bd.label, "up"):
                    e.got, e.done = 1, True
        elif err.code is ErrorCode.BAD_MAP and err.function == Function.MCA_ADMIN_DATA:
            so = self.so_maps.get(err.detail)
            if so is not None and so.board == bd.label:
                del self.so_maps[err.detail]
        self.answer(bd.label, err, error=err)

    def _init_ack(self, bd: TracedBoard, ack: m.InitAck) -> None:
        version = f"{ack.bootloader_version >> 4}.{ack.bootloader_version & 15}"
        text = (f"{ack.kind.name}: seq ID {ack.seq_id or '-'}, fixed ID {ack.fixed_id or '-'}, "
                f"serial 0x{ack.serial:08X}, bootloader {version}")
        self.add(bd.label, "Init Ack", text, {"kind": ack.kind, "seq_id": ack.seq_id,
                 "fixed_id": ack.fixed_id, "bootloader": version,
                 "serial": f"0x{ack.serial:08X}"}, direction=BOARD_TO_PC)
        if ack.kind is InitAckKind.ASSIGNED and ack.seq_id:
            self.chain.append(ack.seq_id)
        if ack.seq_id:
            owner = self.board(str(ack.seq_id))
            if owner.serial != ack.serial:
                owner.bound_done = False  # bind it again, now by its serial
            owner.serial = ack.serial
            if ack.kind is InitAckKind.ASSIGNED:
                owner.running = False if owner.running is None else owner.running
        e = self.answer(bd.label, ack)
        if e is not None and e.init_number is not None:
            for missed in self.init_missed.pop(e.init_number, []):
                self.violation("unanswered", f"{missed.what} was not answered (asked again "
                               "and then answered)", str(e.init_number), t=missed.t,
                               index=missed.index)

    def _info(self, bd: TracedBoard, frame: m.InfoFrame) -> None:
        if frame.index == 0 or bd.info is None:
            self._flush_info(bd)
            msg = self.add(bd.label, "Info", "(incomplete)", {}, direction=BOARD_TO_PC)
            msg.frames = 0
            msg.members.clear()
            bd.info = (msg, {})
        msg, bodies = bd.info
        if frame.index in bodies:  # a new record without its frame 0
            self._flush_info(bd)
            msg = self.add(bd.label, "Info", "(incomplete)", {}, direction=BOARD_TO_PC)
            msg.frames = 0
            msg.members.clear()
            bd.info = (msg, bodies := {})
        bodies[frame.index] = frame.body
        msg.frames += 1
        msg.members.append(self.index)
        self.answer(bd.label, frame)
        if len(bodies) == INFO_FRAMES:
            bd.info = None
            try:
                info = BoardInfo.from_frames(bodies)
            except FrameError as err:
                msg.text = f"malformed record: {err}"
                self.violation("malformed", f"Info record: {err.field}: {err.message}",
                               bd.label)
                return
            msg.text, msg.fields = _info_text(info), jsonable(_info_fields(info))
            bd.serial = info.serial
            bd.running = info.state.name.startswith("RUNNING")

    def _flush_info(self, bd: TracedBoard) -> None:
        if bd.info is None:
            return
        msg, bodies = bd.info
        lacking = [i for i in range(INFO_FRAMES) if i not in bodies]
        msg.text = f"incomplete record: frames {_ranges(lacking)} missing"
        msg.fields = {"missing": lacking}
        bd.info = None

    def _text(self, bd: TracedBoard, piece: m.TextReport) -> None:
        if piece.index == 0 or bd.text is None:
            self._flush_text(bd)
            msg = self.add(bd.label, "Report 2", "", {}, direction=BOARD_TO_PC)
            msg.frames = 0
            msg.members.clear()
            bd.text = (msg, [])
        msg, pieces = bd.text
        if piece.index != len(pieces):
            pieces.append(b"\x00?")  # a gap: shown, the text goes on
        pieces.append(piece.text)
        msg.frames += 1
        msg.members.append(self.index)
        text = b"".join(p for p in pieces if p != b"\x00?").decode("latin-1")
        gaps = sum(1 for p in pieces if p == b"\x00?")
        msg.text = f"text: {text!r}" + (" (incomplete: pieces missing)" if gaps else
                                        "" if piece.last else " (more to come)")
        msg.fields = {"text": text, "complete": piece.last and not gaps}
        self.answer(bd.label, piece)
        if piece.last:
            bd.text = None

    def _flush_text(self, bd: TracedBoard) -> None:
        if bd.text is not None:
            msg, _ = bd.text
            msg.text = msg.text.replace(" (more to come)", " (incomplete: the last piece "
                                        "did not arrive)")
            bd.text = None


    def _describe(self, bd: TracedBoard, message: object) -> tuple[str, dict[str, Any]]:
        """Text and fields of a single-frame board message."""
        if isinstance(message, m.Ready):
            return _ready_text(message), {"reason": message.reason, "state": message.state,
                                          "value16": message.value16,
                                          "value32": message.value32}
        if isinstance(message, m.ProgramResult):
            text = (f"RESULT {message.status.name}: {message.status.text}, ProgID "
                    f"0x{message.progid:08X}")
            if message.reports:
                text += f", {message.reports} reports follow"
            return text, {"kind": "RESULT", "status": message.status,
                          "progid": f"0x{message.progid:08X}", "reports": message.reports}
        if isinstance(message, m.ProgramMissing):
            last = message.first + message.count - 1
            return (f"MISSING blocks {message.first}-{last} ({message.count})",
                    {"kind": "MISSING", "first": message.first, "count": message.count})
        if isinstance(message, m.ProgramPartial):
            last = message.first + message.count - 1
            return (f"PARTIAL block {message.block}: slots {message.first}-{last}",
                    {"kind": "PARTIAL", "block": message.block, "first": message.first,
                     "count": message.count})
        if isinstance(message, m.StatusReport):
            return (f"STATUS {message.state.name}, pins 0x{message.pins:X}, LEDs "
                    f"0x{message.leds:X}, TEC {message.tec}, REC {message.rec}, seq ID "
                    f"{message.seq_id}, overruns {message.overruns}", jsonable(message))
        if isinstance(message, m.MemoryReport):
            words = " ".join(f"{w:04X}" for w in message.words)
            return f"MEMORY {message.address:04X}: {words}", jsonable(message)
        if isinstance(message, m.AppReport):
            try:
                app = mca.AppStatus.decode(message.data)
            except FrameError:
                return f"APPLICATION {message.data.hex(' ').upper()}", {"data": message.data}
            return (f"APPLICATION {app.state.name}, load {app.load_permille / 10:.1f} %, cycle "
                    f"{app.cycle_us} us, {app.overruns} overruns, flags 0x{app.flags:02X}",
                    jsonable(app))
        if isinstance(message, mca.McaReady):
            answers = "unsolicited (the program is up)" if message.answers == \
                Function.MCA_READY else (Function(message.answers).label
                                         if message.answers <= 27 else str(message.answers))
            text = (f"{message.state.name}, answers {answers}, echo "
                    f"{message.echo.hex(' ').upper()}, edges {message.ci} CI / {message.so} "
                    f"SO / {message.par} PAR")
            flags = [n for bit, n in ((mca.FLAG_OVERRUN, "overrun"),
                                      (mca.FLAG_LATCHED_BY_WATCHDOG, "latched"))
                     if message.flags & bit]
            if flags:
                text += f", flags {'+'.join(flags)}"
            return text, jsonable(message)
        if isinstance(message, DescrDigest):
            return f"digest 0x{message.value:08X}", {"digest": f"0x{message.value:08X}"}
        if isinstance(message, mca.DumpValues):
            text, values = self._values_text(bd, message.kind, message.index, message.data)
            return text, {"kind": message.kind.name, "index": message.index,
                          "data": jsonable(message.data), "values": values}
        return "", jsonable(message)


