"""Bringing a robot to its manifest: ``ucom deploy``.

The manifest is the robot's topology: per board the image it should run (``image =``)
and whether it starts by itself (``autostart =``), and its attribute tree.  A deploy

1. plans (:func:`plan`): every bus's init chain and every board's Info (with its FPGA
   registers), compared with its image: *up to date*, *program* (another ProgID, no
   program, interrupted by an earlier deploy), *restore* (the right program, but the
   parameters an interrupted deploy saved are still to be loaded back), *start* (the
   right program, only its AutoStart flag or its start missing), or *refused* (the image
   does not fit the board, the board is missing, the chain is faulty);
2. executes (:func:`execute`), each phase on every bus in parallel: the parameters of the
   boards to program that run a program are dumped into the journal; each image is sent
   once per bus to the boards that need it (one broadcast per image; KAIRO-II has two on
   its bus), verified and read back; the saved parameters are loaded back; AutoStart is
   set as the manifest says and the programs are started.

Boards that are up to date are never reset, stopped or sent anything but the init
chain's and Info's requests: the init chain renumbers a running board without touching
its program (``man/ucom-protocol.7``), the programming job resets (XReset) and
ProgEnables only the seq IDs it programs, and the data frames of a transfer are ignored
by a board that runs its program.

The journal (:class:`Journal`, a directory: ``journal.json`` and ``params/``) records
the plan, each board's progress and the parameter dumps, every change written
atomically (:mod:`ucom_tools.fileio`).  A deploy killed at any point leaves it behind;
the next one resumes from it (boards left in their bootloader or unverified are
programmed again, their saved parameters loaded back although no program ran to dump
them from) and removes it when the robot matches its manifest.

Interrupted at any step (its ``cancel`` event set by Ctrl-C, SIGTERM or SIGHUP, or a
:class:`KeyboardInterrupt` in the thread that runs it), a deploy stops where it is (a
flash under way puts its boards back itself: :mod:`ucom_tools.ops.flash`), then makes
sure on every bus that no board it works on is left ProgEnabled or in a transfer (ABORT,
ProgEnable cleared, every such board's Info read: :func:`~ucom_tools.ops.leave.put_back`)
and raises :class:`DeployInterrupted`, whose result says per board what it was left
with; the journal stays, and the next deploy finishes the work.

Exit codes follow ``ucom(1)``: a manifest whose image is missing, unreadable or does not
fit its board is :class:`~ucom_tools.errors.TopologyError` before anything is sent.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from ucom_tools.config import attrtree
from ucom_tools.config.attrtree import RobotTrees
from ucom_tools.errors import InputError, UcomError
from ucom_tools.ops import leave
from ucom_tools.ops import params as params_ops
from ucom_tools.ops.compat import compare
from ucom_tools.ops.enumerate import (
    BusEnumeration,
    describe_missing,
    enumerate_bus,
    missing_expected,
)
from ucom_tools.ops.flash import flash, listen_first
from ucom_tools.ops.flash_types import FlashRequest, ProgressFn, Selection
from ucom_tools.ops.journal import (
    PARAMS_DIR,
    Journal,
    default_journal,
    safe_name,
)
from ucom_tools.ops.manifest import Manifest, Wanted, image_problems, load_manifest
from ucom_tools.ops.params_dump import live_tree
from ucom_tools.ops.robot import BusHandle, Robot
from ucom_tools.protocol.programmer import Cancelled
from ucom_tools.wire.codes import BoardState, StatusOp
from ucom_tools.wire.ids import ALL, seq
from ucom_tools.wire.info import BoardInfo

RUNNING = (BoardState.RUNNING_FLASH, BoardState.RUNNING_EXTRAM)

UP_TO_DATE = "up to date"
PROGRAM = "program"
RESTORE = "restore"
START = "start"
REFUSED = "refused"
SKIPPED = "skipped"
WORK = (PROGRAM, RESTORE, START)
"""The actions that send something to a board."""

EventFn = Callable[[str], None]
"""Told one line at each step (``CAN0: programming kairo2_alpha.fl.S into 1, 3, 5``)."""

DUMPING = "reading the parameters"
LISTENING = "listening"
PROGRAMMING = "programming"
RESTORING = "loading the parameters back"
FINISHING = "AutoStart and start"
CHECKING = "reading the result"
STEPS = (DUMPING, LISTENING, PROGRAMMING, RESTORING, FINISHING, CHECKING)
"""The steps of :func:`execute`, in order: where an interrupt can find a deploy."""


# ----------------------------------------------------------------------------- plan
@dataclass(frozen=True)
class Seen:
    """A board as it was found (``before``) or left (``after``)."""

    state: str
    progid: int | None
    program: str
    autostart: bool

    @classmethod
    def of(cls, info: BoardInfo) -> Seen:
        return cls(info.state.text, info.progid if info.flash_valid else None,
                   info.name if info.flash_valid else "", info.autostart)


@dataclass(frozen=True)
class PlanRow:
    bus: str
    seq_id: int
    """0: the board did not answer."""
    position: int
    placement: str
    serial: int | None
    image: str
    progid: int
    autostart: bool
    before: Seen | None
    action: str
    reason: str
    warnings: tuple[str, ...] = ()

    @property
    def key(self) -> str:
        return f"{self.bus}:{self.position + 1}"

    @property
    def where(self) -> str:
        return f"{self.bus}:{self.seq_id or '-'} ({self.placement})"


@dataclass(frozen=True)
class Plan:
    manifest: Manifest
    rows: tuple[PlanRow, ...]
    enumerations: tuple[BusEnumeration, ...]
    resumed: bool = False

    def on(self, bus: str, *actions: str) -> list[PlanRow]:
        return [r for r in self.rows if r.bus == bus and (not actions or r.action in actions)]

    @property
    def up_to_date(self) -> list[PlanRow]:
        return [r for r in self.rows if r.action == UP_TO_DATE]

    @property
    def changes(self) -> list[PlanRow]:
        return [r for r in self.rows if r.action != UP_TO_DATE]

    @property
    def work(self) -> list[PlanRow]:
        return [r for r in self.rows if r.action in WORK]

    @property
    def refused(self) -> list[PlanRow]:
        return [r for r in self.rows if r.action == REFUSED]

    @property
    def matches(self) -> bool:
        """Nothing to do: every (selected) board is up to date."""
        return all(r.action in (UP_TO_DATE, SKIPPED) for r in self.rows) and \
            any(r.action == UP_TO_DATE for r in self.rows)


def robot_for(robot: Robot, manifest: Manifest) -> Robot:
    """``robot`` with each bus expecting the manifest's boards; InputError for a bus of
    the manifest the connection does not have."""
    buses: dict[str, BusHandle] = {}
    for bus in manifest.topology.buses:
        if not any(w.bus == bus.name for w in manifest.boards):
            continue
        h = robot.buses.get(bus.name)
        if h is None:
            raise InputError(f"{manifest.topology.name} has boards on bus {bus.name}; the "
                             f"connection has {', '.join(robot.buses) or 'none'}", key="--bus")
        buses[bus.name] = replace(h, expected=bus)
    return replace(robot, buses=buses, topology=manifest.topology)


def plan(robot: Robot, manifest: Manifest, journal: Journal, *,
         only: set[str] | None = None) -> Plan:
    """Init every bus of the manifest, read each board's Info and compare it with its
    image (and with the journal of an unfinished deploy).  ``only``: keys ``BUS:n`` of
    the boards to deploy; the others are shown up to date or not, never changed."""
    part = robot_for(robot, manifest)

    def one(h: BusHandle) -> tuple[BusEnumeration, list[PlanRow]]:
        enum = enumerate_bus(h)
        return enum, _plan_bus(h, enum, manifest, journal)

    done = part.each(one)
    rows = [r for _, bus_rows in done for r in bus_rows]
    if only is not None:
        rows = [r if r.key in only or r.action == UP_TO_DATE else
                replace(r, action=SKIPPED, reason=f"not selected (else: {r.action}"
                        + (f", {r.reason})" if r.reason else ")")) for r in rows]
    return Plan(manifest, tuple(rows), tuple(e for e, _ in done), journal.resumed)


def _plan_bus(h: BusHandle, enum: BusEnumeration, manifest: Manifest,
              journal: Journal) -> list[PlanRow]:
    wanted = manifest.on(h.name)
    rows: dict[int, PlanRow] = {}
    faulty = any(b.duplicate for b in enum.boards) or any(
        d.kind == "fixed-id-clash" for d in enum.diagnosis)
    found = {b.position - 1: b for b in enum.boards if b.position is not None}
    expected = len(h.expected.boards) if h.expected is not None else 0
    missing = {s.position: s for s in
               missing_expected(h, [b.serial for b in enum.boards], enum.found)}
    for w in wanted:
        pos = w.spec.position
        base = PlanRow(h.name, 0, pos, w.spec.placement, None, w.image_path.name,
                       w.plan.progid, w.spec.autostart, None, REFUSED, "")
        b = found.get(pos)
        if b is None or pos in missing:
            rows[pos] = replace(base, reason="missing: " + describe_missing(h.name, w.spec,
                                                                             expected))
            continue
        base = replace(base, seq_id=b.seq_id, serial=b.serial)
        if faulty:
            why = "; ".join(d.message for d in enum.diagnosis)
            rows[pos] = replace(base, reason=f"the init chain is faulty ({why})")
            continue
        if b.info is None:
            rows[pos] = replace(base, reason="its Info record did not arrive")
            continue
        rows[pos] = _judge(base, w, b.info, journal.entry(base.key, b.serial))
    return [rows[w.spec.position] for w in wanted]


def _judge(base: PlanRow, w: Wanted, info: BoardInfo, entry: dict[str, Any] | None
           ) -> PlanRow:
    before = Seen.of(info)
    row = replace(base, before=before)
    findings = compare(w.image.descriptor, info)
    errors = [f for f in findings if f.severity == "error"]
    warnings = tuple(f.message for f in findings if f.severity != "error")
    if errors:
        why = "; ".join(f"{f.field}: expected {f.expected}, found {f.found}" for f in errors)
        return replace(row, reason=f"the image does not fit: {why}", warnings=warnings)
    row = replace(row, warnings=warnings)
    right = info.flash_valid and info.progid == w.plan.progid
    stage = entry.get("stage") if entry else None
    if not right:
        if stage in ("programming", "dumped", "failed", "verified", "restored"):
            why = "interrupted (the last deploy did not finish it"
            why += f"; {before.state}" + (f", ProgID 0x{info.progid:08X})"
                                         if info.flash_valid else ", no program)")
        elif not info.flash_valid:
            why = "no program"
        else:
            why = f"other ProgID 0x{info.progid:08X} ({info.name})"
        return replace(row, action=PROGRAM, reason=why)
    if entry and entry.get("params") and stage in ("dumped", "programming", "verified"):
        return replace(row, action=RESTORE, reason="interrupted after programming: its "
                       "saved parameters are still to be loaded back")
    if stage in ("programming", "verified"):
        return replace(row, action=START, reason="interrupted after programming: AutoStart "
                       "and its start are still to be done")
    if info.autostart != w.spec.autostart:
        return replace(row, action=START, reason="AutoStart is " + ("on" if info.autostart
                                                                      else "off"))
    if w.spec.autostart and info.state not in RUNNING:
        return replace(row, action=START, reason=f"not running ({info.state.text})")
    return replace(row, action=UP_TO_DATE, reason="")


# ----------------------------------------------------------------------------- execute
@dataclass(frozen=True)
class Params:
    """What became of one board's parameters."""

    outcome: str
    """kept (saved and loaded back, read back), none (nothing to keep: no tree, or no
    program ran), failed."""
    values: int = 0
    detail: str = ""


