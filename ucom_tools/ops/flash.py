"""Programming images into boards: ``ucom flash`` (and console options 5, 6, 20).

Per bus, all buses in parallel: init chain with diagnostics, pre-flight checks, boards
running a program back to the bootloader (XReset), ProgEnable, one broadcast transfer,
ProgID verification of every board (and a read-back of its Info), resending only what a
board missed, then AutoStart and Start when asked.  A board is reported programmed only
when it verified.

Another host programming the same bus is noticed (:class:`~ucom_tools.protocol.
programmer.ProgrammingWatch`): :func:`listen_first` before anything is sent (``ucom
flash`` calls it before its reset), and the job itself before it sends to the boards
and before its data; either raises :class:`~ucom_tools.errors.BusError` (exit code 4).

Interrupted at any step (its ``cancel`` event set by Ctrl-C, SIGTERM or SIGHUP, or a
:class:`KeyboardInterrupt` in the thread that runs it), the job stops where it is, puts
each bus's boards back (:func:`~ucom_tools.ops.leave.put_back`: ABORT if the transfer
began, ProgEnable cleared, AutoStart set again on a board its XReset cleared it on and
whose program is intact, every board's Info read) and raises :class:`FlashInterrupted`,
whose result says per board what it was left with (:mod:`ucom_tools.ops.leave`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass, field, replace

from ucom_tools.errors import InputError, UcomError, UcomTimeoutError
from ucom_tools.image.model import Image
from ucom_tools.ops import leave
from ucom_tools.ops.compat import compare
from ucom_tools.ops.enumerate import (
    BusEnumeration,
    describe_missing,
    enumerate_bus,
    expected_positions,
    missing_expected,
)
from ucom_tools.ops.options import NotInitialised
from ucom_tools.ops.robot import BusHandle, Robot
from ucom_tools.protocol.programmer import Cancelled, Programmer
from ucom_tools.protocol.watch import ProgrammingWatch, quiet_time
from ucom_tools.wire import messages as m
from ucom_tools.wire.codes import BoardState, StatusOp, Target
from ucom_tools.wire.descriptor import ImageDescriptor
from ucom_tools.wire.ids import ALL, Address, IdType, seq
from ucom_tools.wire.info import BoardInfo
from ucom_tools.wire.transfer import TransferPlan

ASK_SERIES = 2
"""An answer the job cannot go on without (a board's Info record, its acknowledgement of
ProgEnable) is asked for in up to this many series of questions (``1 + retries`` each):
an Info record is ten frames, and on a bus that loses 5 % of the frames each way one of
them is missing from all three answers of a series about once in a hundred records."""

ProgressFn = Callable[[str, int, int, int], None]
Notes = dict[int, tuple[str, ...]]
"""progress(bus, bytes sent, bytes total, boards)"""

LISTENING = "listening"
KEEP = "reading the values to keep"
RESET = "reset"
INIT = "init chain"
XRESET = "XReset"
ENABLE = "ProgEnable"
ERASE = "erase"
TRANSFER = "transfer"
VERIFICATION = "verification"
AUTOSTART = "AutoStart"
START = "start"
FINISHED = "finished"
NOT_BEGUN = "not begun"
PHASES = (NOT_BEGUN, LISTENING, KEEP, RESET, INIT, XRESET, ENABLE, ERASE, TRANSFER,
          VERIFICATION, AUTOSTART, START, FINISHED)
"""Where an interrupt can find a flash on a bus, in order (``not begun``: another bus's
job was interrupted first; ``finished``: the job was done when it saw the interrupt);
listening, reading the values to keep (``--keep-params``) and the reset are ``ucom
flash``'s, before the job."""


@dataclass(frozen=True)
class Selection:
    """Which boards to program: every board found, the ProgEnabled ones, or seq IDs."""

    kind: str  # "all" | "enabled" | "list"
    numbers: tuple[int, ...] = ()

    @classmethod
    def parse(cls, text: str) -> Selection:
        if text.strip().lower() == "all":
            return cls("all")
        try:
            nums = tuple(sorted({int(x) for x in text.split(",") if x.strip()}))
        except ValueError:
            raise InputError(f"{text!r}: expected 'all' or seq IDs like 1,3,5",
                             key="--boards") from None
        if not nums or not all(1 <= n <= 31 for n in nums):
            raise InputError(f"{text!r}: seq IDs are 1-31", key="--boards")
        return cls("list", nums)


