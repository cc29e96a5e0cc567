"""Carrying a deploy's plan out (:func:`execute`; the plan and the results are
:mod:`ucom_tools.ops.deploy`'s).

Each step on every bus in parallel: the parameters of the boards to program that run a
program are dumped into the journal (:func:`_dump`); each image is sent once per bus to
the boards that need it (:func:`_program_bus`, a :func:`~ucom_tools.ops.flash.flash`
per image); the saved parameters are loaded back (:func:`_restore`); AutoStart is set as
the manifest says and the programs are started (:func:`_finish_bus`); every board's Info
is read to say how it ended.  Interrupted, :func:`_interrupted` puts the boards back and
says what each was left with.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from ucom_tools.config import attrtree
from ucom_tools.config.attrtree import RobotTrees
from ucom_tools.errors import InputError, UcomError
from ucom_tools.ops import leave
from ucom_tools.ops import params as params_ops
from ucom_tools.ops.deploy import (
    CHECKING,
    DUMPING,
    FINISHING,
    LISTENING,
    PROGRAM,
    PROGRAMMING,
    REFUSED,
    RESTORING,
    RUNNING,
    SKIPPED,
    UP_TO_DATE,
    WORK,
    BoardDeploy,
    DeployInterrupted,
    DeployRequest,
    DeployResult,
    EventFn,
    Params,
    Plan,
    PlanRow,
    Seen,
    robot_for,
)
from ucom_tools.ops.flash import flash, listen_first
from ucom_tools.ops.flash_types import FlashRequest, ProgressFn, Selection
from ucom_tools.ops.journal import PARAMS_DIR, Journal, safe_name
from ucom_tools.ops.manifest import Manifest, Wanted
from ucom_tools.ops.params_dump import live_tree
from ucom_tools.ops.robot import BusHandle, Robot
from ucom_tools.protocol.programmer import Cancelled
from ucom_tools.wire.codes import StatusOp
from ucom_tools.wire.ids import ALL, seq
from ucom_tools.wire.info import BoardInfo


@dataclass(frozen=True)
class _Run:
    """One execution of a plan: the robot it works on (the buses its manifest names),
    where it records, how it is told to stop and what it tells."""

    selected: Robot
    plan: Plan
    journal: Journal
    progress: ProgressFn | None
    cancel: threading.Event
    say: EventFn

    @property
    def manifest(self) -> Manifest:
        return self.plan.manifest


def _trees_of(manifest: Manifest, keys: set[str]) -> RobotTrees | None:
    """The manifest's trees of the boards ``keys`` (None: none of them has a tree)."""
    if manifest.trees is None:
        return None
    chosen = tuple(b for b in manifest.trees.boards
                   if f"{b.bus}:{b.spec.position + 1}" in keys)
    return replace(manifest.trees, boards=chosen) if chosen else None


def _one_block(tree: attrtree.Tree, number: int) -> attrtree.Tree:
    return replace(tree, boards=tuple(b for b in tree.boards if b.number == number))


