"""Host side of the programming transfer (``man/ucom-protocol.7``, PROGRAMMING).

One broadcast transfer per bus, for any number of ProgEnabled boards: Begin, Meta,
Erase, Prepare; wait for Ready(ERASED) from every board; stream the blocks, obeying
Ready(PAUSE)/Ready(RESUME); End; read every board's Program Finished; resend only the
blocks some board missed; repeat.  A board counts as programmed only when it reported
VERIFIED with the host's ProgID.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

from ucom_tools.errors import UcomError
from ucom_tools.protocol.link import Link
from ucom_tools.protocol.timeouts import DEFAULT, Timeouts
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import ReadyReason, ResultStatus, Target
from ucom_tools.wire.ids import ALL, Address, Function, encode_id
from ucom_tools.wire.transfer import TransferPlan


class Cancelled(UcomError):
    """The user cancelled a transfer (Ctrl-C); ABORT was sent."""


POLL_EVERY = 8
"""Frames between two looks at the receive queue while streaming (PAUSE, Error)."""

Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class BoardOutcome:
    address: Address
    verified: bool
    progid: int | None
    status: str
    resent_blocks: int = 0
    errors: tuple[str, ...] = ()


@dataclass(frozen=True)
class TransferResult:
    outcomes: dict[Address, BoardOutcome]
    plan_progid: int
    rounds: int
    blocks_sent: int
    frames_sent: int

    @property
    def all_verified(self) -> bool:
        return all(o.verified for o in self.outcomes.values())


class _Board:
    def __init__(self, address: Address) -> None:
        self.address = address
        self.alive = True
        self.erased = False
        self.result: m.ProgramResult | None = None
        self.missing: list[m.ProgramMissing] = []
        self.errors: list[str] = []
        self.failure = ""
        self.resent = 0


class Programmer:
    """Programs one image into the ProgEnabled boards of one bus."""

    def __init__(self, link: Link, timeouts: Timeouts = DEFAULT, *, max_rounds: int = 4,
                 progress: Progress | None = None,
                 cancel: threading.Event | None = None) -> None:
        self.link = link
        self.cancel = cancel
        self.timeouts = timeouts
        self.max_rounds = max_rounds
        self.progress = progress
        self.frames_sent = 0
        self._paused: set[Address] = set()

    # ------------------------------------------------------------------ sending
    def _send(self, msg: m.BootMessage) -> None:
        self.link.send(msg, ALL)
        self.frames_sent += 1

    def transfer(self, plan: TransferPlan, boards: list[Address]) -> TransferResult:
        state = {a: _Board(a) for a in boards}
        self._paused = set()
        self._send(plan.begin())
        for meta in plan.meta():
            self._send(meta)
        erases = plan.erases() if plan.target is Target.FLASH else []
        for erase in erases:
            self._send(erase)
        self._send(m.ProgramPrepare())
        pages = sum(e.count for e in erases)
        self._await_erased(state, self.timeouts.reply + pages * self.timeouts.erase_per_page)
        todo = list(range(len(plan.blocks)))
        rounds = blocks_sent = 0
        total_bytes = sum(len(b.words) * 2 for b in plan.blocks)
        sent_bytes = 0
        data_id = encode_id(Function.PROGRAM, ALL)
        while todo and rounds < self.max_rounds and any(b.alive for b in state.values()):
            rounds += 1
            for i in todo:
                if self.cancel is not None and self.cancel.is_set():
                    self._send(m.ProgramAbort())
                    raise Cancelled("programming cancelled; the boards dropped the transfer "
                                    "and keep no startable program")
                block = plan.blocks[i]
                self._send(block.header())
                raw = block.payload()
                for off in range(0, len(raw), 8):
                    self.link.send_raw(data_id, raw[off:off + 8])
                    self.frames_sent += 1
                    if self.frames_sent % POLL_EVERY == 0:
                        self._poll(state)
                sent_bytes += len(raw)
                blocks_sent += 1
                if self.progress is not None:
                    self.progress(min(sent_bytes, total_bytes), total_bytes)
            self._send(m.ProgramEnd())
            self._await_results(state)
            missing: set[int] = set()
            for b in state.values():
                if b.alive and b.result is not None and b.result.status is ResultStatus.MISSING:
                    for run in b.missing:
                        missing.update(range(run.first, run.first + run.count))
                    b.resent += sum(r.count for r in b.missing)
            todo = sorted(i for i in missing if i < len(plan.blocks))
        outcomes = {a: self._outcome(b, plan.progid) for a, b in state.items()}
        return TransferResult(outcomes, plan.progid, rounds, blocks_sent, self.frames_sent)

    # ------------------------------------------------------------------ receiving
    def _handle(self, state: dict[Address, _Board], got_addr: Address, msg: object) -> None:
        b = state.get(got_addr)
        if b is None:
            return
        if isinstance(msg, m.Ready):
            if msg.reason is ReadyReason.ERASED:
                b.erased = True
            elif msg.reason is ReadyReason.PAUSE:
                self._paused.add(got_addr)
            elif msg.reason is ReadyReason.RESUME:
                self._paused.discard(got_addr)
        elif isinstance(msg, m.Error):
            b.errors.append(msg.describe())
        elif isinstance(msg, m.ProgramResult):
            b.result = msg
            b.missing = []
        elif isinstance(msg, m.ProgramMissing):
            b.missing.append(msg)

    def _poll(self, state: dict[Address, _Board]) -> None:
        while (got := self.link.recv(0.0)) is not None:
            self._handle(state, got.address, got.message)
        while self._paused:
            got = self.link.recv(self.timeouts.pause)
            if got is None:
                for a in self._paused:
                    state[a].alive = False
                    state[a].failure = "stalled: sent PAUSE and no RESUME"
                self._paused.clear()
                break
            self._handle(state, got.address, got.message)

    def _await_erased(self, state: dict[Address, _Board], timeout: float) -> None:
        pending = {a for a, b in state.items() if b.alive}
        while pending:
            got = self.link.recv(timeout)
            if got is None:
                break
            self._handle(state, got.address, got.message)
            pending = {a for a in pending if not state[a].erased}
        for a in pending:
            b = state[a]
            b.alive = False
            b.failure = ("refused the transfer: " + "; ".join(b.errors) if b.errors
                         else "did not report erased flash (Ready ERASED) in time")

    def _await_results(self, state: dict[Address, _Board]) -> None:
        # A board that verified has left the transfer and will not answer again.
        waiting = [b for b in state.values() if b.alive and not _done(b)]
        for b in waiting:
            b.result = None
            b.missing = []

        def complete(b: _Board) -> bool:
            if not b.alive:
                return True
            r = b.result
            if r is None:
                return False
            if r.status is not ResultStatus.MISSING:
                return True
            got = sum(x.count for x in b.missing)
            return got >= r.missing or len(b.missing) >= 8

        while not all(complete(b) for b in waiting):
            got = self.link.recv(self.timeouts.verify)
            if got is None:
                break
            self._handle(state, got.address, got.message)
        for b in waiting:
            if b.alive and b.result is None:
                b.alive = False
                b.failure = "sent no Program Finished after End"

    def _outcome(self, b: _Board, progid: int) -> BoardOutcome:
        errors = tuple(b.errors)
        if not b.alive or b.result is None:
            return BoardOutcome(b.address, False, None, b.failure or "no answer", b.resent,
                                errors)
        r = b.result
        if r.status is ResultStatus.VERIFIED and r.progid == progid:
            return BoardOutcome(b.address, True, r.progid, "verified", b.resent, errors)
        if r.status is ResultStatus.VERIFIED:
            return BoardOutcome(b.address, False, r.progid,
                                f"board reports ProgID 0x{r.progid:08X}, "
                                f"image has 0x{progid:08X}", b.resent, errors)
        detail = r.status.text
        if r.status is ResultStatus.MISSING:
            detail += f" ({r.missing} blocks still missing after the last round)"
        elif r.status is ResultStatus.PROGID_MISMATCH:
            detail += f" (board computed 0x{r.progid:08X}, image has 0x{progid:08X})"
        return BoardOutcome(b.address, False, r.progid or None, detail, b.resent, errors)


def _done(b: _Board) -> bool:
    return b.result is not None and b.result.status is ResultStatus.VERIFIED