@dataclass(frozen=True)
class BoardResult:
    bus: str
    seq_id: int
    """0 for a board the topology expects that never answered (outcome "missing")."""
    serial: int | None
    placement: str | None
    outcome: str  # "verified" | "failed"
    progid: int | None
    detail: str
    resent_frames: int = 0
    """Data frames this board lacked after a round and that were sent again."""
    autostart: bool = False
    started: bool | None = None
    messages: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    left: BoardInfo | None = None
    """After an interrupt: the board's Info as the job left it (None: not read)."""

    @property
    def verified(self) -> bool:
        return self.outcome == "verified"


@dataclass(frozen=True)
class BusFlash:
    bus: str
    boards: tuple[BoardResult, ...]
    enumeration: BusEnumeration | None
    frames: int
    rounds: int
    note: str = ""
    resent_frames: int = 0
    interrupted: str = ""
    """The phase (:data:`PHASES`) an interrupt found the job in on this bus ("": none)."""


@dataclass(frozen=True)
class FlashResult:
    image: str
    progid: int
    size_words: int
    target: Target
    buses: tuple[BusFlash, ...] = field(default=())

    @property
    def boards(self) -> list[BoardResult]:
        return [b for bus in self.buses for b in bus.boards]

    @property
    def all_verified(self) -> bool:
        return bool(self.boards) and all(b.verified for b in self.boards)

    @property
    def failed(self) -> list[BoardResult]:
        """Boards not verified, or verified but not started although a start was asked."""
        return [b for b in self.boards if not b.verified or b.started is False]

    @property
    def interrupted(self) -> bool:
        return any(bus.interrupted for bus in self.buses)


class FlashInterrupted(KeyboardInterrupt):
    """A flash ended by an interrupt (Ctrl-C, SIGTERM, SIGHUP, its cancel event) after it
    put every bus's boards back; :attr:`result` says per board what it was left with
    (outcomes of :mod:`ucom_tools.ops.leave`, the Info in ``left``) and per bus in which
    phase the interrupt came.  Raised from the interrupt (``__cause__``: its signal)."""

    def __init__(self, result: FlashResult) -> None:
        super().__init__("flash interrupted")
        self.result = result


def flash(robot: Robot, image: Image, *, selection: Selection = Selection("all"),
          bus: str | None = None, target: Target = Target.FLASH, init: bool = True,
          autostart: bool = False, start: bool = False, verify: bool = True,
          progress: ProgressFn | None = None, cancel: threading.Event | None = None,
          plan: TransferPlan | None = None, force: bool = False,
          what: str = "programming") -> FlashResult:
    """Program ``image`` into the selected boards of every selected bus, in parallel.

    Boards whose plug-on board, FPGA (Board-ID, App-ID, major version) do not fit the
    image's descriptor are refused unless ``force``; a minor version difference or a
    missing descriptor is a warning."""
    plan = plan or image.plan(target=target)
    handles = robot.select(bus)
    cancel = cancel or threading.Event()
    job = _Job(plan, selection, init, autostart, start, verify, progress, cancel,
               image.descriptor, force, what)
    stop: BaseException | None = None
    if len(handles) == 1 or robot.virtual_time:
        # In virtual time the fleet clock is driven by whoever waits: threads would only
        # take turns on the fleet's lock, one frame at a time; one after the other is as
        # correct and much faster.
        results = []
        for h in handles:
            if stop is not None:  # an interrupted job begins no other bus
                results.append(not_begun(h, NOT_BEGUN))
                continue
            results.append(job.run(h))
            stop = job.stops.get(h.name)
    else:
        with ThreadPoolExecutor(max_workers=len(handles)) as pool:
            futures = [pool.submit(job.run, h) for h in handles]
            try:
                wait(futures)
            except KeyboardInterrupt as e:  # in this thread: every bus stops and undoes
                stop = e
                cancel.set()
                wait(futures)
        results = [f.result() for f in futures]
        stop = stop or next((job.stops[h.name] for h in handles if h.name in job.stops), None)
    if stop is not None:  # a bus whose job was done when the others were interrupted
        results = [r if r.interrupted else replace(r, interrupted=FINISHED) for r in results]
    result = FlashResult(image.name, plan.progid, plan.size_words, target, tuple(results))
    if stop is not None:
        raise FlashInterrupted(result) from stop
    return result