@dataclass(frozen=True)
class BoardDeploy:
    row: PlanRow
    outcome: str
    """up to date, done (it matches its manifest now), failed, refused, untouched."""
    detail: str = ""
    after: Seen | None = None
    params: Params = Params("none")

    @property
    def ok(self) -> bool:
        return self.outcome in (UP_TO_DATE, "done", SKIPPED)


@dataclass(frozen=True)
class DeployResult:
    plan: Plan
    boards: tuple[BoardDeploy, ...]
    journal: Path | None
    """Where the journal is left (None: removed, the robot matches its manifest)."""
    frames: int = 0
    interrupted: str = ""
    """The step (:data:`STEPS`) an interrupt found the deploy in ("": none)."""

    @property
    def ok(self) -> bool:
        return bool(self.boards) and all(b.ok for b in self.boards)

    @property
    def failed(self) -> list[BoardDeploy]:
        return [b for b in self.boards if not b.ok]


class DeployInterrupted(KeyboardInterrupt):
    """A deploy ended by an interrupt after it put its boards back; :attr:`result` says
    per board what it was left with (outcomes of :mod:`ucom_tools.ops.leave`, or up to
    date, refused, skipped).  Raised from the interrupt (``__cause__``: its signal)."""

    def __init__(self, result: DeployResult) -> None:
        super().__init__("deploy interrupted")
        self.result = result


