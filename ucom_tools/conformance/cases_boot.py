"""Conformance cases of the bootloader level: identifiers, reset, init chain, Info,
program enable, programming (into external RAM: flash is never written), AutoStart and
XReset, FPGA registers, bad input.  Each cites the ``man/ucom-protocol.7`` section."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from datetime import UTC, datetime

from ucom_tools.conformance.bench import Bench
from ucom_tools.conformance.case import case
from ucom_tools.protocol.programmer import Programmer
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import (
    BoardState,
    ErrorCode,
    InitAckKind,
    InitOp,
    ReadyReason,
    Space,
    StatusOp,
    Target,
)
from ucom_tools.wire.fpga import FPGA_BASE
from ucom_tools.wire.ids import ALL, Function, IdType, encode_id, seq
from ucom_tools.wire.transfer import TransferPlan

WHEN = datetime(2026, 1, 1, tzinfo=UTC)


def small_image(name: str = "conformance.S", words: int = 300) -> TransferPlan:
    """A small image of the suite's own: ``words`` words at P:0004, for external RAM."""
    data = {(Space.P, 0x0004 + i): (0x1234 + 7 * i) & 0xFFFF for i in range(words)}
    return TransferPlan.build(data, entry=4, name=name, when=WHEN, target=Target.EXTRAM)


# ---------------------------------------------------------------------- identifiers
@case("ids.answer-address", "identifiers", "IDENTIFIERS, Addressing")
def answer_address(b: Bench) -> None:
    """A board answers with its own seq ID and type 0, and only when addressed."""
    numbers = b.boards()
    n = numbers[-1]
    answers = b.ask(m.InfoRequest(), seq(n), answer=lambda g: True,
                    within=b.timeouts.reply, count=10)
    senders = {a.got.address for a in answers}
    b.expect(senders == {seq(n)}, f"senders of the Info answer to board {n}",
             {str(seq(n))}, sorted(str(s) for s in senders))
    b.expect(all(a.got.address.id_type is IdType.SEQUENTIAL for a in answers),
             "identifier type of the answers", "0 (seq ID)", "type 1")


# ---------------------------------------------------------------------- reset
@case("reset.all", "reset", "MESSAGES, Reset; TIMEOUTS")
def reset_all(b: Bench) -> None:
    """Reset: every numbered board answers Ready(BOOT) with its serial, in time."""
    numbers = b.boards()
    serials = {n: b.boot.info(seq(n)).serial for n in numbers}
    answers = b.ask(m.Reset(), ALL, answer=lambda g: isinstance(g.message, m.Ready) and
                    g.message.reason is ReadyReason.BOOT, within=b.timeouts.reset,
                    count=len(numbers))
    got = {a.got.address.number: a.got.message.value32 for a in answers
           if isinstance(a.got.message, m.Ready)}
    b.expect(got == serials, "Ready(BOOT) per board (seq ID: serial)", serials, got)
    late = [a for a in answers if a.delay > b.allowed(b.timeouts.reset, len(numbers))]
    b.expect(not late, "Ready(BOOT) time", f"<= {b.timeouts.reset * 1e3:.0f} ms",
             [f"{a.delay * 1e3:.1f} ms" for a in late])


@case("reset.one", "reset", "MESSAGES, Reset (console option 21)")
def reset_one(b: Bench) -> None:
    """A reset addressed to one board resets that board only."""
    numbers = b.boards()
    n = numbers[0]
    answers = b.ask(m.Reset(), seq(n), answer=lambda g: isinstance(g.message, m.Ready),
                    within=b.timeouts.reset, extra=b.timeouts.reset)
    who = sorted({a.got.address.number for a in answers})
    b.expect(who == [n], "boards answering a reset of one", [n], who)