def at_phase(phase: str) -> str:
    """Where an interrupt came, in words: "while listening", "at the erase", "before the
    job began", "after the job was done"."""
    if phase in (LISTENING, KEEP):
        return f"while {phase}"
    if phase == NOT_BEGUN:
        return "before the job began"
    if phase == FINISHED:
        return "after the job was done"
    return f"at the {phase}"


def not_begun(h: BusHandle, phase: str) -> BusFlash:
    """Bus ``h`` when an interrupt came before the job sent it anything that changes a
    board's program or ProgEnable (``phase``: listening, the reset, the init chain, or
    :data:`NOT_BEGUN`): the boards its topology expects, each kept as found, unread."""
    boards = h.expected.boards if h.expected is not None else ()
    when = f"interrupted {at_phase(phase)} on {h.name}"
    what = ("its program as found, not erased, not ProgEnabled (the reset restarted it "
            "where AutoStart is set, else it waits in its bootloader)" if phase == RESET
            else "as found: nothing that changes its program or ProgEnable was sent")
    rows = tuple(BoardResult(h.name, 0, spec.serial if spec.serial_explicit or h.virtual
                             else None, spec.placement, leave.KEPT, None, f"{what} ({when})")
                 for spec in boards)
    return BusFlash(h.name, rows, None, 0, 0, "nothing programmed", interrupted=phase)


def interrupted_before(robot: Robot, image: Image, phase: str, *, bus: str | None = None,
                       target: Target = Target.FLASH) -> FlashResult:
    """What a flash interrupted before its job began left (``phase``: listening, reading
    the values to keep, the reset): every selected bus :func:`not_begun`."""
    plan = image.plan(target=target)
    return FlashResult(image.name, plan.progid, plan.size_words, target,
                       tuple(not_begun(h, phase) for h in robot.select(bus)))