def _trees_of(manifest: Manifest, keys: set[str]) -> RobotTrees | None:
    """The manifest's trees of the boards ``keys`` (None: none of them has a tree)."""
    if manifest.trees is None:
        return None
    chosen = tuple(b for b in manifest.trees.boards
                   if f"{b.bus}:{b.spec.position + 1}" in keys)
    return replace(manifest.trees, boards=chosen) if chosen else None


def _one_block(tree: attrtree.Tree, number: int) -> attrtree.Tree:
    return replace(tree, boards=tuple(b for b in tree.boards if b.number == number))


def _dump(part: Robot, manifest: Manifest, journal: Journal, rows: list[PlanRow],
          events: EventFn) -> dict[str, str]:
    """Record ``rows`` in the journal, with the parameters of the boards to program that
    run a program and have a tree (and none saved by an earlier, unfinished deploy);
    returns why a board's values could not be read (it is then not programmed)."""
    keys = {r.key for r in rows if r.action == PROGRAM and r.before is not None
            and r.before.state in (s.text for s in RUNNING)
            and not (journal.entry(r.key, r.serial) or {}).get("params")}
    trees = _trees_of(manifest, keys)
    failed: dict[str, str] = {}
    files: dict[str, str] = {}
    if trees is not None:
        events(f"reading the parameters of {len(trees.boards)} board(s)")
        readout = params_ops.read_values(part, trees, running_only=True)
        by_source = {t.source: t for t in trees.trees}
        for read in readout.boards:
            key = f"{read.bus}:{read.board}"
            if read.error:
                failed[key] = f"its parameters could not be read: {read.error}"
                continue
            if not read.ok:
                continue
            tree = _one_block(live_tree(by_source[str(read.tree)], [read]),
                              read.block)
            name = f"{PARAMS_DIR}/{safe_name(read.bus)}-{read.board}.tree"
            text = attrtree.dumps(tree)
            if attrtree.parse(text, name) != tree:  # never keep what does not read back
                failed[key] = "its dumped parameters do not read back as written"
                continue
            files[name] = text
            journal.update(key, params=name, prefix=read.prefix, values=len(read.values))
    for r in rows:
        if r.key not in failed:
            e = journal.entry(r.key, r.serial) or {}
            journal.update(r.key, serial=r.serial, placement=r.placement, image=r.image,
                           progid=f"0x{r.progid:08X}", action=r.action,
                           stage=e.get("stage") if e.get("stage") not in (None, "planned")
                           else "dumped")
    journal.save(files)
    return failed