# ---------------------------------------------------------------------- init chain
@case("init.numbering", "init chain", "INIT CHAIN")
def init_numbering(b: Bench) -> None:
    """The chain numbers the boards 1, 2, ... N, one Init Ack each, each in time."""
    b.boot.reset()
    numbers: list[int] = []
    op, n = InitOp.BEGIN, 1
    while n <= 31:  # BEGIN: the first board takes 1; NEXT n: the next one takes n
        request = m.InitRequest(op, 0 if op is InitOp.BEGIN else n)
        answers = b.ask(request, ALL, answer=lambda g: isinstance(
            g.message, m.InitAck) and g.message.kind is InitAckKind.ASSIGNED,
            within=b.timeouts.init_step, extra=b.timeouts.init_step)
        if not answers:
            break
        got = [a.got.message.seq_id for a in answers]  # type: ignore[union-attr]
        b.expect(got == [n], f"Init Ack(s) for number {n}", [n], got)
        late = [a.delay for a in answers if a.delay > b.allowed(b.timeouts.init_step)]
        b.expect(not late, f"Init Ack time for number {n}",
                 f"<= {b.timeouts.init_step * 1e3:.0f} ms", late)
        numbers.append(n)
        op, n = InitOp.NEXT, n + 1
    b.link.send(m.InitRequest(InitOp.END), ALL)
    b.expect(bool(numbers), "boards numbered", ">= 1", 0)
    b.numbers = numbers


@case("init.first-last", "init chain", "INIT CHAIN, Probes")
def init_first_last(b: Bench) -> None:
    """Get First and Get Last find the first and the last board of the chain."""
    numbers = b.boards()
    first = [a.seq_id for a in b.boot.probe()]
    last = [a.seq_id for a in b.boot.probe(last=True)]
    b.expect(first == [numbers[0]], "Get First", [numbers[0]], first)
    b.expect(last == [numbers[-1]], "Get Last", [numbers[-1]], last)


@case("init.set-init-out", "init chain", "INIT CHAIN; MESSAGES, SetStatus",
      writes="init output pin (released again)")
def init_set_out(b: Bench) -> None:
    """SetInitOut drives the init output; Report STATUS shows it, and it is released."""
    n = b.boards()[0]
    try:
        b.boot.set_status(seq(n), StatusOp.INIT_OUT, 1)
        pins = b.boot.status(seq(n)).pins
        b.expect(bool(pins & 0b100), "init output driven (STATUS pin bit 2)", 1,
                 int(bool(pins & 0b100)))
        b.boot.set_status(seq(n), StatusOp.INIT_OUT, 0)
        pins = b.boot.status(seq(n)).pins
        b.expect(not pins & 0b100, "init output released", 0, int(bool(pins & 0b100)))
    finally:
        b.boot.set_status(seq(n), StatusOp.INIT_OUT, 0)


# ---------------------------------------------------------------------- info
@case("info.record", "info", "MESSAGES, Info")
def info_record(b: Bench) -> None:
    """The Info record is complete, in time, and agrees with the Init Ack (serial)."""
    result = b.init()
    for ack in result.acks:
        got = b.ask_one(m.InfoRequest(), seq(ack.seq_id), m.InfoFrame,
                        within=b.timeouts.reply, what=f"Info of board {ack.seq_id}")
        del got
        info = b.boot.info(seq(ack.seq_id))
        b.expect(info.serial == ack.serial, f"board {ack.seq_id}: Info serial",
                 f"0x{ack.serial:08X} (its Init Ack)", f"0x{info.serial:08X}")
        b.expect(info.seq_id == ack.seq_id, f"board {ack.seq_id}: Info seq ID",
                 ack.seq_id, info.seq_id)


@case("info.set-status-time", "info", "MESSAGES, SetStatus; TIMEOUTS")
def set_status_time(b: Bench) -> None:
    """SetStatus is answered Ready(STATUS) with the op and value, in time."""
    n = b.boards()[0]
    got = b.ask_one(m.SetStatus(StatusOp.PROG_ENABLE, 0), seq(n), m.Ready,
                    within=b.timeouts.reply, what="SetStatus PROG_ENABLE 0")
    ready = got.message
    assert isinstance(ready, m.Ready)
    b.expect(ready.reason is ReadyReason.STATUS and ready.value16 == StatusOp.PROG_ENABLE << 8,
             "Ready answering SetStatus", "STATUS, value16 = op << 8 | value",
             f"{ready.reason.name}, 0x{ready.value16:04X}")


# ---------------------------------------------------------------------- program enable
@case("progenable.required", "program enable", "PROGRAMMING, Sequence",
      writes="a transfer into external RAM")