def _dump(selected: Robot, manifest: Manifest, journal: Journal, rows: list[PlanRow],
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
        readout = params_ops.read_values(selected, trees, running_only=True)
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


def _program_bus(h: BusHandle, run: _Run, rows: list[PlanRow]) -> dict[str, str]:
    """Each image once to the boards of ``rows`` on bus ``h`` that need it; returns the
    outcome by key (verified, or why not)."""
    manifest, journal, events = run.manifest, run.journal, run.say
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
        result = flash(run.selected, request, progress=run.progress, cancel=run.cancel)
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


def _restore(selected: Robot, manifest: Manifest, journal: Journal, keys: list[str],
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
    result = params_ops.load_values(selected, chosen, strict=False)
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


def _after(selected: Robot, manifest: Manifest, rows: list[PlanRow]
           ) -> dict[str, BoardInfo]:
    """The Info of the boards of ``rows`` as the deploy leaves them."""
    def one(h: BusHandle) -> dict[str, BoardInfo]:
        mine = [r for r in rows if r.bus == h.name and r.seq_id]
        if not mine:
            return {}
        infos = h.client.info_many(ALL, expect=[seq(r.seq_id) for r in mine])
        return {r.key: infos[seq(r.seq_id)] for r in mine if seq(r.seq_id) in infos}

    out: dict[str, BoardInfo] = {}
    for outcome_of in selected.each(one):
        out.update(outcome_of)
    return out


def matches(w: Wanted, info: BoardInfo) -> bool:
    """The board runs (or, without AutoStart, holds) its manifest's image, AutoStart as
    the manifest says."""
    return (info.flash_valid and info.progid == w.plan.progid
            and info.autostart == w.spec.autostart
            and (not w.spec.autostart or info.state in RUNNING))


def execute(robot: Robot, request: DeployRequest, the_plan: Plan, *,
            progress: ProgressFn | None = None, cancel: threading.Event | None = None,
            events: EventFn | None = None) -> DeployResult:
    """Carry ``the_plan`` of ``request`` out (see the module docstring); the journal
    records every step and is removed when every board of the manifest matches it.
    Interrupted: :class:`DeployInterrupted` once the boards are put back."""
    run = _Run(robot_for(robot, the_plan.manifest), the_plan, request.journal, progress,
               cancel or threading.Event(), events or (lambda _text: None))
    rows = list(the_plan.rows)
    work = [r for r in rows if r.action in WORK]
    step = [DUMPING]

    def check(next_step: str) -> None:
        if run.cancel.is_set():
            raise Cancelled("cancelled")
        step[0] = next_step

    try:
        failed, params = _work(run, work, check) if work else ({}, {})
        return _outcome(run, rows, work, failed, params)
    except (KeyboardInterrupt, Cancelled) as stop:
        result = _interrupted(run, rows, work, step[0])
        raise DeployInterrupted(result) from stop


def _work(run: _Run, work: list[PlanRow], check: Callable[[str], None]
          ) -> tuple[dict[str, str], dict[str, Params]]:
    """The steps that change boards, for the rows that need work: why each board that
    failed did, and what became of the parameters of each."""
    selected, manifest, journal, say = run.selected, run.manifest, run.journal, run.say
    failed: dict[str, str] = {}
    to_program = [r for r in work if r.action == PROGRAM]
    failed.update(_dump(selected, manifest, journal, work, say))
    to_program = [r for r in to_program if r.key not in failed]
    programmed: dict[str, str] = {}
    if to_program:
        buses = sorted({r.bus for r in to_program}, key=lambda b: list(selected.buses).index(b))
        # another host programming: BusError, nothing programmed
        check(LISTENING)
        listen_first(replace(selected, buses={n: selected.buses[n] for n in buses}))
        check(PROGRAMMING)
        for outcome in selected.each(lambda h: _program_bus(
                h, run, [r for r in to_program if r.bus == h.name])
                if h.name in buses else {}, cancel=run.cancel):
            programmed.update(outcome)
    for k, v in programmed.items():
        if v != "verified":
            failed[k] = f"not verified: {v}"
    ready = [r for r in work if r.key not in failed]
    check(RESTORING)
    params = _restore(selected, manifest, journal, [r.key for r in ready], say)
    for k, p in params.items():
        if p.outcome == "failed":
            failed[k] = f"parameters {p.detail}"
    ready = [r for r in ready if r.key not in failed]
    check(FINISHING)
    say("setting AutoStart and starting the programs")
    for outcome in selected.each(lambda h: _finish_bus(
            h, manifest, [r for r in ready if r.bus == h.name], run.cancel), cancel=run.cancel):
        failed.update(outcome)
    check(CHECKING)
    return failed, params


def _outcome(run: _Run, rows: list[PlanRow], work: list[PlanRow], failed: dict[str, str],
             params: dict[str, Params]) -> DeployResult:
    """How every board ended (its Info read again), the journal removed when the robot
    matches its manifest."""
    manifest, journal = run.manifest, run.journal
    after = _after(run.selected, manifest, work) if work else {}
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
        journal.remove()  # the robot (the buses selected) matches its manifest
        left = None
    elif work:
        journal.save()
    elif not journal.boards:
        left = None
    return DeployResult(run.plan, tuple(boards), left)


def _interrupted(run: _Run, rows: list[PlanRow], work: list[PlanRow], step: str
                 ) -> DeployResult:
    """After an interrupt in ``step``: on every bus, no board the deploy works on left
    ProgEnabled or in a transfer (:func:`~ucom_tools.ops.leave.put_back`), and per board
    what it was left with; the journal is kept (the next deploy finishes the work)."""
    selected, journal = run.selected, run.journal

    def one(h: BusHandle) -> tuple[dict[int, BoardInfo], list[str]]:
        mine = [r.seq_id for r in work if r.bus == h.name and r.seq_id]
        if not mine:
            return {}, []
        # a board still ProgEnabled or in a transfer (its flash put back what it began;
        # one whose transfer failed before the interrupt) is cleared by what its Info says
        return leave.put_back(h, abort=step == PROGRAMMING, enabled=[], ask=mine)

    done = selected.each(one)
    handles = selected.select(None)
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
    return DeployResult(run.plan, tuple(boards), journal.directory if journal.boards else None,
                        interrupted=step)