def _program_bus(h: BusHandle, part: Robot, manifest: Manifest, journal: Journal,
                 rows: list[PlanRow], progress: ProgressFn | None,
                 cancel: threading.Event | None, events: EventFn) -> dict[str, str]:
    """Each image once to the boards of ``rows`` on bus ``h`` that need it; returns the
    outcome by key (verified, or why not)."""
    out: dict[str, str] = {}
    groups: dict[Path, list[PlanRow]] = {}
    for r in rows:
        w = manifest.board(r.bus, r.position)
        assert w is not None
        groups.setdefault(w.image_path, []).append(r)
    for path, group in groups.items():
        w = manifest.board(group[0].bus, group[0].position)
        assert w is not None
        numbers = tuple(r.seq_id for r in group)
        for r in group:
            journal.update(r.key, stage="programming")
        journal.save()
        events(f"{h.name}: programming {path.name} into "
               f"{', '.join(map(str, numbers))}")
        request = FlashRequest(w.image, selection=Selection("list", numbers), bus=h.name,
                               init=False, verify=True, plan=w.plan)
        result = flash(part, request, progress=progress, cancel=cancel)
        by_seq = {b.seq_id: b for b in result.boards}
        for r in group:
            b = by_seq.get(r.seq_id)
            if b is not None and b.verified:
                out[r.key] = "verified"
                journal.update(r.key, stage="verified")
            else:
                out[r.key] = b.detail if b is not None else "not programmed"
                journal.update(r.key, stage="failed")
        journal.save()
        ok = [r.seq_id for r in group if out[r.key] == "verified"]
        events(f"{h.name}: {path.name} verified on {', '.join(map(str, ok)) or 'no board'}")
    return out