def progenable_required(b: Bench) -> None:
    """A board that is not ProgEnabled takes no part in a transfer."""
    n = b.boards()[0]
    b.boot.set_status(seq(n), StatusOp.PROG_ENABLE, 0)
    result = Programmer(b.link, b.timeouts).transfer(small_image(), [seq(n)])
    b.expect(not result.all_verified, "transfer to a board not ProgEnabled",
             "not verified", "verified")


# ---------------------------------------------------------------------- programming
@case("program.transfer", "programming", "PROGRAMMING; PROGID",
      writes="a small image into external RAM (gone after reset)")
def program_transfer(b: Bench) -> None:
    """A transfer into external RAM verifies with the image's ProgID; Info shows it."""
    n = b.boards()[0]
    plan = small_image()
    b.boot.set_status(seq(n), StatusOp.PROG_ENABLE, 1)
    result = Programmer(b.link, b.timeouts).transfer(plan, [seq(n)])
    outcome = result.outcomes[seq(n)]
    b.expect(outcome.verified, "Program Finished", "VERIFIED", outcome.status)
    b.expect(outcome.progid == plan.progid, "ProgID the board computed",
             f"0x{plan.progid:08X}", f"0x{(outcome.progid or 0):08X}")
    b.expect(result.resent_frames == 0, "frames resent on a loss-free bus", 0,
             result.resent_frames)


@case("program.resend", "programming", "PROGRAMMING, Sequence (steps 5 and 6)",
      writes="a small image into external RAM (gone after reset)")
def program_resend(b: Bench) -> None:
    """Data frames that never came are reported missing and taken when sent again."""
    n = b.boards()[0]
    plan = small_image(words=600)
    b.boot.set_status(seq(n), StatusOp.PROG_ENABLE, 1)
    send = b.link.send_raw
    skipped: list[int] = []

    def lossy(arbitration_id: int, data: bytes) -> None:
        if arbitration_id >> 6 == Function.PROGRAM and len(data) == 8 and \
                len(skipped) < 3 and (arbitration_id & 0x3F) in (2, 5, 9) and \
                arbitration_id not in skipped:
            skipped.append(arbitration_id)  # this frame never reaches the bus
            return
        send(arbitration_id, data)

    b.link.send_raw = lossy  # type: ignore[method-assign]
    try:
        result = Programmer(b.link, b.timeouts).transfer(plan, [seq(n)])
    finally:
        del b.link.send_raw
    outcome = result.outcomes[seq(n)]
    b.expect(len(skipped) == 3, "frames withheld", 3, len(skipped))
    b.expect(outcome.verified and outcome.progid == plan.progid,
             "after resending what the board reported missing", "VERIFIED with the ProgID",
             f"{outcome.status} 0x{(outcome.progid or 0):08X}")
    b.expect(result.resent_frames >= 3, "frames resent", ">= 3", result.resent_frames)


@case("program.wrong-progid", "programming", "PROGRAMMING, Sequence (step 5); PROGID",
      writes="a small image into external RAM (refused)")
def program_wrong_progid(b: Bench) -> None:
    """An image whose META ProgID does not match its words is refused and cannot start."""
    n = b.boards()[0]
    plan = small_image()
    wrong = replace(plan, progid=plan.progid ^ 0x00010000)
    b.boot.set_status(seq(n), StatusOp.PROG_ENABLE, 1)
    result = Programmer(b.link, b.timeouts).transfer(wrong, [seq(n)])
    outcome = result.outcomes[seq(n)]
    b.expect(not outcome.verified, "transfer with a wrong ProgID", "refused (not VERIFIED)",
             outcome.status)
    info = b.boot.info(seq(n))
    b.expect(not info.extram_valid, "Info after the refused transfer",
             "no valid program in external RAM", "external RAM program valid")
    b.link.send(m.ProgramAbort(), seq(n))  # close the transfer (a reset would too)
    b.wait(b.timeouts.reply)
    (started,) = b.boot.start(seq(n), Target.EXTRAM)
    codes = [e.code for e in started.errors]
    b.expect(not started.started and ErrorCode.NO_PROGRAM in codes,
             "Start of the refused image", "Error NO_PROGRAM", codes or "started")


