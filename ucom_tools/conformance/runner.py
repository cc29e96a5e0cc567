"""Running the conformance cases: every selected case on every bus, the boards reset
between cases and left as found at the end; a trace per case.

As found: before the first case, each board's Info (program in flash, ProgID, AutoStart)
and whether it ran a program is noted.  Before each case every board is brought to its
bootloader with XReset (a plain reset would start an AutoStart program again); cases
restore what they change themselves, programs under test run from external RAM (a
reset ends them; flash is written only to give AutoStart a program where no board had
one, and made invalid again); at the end the AutoStart flags are set again and the
programs that ran are started again.  What is then not as it was is reported
(``left_as_found`` false).
"""

from __future__ import annotations

import fnmatch
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import can

from ucom_tools.conformance.bench import RUNTIME_IMAGE, Bench
from ucom_tools.conformance.case import Case
from ucom_tools.conformance.catalogue import all_cases
from ucom_tools.conformance.outcome import CaseFailed, Skipped
from ucom_tools.errors import BusError, InputError, UcomError
from ucom_tools.ops.robot import Robot
from ucom_tools.wire.codes import BoardState, StatusOp
from ucom_tools.wire.ids import seq

RENDER_FRAMES = 40
"""A failure shows the last frames of its case, decoded."""


@dataclass
class Outcome:
    case: Case
    bus: str
    status: str
    """passed, failed, skipped or error (the case itself broke: a bus failure)."""
    message: str = ""
    frames: str = ""
    """The case's frames, decoded (failures only)."""
    seconds: float = 0.0
    trace: str | None = None


@dataclass
class Found:
    """A board as the suite found it."""

    bus: str
    board: int
    serial: int
    flash_valid: bool
    progid: int | None
    autostart: bool
    running: bool


@dataclass
class SuiteResult:
    outcomes: list[Outcome] = field(default_factory=list)
    found: list[Found] = field(default_factory=list)
    not_restored: list[str] = field(default_factory=list)
    bus_failure: str | None = None

    @property
    def failed(self) -> list[Outcome]:
        return [o for o in self.outcomes if o.status in ("failed", "error")]

    @property
    def ok(self) -> bool:
        return not self.failed and self.bus_failure is None

    def counts(self) -> dict[str, int]:
        out = {"passed": 0, "failed": 0, "skipped": 0, "error": 0}
        for o in self.outcomes:
            out[o.status] += 1
        return out


def select(pattern: str | None) -> list[Case]:
    """The cases whose id (or group) matches the glob ``pattern`` (all when None);
    InputError when none does."""
    cases = all_cases()
    if not pattern:
        return cases
    chosen = [c for c in cases if fnmatch.fnmatch(c.id, pattern) or
              fnmatch.fnmatch(c.group, pattern) or pattern in c.id]
    if not chosen:
        raise InputError(f"no case matches {pattern!r} (see --list)", key="--only")
    return chosen


def render(frames: Sequence[can.Message]) -> str:
    """The frames, decoded (the trace decoder when it is there, else plain)."""
    frames = list(frames)[-RENDER_FRAMES:]
    try:
        from ucom_tools.ops.decode import decode_frames
        return str(decode_frames(frames).render())
    except Exception:  # the decoder is optional here: plain lines do too
        return "\n".join(f"{f.timestamp:.6f} {'rx' if f.is_rx else 'tx'} "
                         f"{f.arbitration_id:03X} [{len(f.data)}] {bytes(f.data).hex(' ')}"
                         for f in frames)


def _found(bench: Bench) -> list[Found]:
    out = []
    for n in bench.boards():
        if not 1 <= n <= 31:
            raise UcomError(f"a board answered the init chain as number {n}")
        info = bench.boot.info(seq(n))
        out.append(Found(bench.name, n, info.serial, info.flash_valid, info.progid,
                         info.autostart, info.state in (BoardState.RUNNING_FLASH,
                                                        BoardState.RUNNING_EXTRAM)))
    return out


def _restore(bench: Bench, found: list[Found]) -> list[str]:
    """Reset, number, start the programs that ran; what is not as found."""
    problems = []
    bench.reset_all()
    bench.init()
    for f in found:
        where = f"{f.bus} board {f.board}"
        if f.board not in bench.numbers:
            problems.append(f"{where}: did not answer at the end")
            continue
        if f.autostart and f.flash_valid:
            bench.boot.set_status(seq(f.board), StatusOp.AUTOSTART, 1)
        if f.running and f.flash_valid:
            started = bench.boot.start(seq(f.board))
            if not started or not started[0].started:
                problems.append(f"{where}: its program did not start again")
        info = bench.boot.info(seq(f.board))
        now = (info.flash_valid, info.progid if info.flash_valid else None, info.autostart)
        then = (f.flash_valid, f.progid if f.flash_valid else None, f.autostart)
        if now != then:
            problems.append(f"{where}: flash valid/ProgID/AutoStart {then} became {now}")
    return problems


def run_suite(robot: Robot, cases: Sequence[Case], *, trace_dir: Path | None = None,
              runtime_image: Path = RUNTIME_IMAGE,
              progress: Callable[[Outcome], None] | None = None,
              buses: Sequence[str] | None = None) -> SuiteResult:
    """Every case on every bus of ``robot`` (or of ``buses``)."""
    result = SuiteResult()
    try:
        for handle in robot.buses.values():
            if buses is not None and handle.name not in buses:
                continue
            bench = Bench(handle, robot.timeouts, runtime_image)
            try:
                bench.init()  # as found: no reset yet (it would end running programs)
                try:
                    found = _found(bench)
                except (UcomError, CaseFailed, Skipped) as err:
                    found = []
                    result.not_restored.append(f"{bench.name}: the boards could not be "
                                               f"read as found ({err}); nothing restored")
                result.found += found
                for c in cases:
                    outcome = _run_case(bench, c, trace_dir)
                    result.outcomes.append(outcome)
                    if progress is not None:
                        progress(outcome)
                try:
                    result.not_restored += _restore(bench, found)
                except (UcomError, CaseFailed, Skipped) as err:
                    result.not_restored.append(f"{bench.name}: restoring failed: {err}")
            finally:
                bench.close()
    except BusError as err:
        result.bus_failure = str(err)
    return result


def _run_case(bench: Bench, c: Case, trace_dir: Path | None) -> Outcome:
    bench.reset_all()
    bench.frames.clear()
    start = time.perf_counter()
    outcome = Outcome(c, bench.name, "passed")
    try:
        c.run(bench)
    except CaseFailed as err:
        outcome.status, outcome.message = "failed", str(err)
    except Skipped as err:
        outcome.status, outcome.message = "skipped", str(err)
    except BusError:
        raise
    except UcomError as err:  # a board that does not answer a case's request
        outcome.status, outcome.message = "failed", f"{type(err).__name__}: {err}"
    outcome.seconds = time.perf_counter() - start
    if outcome.status == "failed":
        outcome.frames = render(bench.frames)
    if trace_dir is not None:
        outcome.trace = _write_trace(trace_dir, bench.name, c.id, bench.frames)
    return outcome


def _write_trace(trace_dir: Path, bus: str, case_id: str, frames: list[can.Message]) -> str:
    path = trace_dir / bus / f"{case_id}.log"
    path.parent.mkdir(parents=True, exist_ok=True)
    with can.Logger(str(path)) as log:
        for f in frames:
            log.on_message_received(f)
    return str(path)