def _restore(part: Robot, manifest: Manifest, journal: Journal, keys: list[str],
             events: EventFn) -> dict[str, Params]:
    """Load the saved parameters of the boards ``keys`` back (their programs started)."""
    out: dict[str, Params] = {}
    files = []
    prefixes = []
    for key in keys:
        e = journal.boards.get(key, {})
        if e.get("params"):
            files.append(journal.directory / e["params"])
            prefixes.append(e["prefix"])
    if not files or manifest.trees is None:
        return out
    events(f"loading the parameters of {len(files)} board(s) back")
    try:
        given = attrtree.with_files(manifest.trees, files, only=True)
    except InputError as err:
        return {k: Params("failed", 0, f"the saved parameters cannot be used: {err}")
                for k in keys if journal.boards.get(k, {}).get("params")}
    chosen = params_ops.select_prefixes(given, prefixes)
    result = params_ops.load_values(part, chosen, strict=False)
    for b in result.boards:
        key = f"{b.bus}:{b.board}"
        if b.ok:
            out[key] = Params("kept", b.written, f"{b.written} values loaded back and read "
                              "back")
            journal.update(key, stage="restored")
        else:
            why = b.error or ", ".join(f"{x.unique} reads {x.read}, not {x.sent}"
                                       for x in b.not_taken)
            out[key] = Params("failed", 0, f"not loaded back: {why}")
    journal.save()
    return out


def _finish_bus(h: BusHandle, manifest: Manifest, rows: list[PlanRow],
                cancel: threading.Event | None = None) -> dict[str, str]:
    """AutoStart as the manifest says, and a start, for the boards of ``rows``; returns
    why a board could not be (by key).  Cancelled: :class:`Cancelled` between boards."""
    out: dict[str, str] = {}
    if not rows:
        return out
    infos = h.client.info_many(ALL, expect=[seq(r.seq_id) for r in rows])
    for r in rows:
        if cancel is not None and cancel.is_set():
            raise Cancelled("cancelled")
        w = manifest.board(r.bus, r.position)
        assert w is not None
        n = r.seq_id
        info = infos.get(seq(n))
        try:
            if info is None or info.autostart != w.spec.autostart:
                ok = h.client.set_status(seq(n), StatusOp.AUTOSTART, int(w.spec.autostart))
                if not (ok and ok[0].ok):
                    out[r.key] = "AutoStart could not be set"
                    continue
            if info is None or info.state not in RUNNING:
                answers = h.client.start(seq(n))
                if not (answers and answers[0].ok):
                    texts = [e.describe() for a in answers for e in a.errors]
                    out[r.key] = "did not start" + (f": {'; '.join(texts)}" if texts else "")
        except UcomError as err:
            out[r.key] = str(err)
    return out


