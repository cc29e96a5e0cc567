"""Host side of the programming transfer (``man/ucom-protocol.7``, PROGRAMMING).

One broadcast transfer per bus, for any number of ProgEnabled boards:

1. the preamble (BEGIN, META, ERASE, PREPARE) and Ready(ERASED) from every board; a board
   that does not report erased flash is asked again, alone: PREPARE, or what its Error
   SEQUENCE says it lacks, so a lost frame costs a repetition, not the board;
2. the blocks: a BLOCK frame, then its data frames, each carrying its slot, obeying
   Ready(PAUSE)/Ready(RESUME) (a lost RESUME costs the time the board needs to drain);
3. END, and every board's Program Finished with what it lacks, frame by frame; END is
   asked again of a board whose answer does not come;
4. exactly the missing frames again (the union over the boards; a board ignores what
   it has), then END again: a *round*.  Rounds go on until every board verified, or
   :data:`PROGRESS_WINDOW` rounds in a row brought no progress, or the repair deadline
   passed (:meth:`Programmer.repair_time`: what a bus losing half of the frames needs,
   from the image's frames at the bus bitrate and END's round trip), or
   :data:`MAX_ROUNDS`.  A lost resend costs a round, not the transfer; a board that
   stays silent for a round is asked again in the next.

A board counts as programmed only when it reported VERIFIED with the host's ProgID.

A ``cancel`` event (Ctrl-C) is looked at between blocks, between rounds and at least
every :data:`CANCEL_POLL` of a wait for answers (the erase may take seconds): the
transfer then stops with :class:`Cancelled` and sends nothing more.  Undoing it is the
caller's (:mod:`ucom_tools.ops.flash`: ABORT if :attr:`Programmer.began`, ProgEnable
cleared, every board's Info read).

Another host programming the same bus wrecks both transfers (its BEGIN restarts every
board's).  :class:`ProgrammingWatch` notices its frames, and the answers to requests this
host never made; the programmer then stops before it sends data (:class:`BusError`).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from ucom_tools.errors import UcomError
from ucom_tools.protocol.link import SHARED_BUS_FACTOR, Link, Received
from ucom_tools.protocol.timeouts import DEFAULT, Timeouts
from ucom_tools.protocol.watch import ProgrammingWatch
from ucom_tools.wire import messages as m
from ucom_tools.wire.answers import MAX_REPORTS
from ucom_tools.wire.canbits import unstuffed_bits
from ucom_tools.wire.codes import (
    ErrorCode,
    PrepareLack,
    ReadyReason,
    ResultStatus,
    split_prepare_lack,
)
from ucom_tools.wire.ids import ALL, Address, Function, data_frame_id
from ucom_tools.wire.transfer import TransferPlan


class Cancelled(UcomError):
    """The user cancelled a job (Ctrl-C, SIGTERM, SIGHUP: its cancel event was set); the
    job stopped where it was, without undoing anything itself."""


PREAMBLE_ASKS = 2
"""The preamble is repaired up to this many times (1 + retries) times: it is many frames."""
REFUSALS = frozenset({ErrorCode.PROTECTED_ADDRESS, ErrorCode.UNMAPPED_ADDRESS,
                      ErrorCode.BAD_VALUE, ErrorCode.NOT_ENABLED, ErrorCode.RUNNING,
                      ErrorCode.FLASH_FAILURE})
"""Errors by which a board refuses a transfer (asking again would not help)."""
POLL_EVERY = 8
"""Frames between two looks at the receive queue while streaming (PAUSE, Error)."""
RING_RESERVE = 8
"""Frames of a board's receive ring the host leaves free by its own reckoning
(:meth:`Programmer._admit`): what its estimate of when its frames pass may be off by."""
PROGRESS_WINDOW = 4
"""Rounds in a row that brought no progress (no board verified, what no board lacks
changed) end the transfer.  One such round is no verdict: on a bus losing 5 % of the
frames each way a round that resends one frame (and its BLOCK frame) brings nothing one
time in ten, four in a row one time in 10,000."""
MAX_ROUNDS = 64
"""A safety bound: rounds stop earlier, by the progress window or the repair deadline."""
CANCEL_POLL = 0.05
"""Seconds (bus clock) a wait for answers goes on at most without a look at the cancel
event: a Ctrl-C during the erase is taken within this, not after it."""


DATA_ID = data_frame_id(0)
"""Identifier of a Program data frame at slot 0; slot s is DATA_ID | s."""

Progress = Callable[[int, int], None]
Missing = frozenset[tuple[int, int]]
"""(block, slot) pairs a board lacks."""


@dataclass(frozen=True)
class BoardOutcome:
    address: Address
    verified: bool
    progid: int | None
    status: str
    resent_frames: int = 0
    errors: tuple[str, ...] = ()


@dataclass(frozen=True)
class TransferResult:
    outcomes: dict[Address, BoardOutcome]
    plan_progid: int
    rounds: int
    frames_sent: int
    data_frames: int
    resent_frames: int

    @property
    def all_verified(self) -> bool:
        return all(o.verified for o in self.outcomes.values())


class _Board:
    def __init__(self, address: Address) -> None:
        self.address = address
        self.alive = True
        self.erased = False
        self.lacks: tuple[PrepareLack | None, int] | None = None
        """What the board's Error SEQUENCE said it lacks of the preamble."""
        self.silent = 0
        """Preamble questions to this board that brought no answer at all."""
        self.refusal: str | None = None
        """The Error with which the board refused the transfer (described)."""
        self.frame_us = 100.0
        """Microseconds the board needs per data frame (its Ready ERASED)."""
        self.ring = 0
        """Frames its receive ring holds (its Ready ERASED; 0: not told)."""
        self.busy_until = 0.0
        """When, by the host's reckoning, the board will have worked off the data frames
        sent so far (link clock)."""
        self.result: m.ProgramResult | None = None
        self.reports: list[m.ProgramMissing | m.ProgramPartial] = []
        self.missing: Missing | None = None
        """What the board lacks as far as its answers tell (None: it never answered)."""
        self.said: tuple[int, Missing] | None = None
        """Its last MISSING answer: the RESULT's number of reports, the frames they named."""
        self.unanswered = 0
        """ENDs asked of this board in a row that brought no Program Finished."""
        self.errors: list[str] = []
        self.failure = ""
        self.resent = 0

    @property
    def verified(self) -> bool:
        return self.result is not None and self.result.status is ResultStatus.VERIFIED

    @property
    def answered(self) -> bool:
        """A RESULT and every report it announced have arrived."""
        r = self.result
        return r is not None and len(self.reports) >= r.reports