@case("extram.start", "extram", "PROGRAMMING, ExtRAM",
      writes="a small image into external RAM (gone after reset)")
def extram_start(b: Bench) -> None:
    """An image in external RAM starts (state RUNNING_EXTRAM) and a reset ends it."""
    n = b.boards()[0]
    b.boot.set_status(seq(n), StatusOp.PROG_ENABLE, 1)
    result = Programmer(b.link, b.timeouts).transfer(small_image(), [seq(n)])
    if not result.all_verified:
        b.skip("the board takes no program into external RAM")
    (started,) = b.boot.start(seq(n), Target.EXTRAM)
    b.expect(started.state is BoardState.RUNNING_EXTRAM, "state after Start EXTRAM",
             "RUNNING_EXTRAM", started.state)
    b.boot.reset(seq(n))
    b.expect(b.boot.info(seq(n)).state is BoardState.BOOTLOADER, "state after a reset",
             "BOOTLOADER", b.boot.info(seq(n)).state)


# ---------------------------------------------------------------------- autostart
@contextmanager
def _with_program(b: Bench) -> Iterator[int]:
    """A board that holds a program in flash: one that did, or the first board with the
    suite's small image programmed for the case and made invalid again afterwards (a
    transfer that begins and is aborted leaves no valid program: PROGRAMMING, Sequence)."""
    for n in b.boards():
        if b.boot.info(seq(n)).flash_valid:
            yield n
            return
    n = b.boards()[0]
    plan = replace(small_image(), target=Target.FLASH)
    b.boot.set_status(seq(n), StatusOp.PROG_ENABLE, 1)
    result = Programmer(b.link, b.timeouts).transfer(plan, [seq(n)])
    b.expect(result.all_verified, "programming the suite's image into flash", "VERIFIED",
             result.outcomes[seq(n)].status)
    try:
        yield n
    finally:
        b.boot.reset(seq(n), clear_autostart=True)
        b.wait(b.timeouts.reset)
        b.init()
        b.boot.set_status(seq(n), StatusOp.PROG_ENABLE, 1)
        b.link.send(m.ProgramBegin(Target.FLASH, 1, 4), seq(n))
        b.link.send(m.ProgramAbort(), seq(n))
        b.wait(b.timeouts.reply)
        b.boot.set_status(seq(n), StatusOp.PROG_ENABLE, 0)


@case("autostart.reset-keeps", "autostart", "MESSAGES, SetStatus (AUTOSTART); MESSAGES, Reset",
      writes="the AutoStart flag (restored); the suite's image into flash if no board "
             "held a program (made invalid again)")
def autostart_kept(b: Bench) -> None:
    """AutoStart set stays set across a reset, and the board starts its program."""
    with _with_program(b) as n:
        before = b.boot.info(seq(n)).autostart
        try:
            b.boot.set_status(seq(n), StatusOp.AUTOSTART, 1)
            b.boot.reset(seq(n))
            b.wait(b.timeouts.reset)
            info = b.boot.info(seq(n))
            b.expect(info.autostart, "AutoStart after a reset", True, info.autostart)
            b.expect(info.state is BoardState.RUNNING_FLASH, "state after a reset with "
                     "AutoStart", "RUNNING_FLASH", info.state.name)
        finally:
            b.boot.reset(seq(n), clear_autostart=not before)
            b.wait(b.timeouts.reset)
            b.init()


@case("autostart.xreset-clears", "autostart", "MESSAGES, XReset",
      writes="the AutoStart flag (restored); the suite's image into flash if no board "
             "held a program (made invalid again)")
def xreset_clears(b: Bench) -> None:
    """XReset clears AutoStart (and the board stays in its bootloader)."""
    with _with_program(b) as n:
        before = b.boot.info(seq(n)).autostart
        try:
            b.boot.set_status(seq(n), StatusOp.AUTOSTART, 1)
            b.boot.reset(seq(n), clear_autostart=True)
            b.wait(b.timeouts.reset)
            info = b.boot.info(seq(n))
            b.expect(not info.autostart, "AutoStart after XReset", False, info.autostart)
            b.expect(info.state is BoardState.BOOTLOADER, "state after XReset",
                     "BOOTLOADER", info.state.name)
        finally:
            if before:
                b.boot.set_status(seq(n), StatusOp.AUTOSTART, 1)