def _after(part: Robot, manifest: Manifest, rows: list[PlanRow]
           ) -> dict[str, BoardInfo]:
    """The Info of the boards of ``rows`` as the deploy leaves them."""
    def one(h: BusHandle) -> dict[str, BoardInfo]:
        mine = [r for r in rows if r.bus == h.name and r.seq_id]
        if not mine:
            return {}
        infos = h.client.info_many(ALL, expect=[seq(r.seq_id) for r in mine])
        return {r.key: infos[seq(r.seq_id)] for r in mine if seq(r.seq_id) in infos}

    out: dict[str, BoardInfo] = {}
    for part_out in part.each(one):
        out.update(part_out)
    return out


def matches(w: Wanted, info: BoardInfo) -> bool:
    """The board runs (or, without AutoStart, holds) its manifest's image, AutoStart as
    the manifest says."""
    return (info.flash_valid and info.progid == w.plan.progid
            and info.autostart == w.spec.autostart
            and (not w.spec.autostart or info.state in RUNNING))


def execute(robot: Robot, the_plan: Plan, journal: Journal, *,
            progress: ProgressFn | None = None, cancel: threading.Event | None = None,
            events: EventFn | None = None) -> DeployResult:
    """Carry ``the_plan`` out (see the module docstring); the journal records every step
    and is removed when every board of the manifest matches it.  Interrupted:
    :class:`DeployInterrupted` once the boards are put back."""
    say = events or (lambda _text: None)
    manifest = the_plan.manifest
    part = robot_for(robot, manifest)
    rows = list(the_plan.rows)
    work = [r for r in rows if r.action in WORK]
    cancel = cancel or threading.Event()
    step = [DUMPING]

    def check(next_step: str) -> None:
        if cancel.is_set():
            raise Cancelled("cancelled")
        step[0] = next_step

    try:
        return _execute(part, the_plan, journal, rows, work, progress, cancel, say, check)
    except (KeyboardInterrupt, Cancelled) as stop:
        result = _interrupted(part, the_plan, journal, rows, work, step[0])
        raise DeployInterrupted(result) from stop


def _execute(part: Robot, the_plan: Plan, journal: Journal, rows: list[PlanRow],
             work: list[PlanRow], progress: ProgressFn | None, cancel: threading.Event,
             say: EventFn, check: Callable[[str], None]) -> DeployResult:
    manifest = the_plan.manifest
    failed: dict[str, str] = {}
    params: dict[str, Params] = {}
    if work:
        to_program = [r for r in work if r.action == PROGRAM]
        failed.update(_dump(part, manifest, journal, work, say))
        to_program = [r for r in to_program if r.key not in failed]
        programmed: dict[str, str] = {}
        if to_program:
            buses = sorted({r.bus for r in to_program},
                           key=lambda b: list(part.buses).index(b))
            # another host programming: BusError, nothing programmed
            check(LISTENING)
            listen_first(replace(part, buses={n: part.buses[n] for n in buses}))
            check(PROGRAMMING)
            for outcome in part.each(lambda h: _program_bus(
                    h, part, manifest, journal, [r for r in to_program if r.bus == h.name],
                    progress, cancel, say) if h.name in buses else {}, cancel=cancel):
                programmed.update(outcome)
        for k, v in programmed.items():
            if v != "verified":
                failed[k] = f"not verified: {v}"
        ready = [r for r in work if r.key not in failed]
        check(RESTORING)
        params = _restore(part, manifest, journal, [r.key for r in ready], say)
        for k, p in params.items():
            if p.outcome == "failed":
                failed[k] = f"parameters {p.detail}"
        ready = [r for r in ready if r.key not in failed]
        check(FINISHING)
        say("setting AutoStart and starting the programs")
        for outcome in part.each(lambda h: _finish_bus(
                h, manifest, [r for r in ready if r.bus == h.name], cancel), cancel=cancel):
            failed.update(outcome)
        check(CHECKING)
    after = _after(part, manifest, work) if work else {}
    boards = []
    for r in rows:
        w = manifest.board(r.bus, r.position)
        assert w is not None
        p = params.get(r.key, Params("none"))
        if r.action == UP_TO_DATE:
            boards.append(BoardDeploy(r, UP_TO_DATE, "", r.before, p))
            continue
        if r.action in (REFUSED, SKIPPED):
            boards.append(BoardDeploy(r, r.action, r.reason, r.before, p))
            continue
        info = after.get(r.key)
        seen = Seen.of(info) if info is not None else None
        if r.key in failed:
            boards.append(BoardDeploy(r, "failed", failed[r.key], seen, p))
        elif info is None or not matches(w, info):
            boards.append(BoardDeploy(r, "failed", "does not match its manifest afterwards"
                                      + (f" ({seen.state})" if seen else " (no Info)"), seen, p))
        else:
            boards.append(BoardDeploy(r, "done", "", seen, p))
            journal.update(r.key, stage="done")
    skipped = {b.row.key for b in boards if b.outcome == SKIPPED}
    left: Path | None = journal.directory
    if all(b.ok for b in boards) and not skipped & set(journal.boards):
        journal.remove()  # the robot (the selected part of it) matches its manifest
        left = None
    elif work:
        journal.save()
    elif not journal.boards:
        left = None
    return DeployResult(the_plan, tuple(boards), left)


