"""The job of a flash on one bus (:class:`BusJob`), from the init chain to the start.

:func:`ucom_tools.ops.flash.flash` runs one per bus.  Its steps: who is on the bus (a
fresh init chain, or the seq IDs the boards have) and which of them to program
(:meth:`BusJob._survey`, :meth:`BusJob._choose`); the pre-flight check of the image
against each board; boards that run a program back to their bootloader (XReset);
ProgEnable; the transfer (:class:`~ucom_tools.protocol.programmer.Programmer`); the Info
read back; AutoStart and start when asked.  What it has done so far is kept in
:class:`_Bus`, so that an interrupt at any step can undo it (:meth:`BusJob._undo`).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field, replace

from ucom_tools.errors import UcomError, UcomTimeoutError
from ucom_tools.ops import leave
from ucom_tools.ops.compat import compare
from ucom_tools.ops.enumerate import (
    BusEnumeration,
    describe_missing,
    enumerate_bus,
    expected_positions,
    missing_expected,
)
from ucom_tools.ops.flash_types import (
    AUTOSTART,
    ENABLE,
    ERASE,
    FINISHED,
    INIT,
    START,
    VERIFICATION,
    XRESET,
    BoardResult,
    BusFlash,
    FlashRequest,
    ProgressFn,
    at_phase,
    not_begun,
)
from ucom_tools.ops.options import NotInitialised
from ucom_tools.ops.robot import BusHandle
from ucom_tools.protocol.programmer import Cancelled, Programmer
from ucom_tools.protocol.watch import ProgrammingWatch
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import BoardState, StatusOp, Target
from ucom_tools.wire.ids import ALL, Address, IdType, seq
from ucom_tools.wire.info import BoardInfo
from ucom_tools.wire.transfer import TransferPlan

ASK_SERIES = 2
"""An answer the job cannot go on without (a board's Info record, its acknowledgement of
ProgEnable) is asked for in up to this many series of questions (``1 + retries`` each):
an Info record is ten frames, and on a bus that loses 5 % of the frames each way one of
them is missing from all three answers of a series about once in a hundred records."""

Notes = dict[int, tuple[str, ...]]
"""Warnings by seq ID."""


@dataclass
class _Bus:
    """What the job has done on one bus so far: what an undo needs to know."""

    phase: str = INIT
    enum: BusEnumeration | None = None
    present: dict[int, BoardInfo] = field(default_factory=dict)
    """The boards found, by seq ID, with their Info as found."""
    placements: dict[int, tuple[int, str | None]] = field(default_factory=dict)
    targets: list[int] = field(default_factory=list)
    xreset: dict[int, bool] = field(default_factory=dict)
    """Boards sent XReset (which clears AutoStart), with their AutoStart as found."""
    enabling: set[int] = field(default_factory=set)
    """Boards that were (or were being) asked for ProgEnable."""
    programmer: Programmer | None = None
    results: dict[int, BoardResult] = field(default_factory=dict)
    absent: list[BoardResult] = field(default_factory=list)


@dataclass
class BusJob:
    """The flash of ``request`` on each bus :meth:`run` is given (one job serves every bus
    of a flash: what is per bus lives in :class:`_Bus`)."""

    request: FlashRequest
    plan: TransferPlan
    progress: ProgressFn | None = None
    cancel: threading.Event | None = None
    stops: dict[str, BaseException] = field(default_factory=dict)
    """The interrupt that ended the job, by bus."""

    def _preflight(self, h: BusHandle, targets: list[int], present: dict[int, BoardInfo],
                   results: dict[int, BoardResult],
                   placements: dict[int, tuple[int, str | None]]) -> tuple[list[int], Notes]:
        """Compare the image with every target board; refuse misfits unless forced."""
        keep: list[int] = []
        warnings: Notes = {}
        for n in targets:
            findings = compare(self.request.image.descriptor, present[n])
            errors = [f for f in findings if f.severity == "error"]
            notes = [f"warning: {f.message}" for f in findings if f.severity != "error"]
            if errors and not self.request.force:
                serial, placement = placements[n]
                why = "; ".join(f"{f.field}: expected {f.expected}, found {f.found} ({f.message})"
                                for f in errors)
                results[n] = BoardResult(h.name, n, serial, placement, "refused", None,
                                         f"refused: {why}",
                                         warnings=tuple(notes))
                continue
            notes = [f"forced despite: {f.message}" for f in errors] + notes
            warnings[n] = tuple(notes)
            keep.append(n)
        return keep, warnings

    def _survey(self, h: BusHandle) -> BusFlash | tuple[
            BusEnumeration | None, dict[Address, BoardInfo], dict[int, tuple[int, str | None]]]:
        """Who is on the bus (with a fresh init chain, or the numbers the boards have), and
        where; a faulty chain ends the job for this bus."""
        if self.request.init:
            enum = enumerate_bus(h)
            if any(b.duplicate for b in enum.boards) or any(
                    d.kind == "fixed-id-clash" for d in enum.diagnosis):
                why = "; ".join(d.message for d in enum.diagnosis)
                rows = tuple(_fail(h.name, b.seq_id, b.serial, b.placement,
                                   f"not programmed: the init chain is faulty ({why})")
                             for b in enum.boards)
                return BusFlash(h.name, rows, enum, 0, 0, "init chain faulty")
            infos = {seq(b.seq_id): b.info for b in enum.boards if b.info is not None}
            for b in enum.boards:
                if b.info is None and not b.duplicate:
                    again = _info(h, b.seq_id, ASK_SERIES - 1)
                    if again is not None and again.serial == b.serial:
                        infos[seq(b.seq_id)] = again
            return enum, infos, {b.seq_id: (b.serial, b.placement) for b in enum.boards}
        infos = h.client.info_many(ALL)
        if not infos:
            raise NotInitialised(h.name)
        firsts = h.client.probe()
        if len(firsts) > 1:
            serials = ", ".join(f"0x{a.serial:08X}" for a in firsts)
            rows = tuple(_fail(h.name, a.number, inf.serial, None,
                               "not programmed: the init chain is faulty (Get First: "
                               f"{len(firsts)} boards answer, serials {serials}); two "
                               "boards may share this seq ID")
                         for a, inf in sorted(infos.items(), key=lambda kv: kv[0].number))
            return BusFlash(h.name, rows, None, 0, 0, "init chain faulty")
        boards = h.expected.boards if h.expected is not None else ()
        known = {serial: boards[pos].placement for serial, pos in expected_positions(h).items()}

        def placement(a: Address, serial: int) -> str | None:
            if known or a.number > len(boards):
                return known.get(serial)
            return boards[a.number - 1].placement  # a sound chain: topology order

        return None, infos, {a.number: (inf.serial, placement(a, inf.serial))
                             for a, inf in infos.items() if a.id_type is IdType.SEQUENTIAL}

    def run(self, h: BusHandle) -> BusFlash:
        """The job on bus ``h``; interrupted, the bus's boards put back and said per board
        (:meth:`_undo`), the interrupt kept in :attr:`stops`."""
        st = _Bus()
        try:
            with ProgrammingWatch(h.link) as watch:
                return self._run(h, watch, st)
        except (KeyboardInterrupt, Cancelled) as stop:
            self.stops[h.name] = stop
            return self._undo(h, st)

    def _check(self) -> None:
        """Between two steps: stop here if the job was cancelled."""
        if self.cancel is not None and self.cancel.is_set():
            raise Cancelled("cancelled")

    def _run(self, h: BusHandle, watch: ProgrammingWatch, st: _Bus) -> BusFlash:
        st.phase = INIT
        survey = self._survey(h)
        if isinstance(survey, BusFlash):
            return survey
        st.enum, infos, st.placements = survey
        st.present = {a.number: inf for a, inf in infos.items()
                      if a.id_type is IdType.SEQUENTIAL}
        self._check()
        warnings = self._choose(h, st)
        if not st.targets:
            return BusFlash(h.name, _rows(st), st.enum, 0, 0, "no board to program")
        watch.check(h.name, "nothing was programmed")
        st.phase = XRESET
        self._to_bootloader(h, st.targets, st.present, st)
        st.phase = ENABLE
        self._check()
        enabled = self._enable(h, st.targets, st.present, st.results, st.placements, st)
        frames = rounds = resent = 0
        if enabled:
            self._check()
            st.phase = ERASE
            frames, rounds, resent = self._transfer(h, watch, st, enabled, warnings)
            st.phase = VERIFICATION
        verified = [n for n in enabled if st.results[n].verified]
        if self.request.verify and verified:
            self._read_back(h, verified, st.results)
            verified = [n for n in verified if st.results[n].verified]
        self._autostart_and_start(h, st, verified)
        st.phase = FINISHED
        return BusFlash(h.name, _rows(st), st.enum, frames, rounds, resent_frames=resent)

    def _choose(self, h: BusHandle, st: _Bus) -> Notes:
        """The boards to program (:attr:`_Bus.targets`): the selection's, those not on the
        bus failed, those the image does not fit refused (unless forced); the warnings
        of the others."""
        present, results = st.present, st.results
        selection = self.request.selection
        if selection.kind == "all":
            wanted = sorted(present)
            st.absent = self._unaccounted(h, st.enum, present, results)
        elif selection.kind == "enabled":
            wanted = sorted(n for n, inf in present.items() if inf.prog_enable)
        else:
            wanted = list(selection.numbers)
        for n in wanted:
            if n not in present:
                results[n] = _fail(h.name, n, None, None, f"no board with seq ID {n} on {h.name}")
        targets = [n for n in wanted if n in present]
        st.targets, warnings = self._preflight(h, targets, present, results, st.placements)
        return warnings

    def _transfer(self, h: BusHandle, watch: ProgrammingWatch, st: _Bus, enabled: list[int],
                  warnings: Notes) -> tuple[int, int, int]:
        """The image to the ProgEnabled boards in one broadcast, each board's outcome in
        :attr:`_Bus.results`; returns the frames sent, the rounds and the frames resent."""
        total = self.plan.size_words * 2

        def report(sent: int, _total: int) -> None:
            if self.progress is not None:
                self.progress(h.name, sent, total, len(enabled))

        programmer = st.programmer = Programmer(h.link, h.client.timeouts, progress=report,
                                                cancel=self.cancel, others=watch)
        transfer = programmer.transfer(self.plan, [seq(n) for n in enabled])
        for n in enabled:
            o = transfer.outcomes[seq(n)]
            serial, placement = st.placements[n]
            detail = o.status + ("; " + "; ".join(o.errors) if o.errors and not o.verified
                                 else "")
            st.results[n] = BoardResult(h.name, n, serial, placement,
                                        "verified" if o.verified else "failed", o.progid,
                                        detail, o.resent_frames, warnings=warnings.get(n, ()))
        return transfer.frames_sent, transfer.rounds, transfer.resent_frames

    def _autostart_and_start(self, h: BusHandle, st: _Bus, verified: list[int]) -> None:
        """AutoStart set on, and a start of, the verified boards, as the request asks."""
        results = st.results
        if self.request.autostart and verified and self.plan.target is Target.FLASH:
            st.phase = AUTOSTART
            for n in verified:
                self._check()
                ok = h.client.set_status(seq(n), StatusOp.AUTOSTART, 1)
                results[n] = replace(results[n], autostart=bool(ok and ok[0].ok))
        if self.request.start and verified:
            st.phase = START
            for n in verified:
                self._check()
                answers = h.client.start(seq(n), self.plan.target)
                r = results[n]
                started = bool(answers) and answers[0].ok
                texts = tuple(e.describe() for a in answers for e in a.errors) + tuple(
                    t for a in answers for t in a.reports)
                results[n] = replace(r, started=started, messages=r.messages + texts)

    def _undo(self, h: BusHandle, st: _Bus) -> BusFlash:
        """After an interrupt on bus ``h``: put its boards back (ABORT if the transfer
        began, ProgEnable cleared, AutoStart set again where the job's XReset cleared it
        and the program is intact) and say per board what it was left with."""
        prog = st.programmer
        phase = st.phase
        if phase == ERASE:  # where the transfer was; before its BEGIN: still ProgEnable
            phase = prog.step if prog is not None and prog.began else ENABLE
        if not st.present:  # the init chain did not finish: nothing else was sent
            return replace(not_begun(h, phase), enumeration=st.enum)
        verified = {n for n, r in st.results.items() if r.verified}
        touched = set(st.targets) | st.enabling | set(st.xreset)
        if not st.targets:  # interrupted before it chose them: every board it found
            touched |= set(st.present)
        infos, notes = leave.put_back(h, abort=prog is not None and prog.began,
                                      enabled=st.enabling - verified, ask=touched)
        rows = dict(st.results)
        for n in sorted(touched):
            old = st.present.get(n)
            left = leave.judge(infos.get(n), old_progid=old.progid if old is not None
                               and old.flash_valid else None, new_progid=self.plan.progid,
                               verified=n in verified, target=self.plan.target)
            detail = left.detail
            info = left.info
            if (left.outcome == leave.KEPT and st.xreset.get(n) and info is not None
                    and info.flash_valid and not info.autostart):
                try:  # the XReset cleared it; the program is intact: as found
                    ok = h.client.set_status(seq(n), StatusOp.AUTOSTART, 1)
                except UcomError:
                    ok = []
                detail += ("; AutoStart set again" if ok and ok[0].ok
                           else "; AutoStart (cleared by its XReset) could not be set again")
                info = replace(info, autostart=bool(ok and ok[0].ok))
            if n not in st.enabling and left.outcome == leave.KEPT:
                detail += f" (interrupted {at_phase(phase)}, before its ProgEnable)"
            serial, placement = st.placements.get(n, (None, None))
            was = rows.get(n)
            rows[n] = BoardResult(h.name, n, serial, placement, left.outcome,
                                  info.progid if info is not None and info.flash_valid
                                  else None, detail,
                                  was.resent_frames if was is not None else 0,
                                  autostart=was.autostart if was is not None else False,
                                  started=was.started if was is not None else None,
                                  messages=(was.messages if was is not None else ()) +
                                  tuple(notes),
                                  warnings=was.warnings if was is not None else (),
                                  left=info)
        prog_frames = prog.frames_sent if prog is not None else 0
        return BusFlash(h.name, (*(rows[n] for n in sorted(rows)), *st.absent), st.enum,
                        prog_frames, 0, f"interrupted {at_phase(phase)}", interrupted=phase)

    def _unaccounted(self, h: BusHandle, enum: BusEnumeration | None,
                     present: dict[int, BoardInfo], results: dict[int, BoardResult]
                     ) -> list[BoardResult]:
        """Boards that cannot be programmed although they belong to the job: found by the
        init chain without an Info record, and expected by the topology without answering
        at all.  Each becomes a failed result, so the job cannot end "all verified"."""
        found = list(enum.boards) if enum is not None else []
        for b in found:
            if b.info is None and b.seq_id not in present and not b.duplicate:
                results[b.seq_id] = _fail(
                    h.name, b.seq_id, b.serial, b.placement,
                    "answered the init chain, but its Info record did not arrive "
                    f"(asked {1 + h.client.timeouts.retries} times); not programmed")
        serials = [b.serial for b in found] + [inf.serial for inf in present.values()]
        answered = len(found) if enum is not None else len(present)
        expected = len(h.expected.boards) if h.expected is not None else 0
        return [BoardResult(h.name, 0, spec.serial if spec.serial_explicit or h.virtual
                            else None, spec.placement, "missing", None,
                            describe_missing(h.name, spec, expected))
                for spec in missing_expected(h, serials, answered)]

    def _to_bootloader(self, h: BusHandle, targets: list[int],
                       present: dict[int, BoardInfo], st: _Bus) -> None:
        for n in targets:
            if present[n].state in (BoardState.RUNNING_FLASH, BoardState.RUNNING_EXTRAM):
                self._check()
                st.xreset[n] = present[n].autostart  # before: the XReset may go out
                h.client.reset(seq(n), clear_autostart=True)

    def _enable(self, h: BusHandle, targets: list[int], present: dict[int, BoardInfo],
                results: dict[int, BoardResult],
                placements: dict[int, tuple[int, str | None]], st: _Bus) -> list[int]:
        others = [n for n, inf in present.items() if inf.prog_enable and n not in targets]
        for n in others:  # never program a board that was not asked for
            h.client.set_status(seq(n), StatusOp.PROG_ENABLE, 0)
        st.enabling.update(targets)  # before the request: an interrupt may cut it after
        if set(targets) == set(present):
            replies = h.client.set_status(ALL, StatusOp.PROG_ENABLE, 1,
                                          expect=[seq(n) for n in targets])
        else:
            replies = [r for n in targets
                       for r in h.client.set_status(seq(n), StatusOp.PROG_ENABLE, 1)]
        for _ in range(ASK_SERIES - 1):
            answered = {r.address.number for r in replies}
            replies += [r for n in targets if n not in answered
                        for r in h.client.set_status(seq(n), StatusOp.PROG_ENABLE, 1)]
        ok = {r.address.number for r in replies if r.ok}
        for r in replies:
            if not r.ok and isinstance(r.message, m.Error):
                serial, placement = placements.get(r.address.number, (None, None))
                results[r.address.number] = _fail(h.name, r.address.number, serial, placement,
                                                  "refused ProgEnable: " + r.message.describe())
        for n in targets:
            if n not in ok and n not in results:
                serial, placement = placements[n]
                results[n] = _fail(h.name, n, serial, placement, "did not acknowledge ProgEnable")
        return [n for n in targets if n in ok]

    def _read_back(self, h: BusHandle, verified: list[int],
                   results: dict[int, BoardResult]) -> None:
        for n in verified:
            self._check()
            r = results[n]
            inf = _info(h, n, ASK_SERIES)
            if inf is None:
                results[n] = replace(r, outcome="failed",
                                      detail="verified, but the Info read-back timed out")
                continue
            valid = inf.flash_valid if self.plan.target is Target.FLASH else inf.extram_valid
            if not valid or inf.progid != self.plan.progid:
                results[n] = replace(r, outcome="failed", detail=(
                    f"Info read-back shows ProgID 0x{inf.progid:08X}, valid={valid}"))


def _info(h: BusHandle, n: int, series: int) -> BoardInfo | None:
    """Board ``n``'s Info record, asked for in up to ``series`` series of questions."""
    for _ in range(series):
        try:
            return h.client.info(Address(IdType.SEQUENTIAL, n))
        except UcomTimeoutError:
            continue
    return None


def _rows(st: _Bus) -> tuple[BoardResult, ...]:
    """The bus's rows: by seq ID, then the expected boards that never answered."""
    return (*(st.results[n] for n in sorted(st.results)), *st.absent)


def _fail(bus: str, n: int, serial: int | None, placement: str | None,
          detail: str) -> BoardResult:
    return BoardResult(bus, n, serial, placement, "failed", None, detail)