def listen_first(robot: Robot, bus: str | None = None) -> None:
    """Listen on the selected buses, all at once, before anything is sent to them: for as
    long as a host that is programming leaves its bus silent (:func:`~ucom_tools.protocol.
    programmer.quiet_time`, a fraction of a second over socketcand).  BusError naming
    what was seen when another host is programming one of them."""
    handles = robot.select(bus)

    def one(h: BusHandle) -> None:
        with ProgrammingWatch(h.link) as watch:
            watch.listen(quiet_time(h.link, h.client.timeouts))
            watch.check(h.name, "nothing was sent; try again when it is done")

    if len(handles) == 1 or robot.virtual_time:
        for h in handles:
            one(h)
    else:
        with ThreadPoolExecutor(max_workers=len(handles)) as pool:
            list(pool.map(one, handles))


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
class _Job:
    plan: TransferPlan
    selection: Selection
    init: bool
    autostart: bool
    start: bool
    verify: bool
    progress: ProgressFn | None
    cancel: threading.Event | None
    descriptor: ImageDescriptor | None = None
    force: bool = False
    what: str = "programming"
    stops: dict[str, BaseException] = field(default_factory=dict)
    """The interrupt that ended the job, by bus."""

    def _preflight(self, h: BusHandle, targets: list[int], present: dict[int, BoardInfo],
                   results: dict[int, BoardResult],
                   placements: dict[int, tuple[int, str | None]]) -> tuple[list[int], Notes]:
        """Compare the image with every target board; refuse misfits unless forced."""
        keep: list[int] = []
        warnings: Notes = {}
        for n in targets:
            findings = compare(self.descriptor, present[n])
            errors = [f for f in findings if f.severity == "error"]
            notes = [f"warning: {f.message}" for f in findings if f.severity != "error"]
            if errors and not self.force:
                serial, placement = placements[n]
                why = "; ".join(f"{f.field}: expected {f.expected}, found {f.found} ({f.message})"
                                for f in errors)
                results[n] = BoardResult(h.name, n, serial, placement, "refused", None,
                                         f"refused: {why}; --force programs it anyway",
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
        if self.init:
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
            what = self.what[:1].upper() + self.what[1:]
            raise NotInitialised(
                f"{h.name}: no board has a seq ID yet. {what} works only after a successful "
                "init chain (option 2): run 'ucom init' first, or add --init to this "
                "command; 'ucom flash' runs it itself.")
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
        enum, infos, placements = survey
        present = {a.number: inf for a, inf in infos.items()
                   if a.id_type is IdType.SEQUENTIAL}
        st.enum, st.present, st.placements = enum, present, placements
        results = st.results
        self._check()
        if self.selection.kind == "all":
            wanted = sorted(present)
            st.absent = self._unaccounted(h, enum, present, results)
        elif self.selection.kind == "enabled":
            wanted = sorted(n for n, inf in present.items() if inf.prog_enable)
        else:
            wanted = list(self.selection.numbers)
        for n in wanted:
            if n not in present:
                results[n] = _fail(h.name, n, None, None, f"no board with seq ID {n} on {h.name}")
        targets = [n for n in wanted if n in present]
        targets, warnings = self._preflight(h, targets, present, results, placements)
        st.targets = targets
        if not targets:
            return BusFlash(h.name, (*(results[n] for n in sorted(results)), *st.absent), enum,
                            0, 0, "no board to program")
        watch.check(h.name, "nothing was programmed")
        st.phase = XRESET
        self._to_bootloader(h, targets, present, st)
        st.phase = ENABLE
        self._check()
        enabled = self._enable(h, targets, present, results, placements, st)
        frames = rounds = resent = 0
        if enabled:
            self._check()
            st.phase = ERASE
            total = self.plan.size_words * 2

            def report(sent: int, _total: int) -> None:
                if self.progress is not None:
                    self.progress(h.name, sent, total, len(enabled))

            programmer = st.programmer = Programmer(h.link, h.client.timeouts,
                                                    progress=report, cancel=self.cancel,
                                                    others=watch)
            transfer = programmer.transfer(self.plan, [seq(n) for n in enabled])
            frames, rounds = transfer.frames_sent, transfer.rounds
            resent = transfer.resent_frames
            for n in enabled:
                o = transfer.outcomes[seq(n)]
                serial, placement = placements[n]
                detail = o.status + ("; " + "; ".join(o.errors) if o.errors and not o.verified
                                     else "")
                results[n] = BoardResult(h.name, n, serial, placement,
                                         "verified" if o.verified else "failed", o.progid,
                                         detail, o.resent_frames,
                                         warnings=warnings.get(n, ()))
            st.phase = VERIFICATION
        verified = [n for n in enabled if results[n].verified]
        if self.verify and verified:
            self._read_back(h, verified, results)
            verified = [n for n in verified if results[n].verified]
        if self.autostart and verified and self.plan.target is Target.FLASH:
            st.phase = AUTOSTART
            for n in verified:
                self._check()
                ok = h.client.set_status(seq(n), StatusOp.AUTOSTART, 1)
                r = results[n]
                results[n] = replace(r, autostart=bool(ok and ok[0].ok))
        if self.start and verified:
            st.phase = START
            for n in verified:
                self._check()
                answers = h.client.start(seq(n), self.plan.target)
                r = results[n]
                started = bool(answers) and answers[0].ok
                texts = tuple(e.describe() for a in answers for e in a.errors) + tuple(
                    t for a in answers for t in a.reports)
                results[n] = replace(r, started=started, messages=r.messages + texts)
        st.phase = FINISHED
        return BusFlash(h.name, (*(results[n] for n in sorted(results)), *st.absent), enum,
                        frames, rounds, resent_frames=resent)

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


def _fail(bus: str, n: int, serial: int | None, placement: str | None,
          detail: str) -> BoardResult:
    return BoardResult(bus, n, serial, placement, "failed", None, detail)