class Programmer:
    """Programs one image into the ProgEnabled boards of one bus.

    ``others`` watches for another host programming the same bus: the transfer stops with
    :class:`BusError` before its preamble and before its data when that host showed
    itself (and between blocks and rounds: both transfers are lost then)."""

    def __init__(self, link: Link, timeouts: Timeouts = DEFAULT, *,
                 max_rounds: int = MAX_ROUNDS, progress: Progress | None = None,
                 cancel: threading.Event | None = None,
                 others: ProgrammingWatch | None = None) -> None:
        self.link = link
        self.cancel = cancel
        self.timeouts = timeouts
        self.max_rounds = max_rounds
        self.progress = progress
        self.others = others
        self.frames_sent = 0
        self.began = False
        """BEGIN was (or was being) handed to the bus: the boards may be in the transfer."""
        self.step = "erase"
        """Where the transfer is: erase (the preamble and Ready ERASED), transfer (the
        data), verification (END, Program Finished and the rounds that resend)."""
        self._state: dict[Address, _Board] = {}
        self._paused: dict[Address, float] = {}

    # ------------------------------------------------------------------ sending
    def _send(self, msg: m.BootMessage, address: Address = ALL) -> None:
        arb, data = m.encode(msg, address)
        self.link.send_raw(arb, data)
        self.frames_sent += 1
        if self.others is not None:
            self.others.own(arb, data)

    def _preamble_frames(self, plan: TransferPlan) -> list[m.BootMessage]:
        return [plan.begin(), *plan.meta(), *plan.erases(), plan.prepare()]

    def _check_cancel(self) -> None:
        if self.cancel is not None and self.cancel.is_set():
            raise Cancelled(f"{self.link.name}: programming cancelled during the {self.step}")

    def _until(self, deadline: float) -> Iterator[Received]:
        """:meth:`Link.until <ucom_tools.protocol.link.Link.until>`, with a look at the
        cancel event at least every :data:`CANCEL_POLL` seconds and at every answer."""
        link = self.link
        if self.cancel is None:
            yield from link.until(deadline)
            return
        while True:
            self._check_cancel()
            now = link.clock()
            if now >= deadline:
                return
            got = link.recv_until(min(deadline, now + CANCEL_POLL))
            if got is not None:
                yield got

    def _check_others(self, done: str) -> None:
        if self.others is not None:
            self.others.check(self.link.name, done)

    # ------------------------------------------------------------------ transfer
    def transfer(self, plan: TransferPlan, boards: list[Address]) -> TransferResult:
        state = self._state = {a: _Board(a) for a in boards}
        self._paused = {}
        self._check_others("this host sent nothing of its transfer")
        self._check_cancel()
        self._preamble(plan)
        self._check_others("this host stopped before sending data")
        needed: dict[int, set[int]] = {i: set(range(b.frames))
                                       for i, b in enumerate(plan.blocks)}
        rounds = data_frames = resent = 0
        total = sum(len(b.words) * 2 for b in plan.blocks)
        still = 0  # rounds in a row without progress
        deadline: float | None = None
        allowed = 0.0
        why = ""
        while any(b.alive and not b.verified for b in state.values()):
            if still >= PROGRESS_WINDOW:
                why = f"the last {still} rounds brought no progress"
                break
            if rounds >= self.max_rounds:
                why = f"the most rounds a transfer takes ({self.max_rounds})"
                break
            if deadline is not None and self.link.clock() >= deadline:
                why = (f"the repair rounds took the time they have ({allowed:.2f} s, what a "
                       "bus losing half of the frames needs)")
                break
            if rounds:
                self._check_others("both transfers are lost")
            self._check_cancel()
            rounds += 1
            self.step = "transfer" if rounds == 1 else "verification"
            sent = self._stream(plan, needed, total if rounds == 1 else None)
            data_frames += sent
            if rounds > 1:
                resent += sent
            self.step = "verification"
            self._end(plan)
            if deadline is None:
                allowed = self.repair_time(plan, len(boards))
                deadline = self.link.clock() + allowed
            needed, progress = self._missing(plan)
            still = 0 if progress else still + 1
        for b in state.values():
            if not b.alive or b.verified:
                continue
            if b.result is None and not b.missing:
                b.failure = f"sent no Program Finished after End, asked {b.unanswered} times"
            else:
                lacking = len(b.missing if b.missing is not None else self._reported(plan, b))
                b.failure = (f"{lacking} data frame(s) still missing after {rounds} "
                             f"round(s); {why}")
        outcomes = {a: self._outcome(b, plan.progid) for a, b in state.items()}
        return TransferResult(outcomes, plan.progid, rounds, self.frames_sent, data_frames,
                              resent)

    def repair_time(self, plan: TransferPlan, boards: int) -> float:
        """How long the rounds after the first may take together (bus clock): what a bus
        that loses up to half of what is sent needs.  Every BLOCK and data frame of the
        image once more at the bus bitrate (doubled, as every wire time of a wait: the bus
        may carry other traffic), and for each halving of them down to one frame, and for
        each round of the progress window, a round's END asked ``1 + retries`` times,
        each wait as :meth:`~ucom_tools.protocol.link.Link.budget` allows it with nothing
        ahead of it (the boards' verification, their answers at the bitrate, the
        transport margin)."""
        frames = sum(b.frames + 1 for b in plan.blocks)
        image = SHARED_BUS_FACTOR * self.link.wire_time(frames)
        trip = (SHARED_BUS_FACTOR * self.link.wire_time(boards * (1 + MAX_REPORTS))
                + self.timeouts.verify(plan.size_words) + self.link.margin)
        rounds = math.ceil(math.log2(max(frames, 2))) + PROGRESS_WINDOW
        return image + rounds * (1 + self.timeouts.retries) * trip

    # ------------------------------------------------------------------ preamble
    def _preamble(self, plan: TransferPlan) -> None:
        """Preamble broadcast, then Ready(ERASED) from every board.  A board that did not
        answer is asked again alone: PREPARE (its answer or PREPARE may have been lost),
        exactly what its Error SEQUENCE says it lacks, or the whole preamble."""
        state = self._state
        self.step = "erase"
        self.began = True  # before the send: an interrupt inside it may have let BEGIN out
        for frame in self._preamble_frames(plan):
            self._send(frame)
        pages = plan.prepare().pages
        board_time = self.timeouts.reply + pages * self.timeouts.erase_per_page
        attempts = PREAMBLE_ASKS * (1 + self.timeouts.retries)
        for attempt in range(attempts):
            pending = [b for b in state.values() if b.alive and not b.erased]
            deadline = self.link.deadline(board_time, answers=len(pending))
            for got in self._until(deadline):
                self._handle(got)
                if all(b.erased or b.refusal or b.lacks is not None for b in pending):
                    break
            for b in pending:
                if b.refusal and not b.erased:
                    b.alive = False
                    b.failure = "refused the transfer: " + b.refusal
            pending = [b for b in pending if b.alive and not b.erased]
            if not pending or attempt == attempts - 1:
                break
            self._check_others("this host stopped before sending data")
            for b in pending:
                self._check_cancel()
                for frame in self._repair(plan, b):
                    self._send(frame, b.address)
        for b in state.values():
            if b.alive and not b.erased:
                b.alive = False
                b.failure = ("did not report erased flash (Ready ERASED), asked "
                             f"{attempts} times")

    def _repair(self, plan: TransferPlan, b: _Board) -> list[m.BootMessage]:
        """The frames that complete board ``b``'s preamble, from what it said it lacks.
        After silence PREPARE alone: its answer, or PREPARE, was lost, or the board is
        still erasing (it ignores PREPARE then); BEGIN would restart its erase, so the
        whole preamble goes only to a board that says no BEGIN came."""
        lacks, b.lacks = b.lacks, None
        if lacks is None:
            b.silent += 1
            return [plan.prepare()]
        lack, info = lacks
        if lack is PrepareLack.META_INCOMPLETE:
            return [*(f for f in plan.meta() if info >> f.field & 1), plan.prepare()]
        if lack is PrepareLack.ERASE_INCOMPLETE:
            return [*plan.erases(), plan.prepare()]
        return self._preamble_frames(plan)

    # ------------------------------------------------------------------ data
    def _stream(self, plan: TransferPlan, needed: dict[int, set[int]],
                total: int | None) -> int:
        """Send the needed frames of each block; returns the number of data frames."""
        sent = 0
        sent_bytes = 0
        send_raw = self.link.send_raw
        filling = self._filling()
        others = self.others
        if others is not None and needed:
            others.sending_data()
            others.pause()  # the hot path: the BLOCK frames are reported by _send
        try:
            for i in sorted(needed):
                self._check_cancel()
                if others is not None and others.seen:
                    self._check_others("both transfers are lost")
                block = plan.blocks[i]
                self._send(block.header())
                raw = block.payload()
                for slot in sorted(needed[i]):  # the hot path: frames as (identifier, bytes)
                    if filling:
                        self._admit(filling)
                    send_raw(DATA_ID | slot, raw[8 * slot:8 * slot + 8])
                    if filling:
                        self._admitted(filling)
                    sent += 1
                    if sent % POLL_EVERY == 0:
                        self._poll()
                self.frames_sent += len(needed[i])
                sent_bytes += 8 * len(needed[i])
                if total is not None and self.progress is not None:
                    self.progress(min(sent_bytes, total), total)
        finally:
            if others is not None:
                others.resume()
        return sent

    def _filling(self) -> list[_Board]:
        """The boards whose receive ring this host's data frames can fill: those that
        said how large it is and need longer per frame than the shortest data frame takes
        on the bus (the others keep up with any sender)."""
        shortest = unstuffed_bits(8) / self.link.bitrate
        return [b for b in self._state.values()
                if b.alive and b.erased and b.ring and b.frame_us / 1e6 > shortest]

    def _admit(self, filling: list[_Board]) -> None:
        """Wait, handling what arrives, until the next data frame finds room in every
        filling board's ring by the host's reckoning: no board holds more than its ring
        less :data:`RING_RESERVE` frames when the frame passes (at the link's horizon, or
        a frame's wire time from now).  PAUSE alone cannot promise that where the host runs
        ahead of the bus (a network bus, a deep transmit queue): the frames handed over
        before PAUSE arrives reach the board all the same.  The wait is bounded by what the
        boards have to work off."""
        link = self.link
        wire = link.wire_time(1)
        gate = max(b.busy_until - max(1, b.ring - RING_RESERVE) * b.frame_us / 1e6
                   for b in filling)
        while True:
            now = link.clock()
            horizon = link.horizon
            if (horizon if horizon > now else now) + wire >= gate:
                return
            got = link.recv_until(gate - wire)
            if got is not None:
                self._handle(got)
                if self._paused:
                    self._poll()  # a board paused meanwhile: its RESUME first

    def _admitted(self, filling: list[_Board]) -> None:
        """A data frame was handed over: it reaches every board at the link's horizon and
        keeps it busy for its time per frame."""
        passes = self.link.horizon
        for b in filling:
            busy = b.busy_until
            b.busy_until = (busy if busy > passes else passes) + b.frame_us / 1e6

    def _poll(self) -> None:
        """Handle what arrived; while a board paused, wait for its RESUME, at most as long
        as it needs to drain its ring (a lost RESUME must not stall the transfer)."""
        while (got := self.link.recv_until(self.link.clock())) is not None:
            self._handle(got)
        while self._paused:
            addr, until = min(self._paused.items(), key=lambda kv: kv[1])
            got = self.link.recv_until(until)
            if got is None:
                self._paused.pop(addr, None)
            else:
                self._handle(got)

    # ------------------------------------------------------------------ end
    def _end(self, plan: TransferPlan) -> None:
        """END, and every board's Program Finished with its reports; END asked again
        (addressed) of a board whose RESULT did not come.  A board still silent after
        that is not given up: the next round asks it again."""
        waiting = [b for b in self._state.values() if b.alive and not b.verified]
        for b in waiting:
            b.result = None
            b.reports = []
        self._send(m.ProgramEnd())
        board_time = self.timeouts.verify(plan.size_words)
        asks = {b.address: 1 for b in waiting}
        for attempt in range(1 + self.timeouts.retries):
            lacking = [b for b in waiting if not b.answered]
            deadline = self.link.deadline(board_time,
                                          answers=len(lacking) * (1 + MAX_REPORTS))
            for got in self._until(deadline):
                self._handle(got)
                if all(b.answered or not b.alive for b in lacking):
                    break
            lacking = [b for b in waiting if b.alive and b.result is None]
            if not lacking or attempt == self.timeouts.retries:
                break
            for b in lacking:
                self._send(m.ProgramEnd(), b.address)
                asks[b.address] += 1
        for b in waiting:
            b.unanswered = 0 if b.result is not None else b.unanswered + asks[b.address]

    def _missing(self, plan: TransferPlan) -> tuple[dict[int, set[int]], bool]:
        """What to send again (the union over the boards), and whether the round made
        progress: a board verified, or what a board reported (its RESULT's number of
        reports and the reports that came) changed.  A board that did not answer gets
        again what it reported the round before."""
        needed: dict[int, set[int]] = {}
        progress = False
        for b in self._state.values():
            if not b.alive:
                continue
            r = b.result
            if r is None:
                again: frozenset[tuple[int, int]] = b.missing or frozenset()
            elif r.status is ResultStatus.VERIFIED:
                progress |= b.missing is None or bool(b.missing)
                b.missing = frozenset()
                continue
            elif r.status is not ResultStatus.MISSING:
                b.alive = False
                b.failure = r.status.text + (
                    f" (board computed 0x{r.progid:08X}, image has 0x{plan.progid:08X})"
                    if r.status is ResultStatus.PROGID_MISMATCH else "")
                continue
            else:
                lacks = frozenset(self._reported(plan, b))
                said = (r.reports, lacks)
                progress |= said != b.said
                b.said = said
                b.missing = again = lacks  # a lost report: its frames are asked next round
            b.resent += len(again)
            for i, s in again:
                needed.setdefault(i, set()).add(s)
        return needed, progress

    @staticmethod
    def _reported(plan: TransferPlan, b: _Board) -> set[tuple[int, int]]:
        """The (block, slot) pairs board ``b``'s MISSING and PARTIAL reports name."""
        lacks: set[tuple[int, int]] = set()
        for rep in b.reports:
            if isinstance(rep, m.ProgramMissing):
                for i in range(rep.first, min(rep.first + rep.count, len(plan.blocks))):
                    lacks.update((i, s) for s in range(plan.blocks[i].frames))
            elif rep.block < len(plan.blocks):
                lacks.update((rep.block, s) for s in range(rep.first, rep.first + rep.count)
                             if s < plan.blocks[rep.block].frames)
        return lacks

    # ------------------------------------------------------------------ receiving
    def _handle(self, got: Received) -> None:
        b = self._state.get(got.address)
        if b is None:
            return
        msg = got.message
        if isinstance(msg, m.Ready):
            if msg.reason is ReadyReason.ERASED:
                b.erased = True
                b.frame_us = float(msg.value32 or b.frame_us)
                b.ring = msg.value16
            elif msg.reason is ReadyReason.PAUSE:
                drain = msg.value16 * b.frame_us / 1e6
                self._paused[got.address] = self.link.deadline(drain)
            elif msg.reason is ReadyReason.RESUME:
                self._paused.pop(got.address, None)
        elif isinstance(msg, m.Error):
            b.errors.append(msg.describe())
            if msg.function == Function.PROGRAM:
                if msg.code is ErrorCode.SEQUENCE:
                    b.lacks = split_prepare_lack(msg.detail)
                elif msg.code in REFUSALS and not b.erased:
                    b.refusal = msg.describe()
        elif isinstance(msg, m.ProgramResult):
            b.result = msg
            b.reports = []
        elif isinstance(msg, m.ProgramMissing | m.ProgramPartial):
            b.reports.append(msg)

    def _outcome(self, b: _Board, progid: int) -> BoardOutcome:
        errors = tuple(b.errors)
        r = b.result
        if b.verified and r is not None and r.progid == progid:
            return BoardOutcome(b.address, True, r.progid, "verified", b.resent, errors)
        if b.verified and r is not None:
            return BoardOutcome(b.address, False, r.progid,
                                f"board reports ProgID 0x{r.progid:08X}, image has "
                                f"0x{progid:08X}", b.resent, errors)
        return BoardOutcome(b.address, False, r.progid if r and r.progid else None,
                            b.failure or "no answer", b.resent, errors)
