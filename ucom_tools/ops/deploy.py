"""Bringing a robot to its manifest: ``ucom deploy``.

The manifest is the robot's topology: per board the image it should run (``image =``)
and whether it starts by itself (``autostart =``), and its attribute tree.  A deploy

1. plans (:func:`plan`): every bus's init chain and every board's Info (with its FPGA
   registers), compared with its image: *up to date*, *program* (another ProgID, no
   program, interrupted by an earlier deploy), *restore* (the right program, but the
   parameters an interrupted deploy saved are still to be loaded back), *start* (the
   right program, only its AutoStart flag or its start missing), or *refused* (the image
   does not fit the board, the board is missing, the chain is faulty);
2. executes (:func:`~ucom_tools.ops.deploy_execute.execute`), each phase on every bus
   in parallel: the parameters of the boards to program that run a program are dumped
   into the journal; each image is sent once per bus to the boards that need it (one
   broadcast per image; KAIRO-II has two on its bus), verified and read back; the saved
   parameters are loaded back; AutoStart is set as the manifest says and the programs
   are started.

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

This module plans (:func:`plan`, :class:`DeployRequest`) and holds what a deploy says
(:class:`DeployResult`); :mod:`ucom_tools.ops.deploy_execute` carries a plan out.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import KW_ONLY, dataclass, replace
from pathlib import Path
from typing import Any

from ucom_tools.errors import InputError
from ucom_tools.ops.compat import compare
from ucom_tools.ops.enumerate import (
    BusEnumeration,
    describe_missing,
    enumerate_bus,
    missing_expected,
)
from ucom_tools.ops.journal import (
    Journal,
    default_journal,
)
from ucom_tools.ops.manifest import Manifest, Wanted, image_problems, load_manifest
from ucom_tools.ops.robot import BusHandle, Robot
from ucom_tools.wire.codes import BoardState
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
class DeployRequest:
    """A deploy to do: bring the boards of ``manifest`` to it, recording the work in
    ``journal`` (an unfinished deploy's is resumed); ``only``: keys ``BUS:n`` of the
    boards to deploy (None: every board of the manifest)."""

    manifest: Manifest
    journal: Journal
    _: KW_ONLY
    only: frozenset[str] | None = None


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
                             f"connection has {', '.join(robot.buses) or 'none'}", key="bus")
        buses[bus.name] = replace(h, expected=bus)
    return replace(robot, buses=buses, topology=manifest.topology)


def plan(robot: Robot, request: DeployRequest) -> Plan:
    """Init every bus of the manifest, read each board's Info and compare it with its
    image (and with the journal of an unfinished deploy); the boards not in
    ``request.only`` are shown up to date or not, never changed."""
    manifest, journal, only = request.manifest, request.journal, request.only
    selected = robot_for(robot, manifest)

    def one(h: BusHandle) -> tuple[BusEnumeration, list[PlanRow]]:
        enum = enumerate_bus(h)
        return enum, _plan_bus(h, enum, manifest, journal)

    done = selected.each(one)
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


__all__ = ["PROGRAM", "REFUSED", "RESTORE", "SKIPPED", "START", "STEPS", "UP_TO_DATE", "WORK",
           "BoardDeploy", "DeployInterrupted", "DeployRequest", "DeployResult", "Journal",
           "Manifest", "Plan", "PlanRow", "Seen", "Wanted", "default_journal",
           "image_problems", "load_manifest", "plan"]