def _interrupted(part: Robot, the_plan: Plan, journal: Journal, rows: list[PlanRow],
                 work: list[PlanRow], step: str) -> DeployResult:
    """After an interrupt in ``step``: on every bus, no board the deploy works on left
    ProgEnabled or in a transfer (:func:`~ucom_tools.ops.leave.put_back`), and per board
    what it was left with; the journal is kept (the next deploy finishes the work)."""
    def one(h: BusHandle) -> tuple[dict[int, BoardInfo], list[str]]:
        mine = [r.seq_id for r in work if r.bus == h.name and r.seq_id]
        if not mine:
            return {}, []
        # a board still ProgEnabled or in a transfer (its flash put back what it began;
        # one whose transfer failed before the interrupt) is cleared by what its Info says
        return leave.put_back(h, abort=step == PROGRAMMING, enabled=[], ask=mine)

    done = part.each(one)
    handles = part.select(None)
    infos = {h.name: got for h, (got, _) in zip(handles, done, strict=True)}
    notes = {h.name: bus_notes for h, (_, bus_notes) in zip(handles, done, strict=True)}
    boards = []
    for r in rows:
        if r.action not in WORK:
            boards.append(BoardDeploy(r, r.action, r.reason if r.action != UP_TO_DATE
                                      else "", r.before))
            continue
        entry = journal.entry(r.key, r.serial) or {}
        stage = entry.get("stage")
        info = infos.get(r.bus, {}).get(r.seq_id)
        left = leave.judge(info, old_progid=r.before.progid if r.before else None,
                           new_progid=r.progid,
                           verified=stage in ("verified", "restored", "done"))
        detail = left.detail
        if left.outcome == leave.KEPT and r.action == PROGRAM and step in (LISTENING,
                                                                           DUMPING):
            detail += f" (interrupted while {step}, before its programming)"
        if entry.get("params") and stage != "restored" and left.outcome != leave.UNREACHABLE:
            detail += ("; its saved parameters are in the journal, to be loaded back by the "
                       "next deploy")
        detail = "; ".join([detail, *notes.get(r.bus, [])])
        boards.append(BoardDeploy(r, left.outcome, detail,
                                  Seen.of(left.info) if left.info is not None else None))
    if journal.boards:
        journal.save()
    return DeployResult(the_plan, tuple(boards), journal.directory if journal.boards else None,
                        interrupted=step)


__all__ = ["PROGRAM", "REFUSED", "RESTORE", "SKIPPED", "START", "STEPS", "UP_TO_DATE", "WORK",
           "BoardDeploy", "DeployInterrupted", "DeployResult", "Journal", "Manifest", "Plan",
           "PlanRow", "Seen", "Wanted", "default_journal", "execute", "image_problems",
           "load_manifest", "plan"]