@case("autostart.needs-program", "autostart", "MESSAGES, SetStatus (AUTOSTART)")
def autostart_needs_program(b: Bench) -> None:
    """AutoStart on a board without a program in flash is refused (NO_PROGRAM)."""
    for n in b.boards():
        if not b.boot.info(seq(n)).flash_valid:
            me = seq(n)
            answers = b.ask(m.SetStatus(StatusOp.AUTOSTART, 1), me,
                            answer=lambda g, me=me: g.address == me,  # type: ignore[misc]
                            within=b.timeouts.reply)
            errors = [a.got.message.code for a in answers
                      if isinstance(a.got.message, m.Error)]
            b.expect(ErrorCode.NO_PROGRAM in errors, f"board {n}: AutoStart without a program",
                     "Error NO_PROGRAM", errors or [type(a.got.message).__name__
                                                    for a in answers])
            return
    b.skip("every board holds a program")


# ---------------------------------------------------------------------- fpga
@case("fpga.version", "fpga", "COMPATIBILITY, FPGA registers")
def fpga_version(b: Bench) -> None:
    """The FPGA's version and Board-ID registers (X:4000-4002) agree with the Info
    record."""
    for n in b.boards():
        info = b.boot.info(seq(n))
        words = b.boot.read_memory(seq(n), Space.X, FPGA_BASE, 3)
        expected = [info.fpga_register1, info.fpga_register2, info.measured_board_id]
        got = [words[0], words[1], words[2] & 0xF]
        b.expect(got == expected, f"board {n}: X:4000, X:4001, X:4002 bits 3-0",
                 [hex(w) for w in expected], [hex(w) for w in got])


# ---------------------------------------------------------------------- bad input
@case("bad.unknown-function", "bad input", "BOOTLOADER, Frames a board does not take")
def bad_unknown_function(b: Bench) -> None:
    """An unassigned function (28-31) addressed to a board is answered Error
    UNKNOWN_FUNCTION."""
    n = b.boards()[0]
    b.link.send_raw(encode_id(30, seq(n)), b"")
    errors = [g.message for g in b.wait(b.allowed(b.timeouts.reply))
              if g.address == seq(n) and isinstance(g.message, m.Error)]
    codes = [(e.code, e.function) for e in errors]
    b.expect((ErrorCode.UNKNOWN_FUNCTION, 30) in codes, "answer to function 30",
             "Error UNKNOWN_FUNCTION, function 30", codes or "nothing")


@case("bad.wrong-length", "bad input", "BOOTLOADER, Frames a board does not take")
def bad_wrong_length(b: Bench) -> None:
    """A request of the wrong length is answered Error BAD_LENGTH and not carried out."""
    n = b.boards()[0]
    b.link.send_raw(encode_id(Function.SET_STATUS, seq(n)), bytes((StatusOp.INIT_OUT,)))
    got = [g.message for g in b.wait(b.allowed(b.timeouts.reply)) if g.address == seq(n)]
    codes = [e.code for e in got if isinstance(e, m.Error)]
    b.expect(ErrorCode.BAD_LENGTH in codes, "SetStatus with 1 byte", "Error BAD_LENGTH",
             codes or [type(x).__name__ for x in got])
    b.expect(not any(isinstance(x, m.Ready) for x in got), "the short SetStatus",
             "not carried out (no Ready)", "a Ready")


@case("bad.other-boards", "bad input", "IDENTIFIERS, Addressing")
def bad_other_boards(b: Bench) -> None:
    """A board ignores requests addressed to another board's seq ID."""
    numbers = b.boards()
    if len(numbers) < 2:
        b.skip("one board on the bus")
    target = numbers[-1]
    answers = b.ask(m.SetStatus(StatusOp.PROG_ENABLE, 0), seq(target), answer=lambda g: True,
                    within=b.timeouts.reply, extra=b.timeouts.reply)
    who = sorted({a.got.address.number for a in answers})
    b.expect(who == [target], f"boards answering SetStatus to board {target}", [target], who)

