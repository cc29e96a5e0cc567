"""Running the conformance cases: every selected case on every bus, the boards reset
between cases and left as found at the end, whatever ends the suite; a trace per case.

As found: before the first case, each board's Info (program in flash, ProgID, AutoStart),
whether it ran a program and its program's parameters are noted
(:mod:`ucom_tools.conformance.restore`).  Before each case every board is brought to its
bootloader with XReset (a plain reset would start an AutoStart program again); cases
restore what they change themselves, programs under test run from external RAM (a
reset ends them; flash is written only to give AutoStart a program where no board had
one, and made invalid again); at the end the AutoStart flags are set again, the programs
that ran are started again and their parameters written back.  What is then not as it
was is named (``not_restored``).

The restore runs on every way out of a bus's cases: their end, an interrupt (Ctrl-C,
SIGTERM, SIGHUP: :class:`KeyboardInterrupt`), a trace that cannot be written, a lost
connection (opened again when the bus comes back within :data:`RECONNECT_S`), an error of
the suite itself.  Further signals wait until it is done (:mod:`.shield`); the suite then
stops, and the result says why (``stopped``).
"""

from __future__ import annotations

import contextlib
import fnmatch
import os
import signal
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import can

from ucom_tools import fileio
from ucom_tools.conformance.bench import RUNTIME_IMAGE, Bench
from ucom_tools.conformance.case import Case
from ucom_tools.conformance.catalogue import all_cases
from ucom_tools.conformance.outcome import CaseFailed, Skipped
from ucom_tools.conformance.restore import (
    RECONNECT_S,
    Found,
    note_found,
    reopen,
    restore,
    unrestored,
)
from ucom_tools.conformance.shield import Shield
from ucom_tools.errors import BusError, InputError, UcomError, WriteError
from ucom_tools.ops.robot import Robot
from ucom_tools.signals import Terminated

Words = Callable[[BaseException], str]
"""How an error is worded for whoever reads it (``str``, or the command line's words)."""

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
class SuiteResult:
    outcomes: list[Outcome] = field(default_factory=list)
    found: list[Found] = field(default_factory=list)
    not_restored: list[str] = field(default_factory=list)
    """What could not be restored, one line per board (``CAN0:2: AutoStart not set``)."""
    bus_failure: str | None = None
    stopped: BaseException | None = None
    """What ended the suite before its end, after the restore: an interrupt
    (:class:`KeyboardInterrupt`; :class:`~ucom_tools.signals.Terminated` for SIGTERM and
    SIGHUP) or a trace that could not be written (a :class:`UcomError`)."""

    @property
    def failed(self) -> list[Outcome]:
        return [o for o in self.outcomes if o.status in ("failed", "error")]

    @property
    def ok(self) -> bool:
        return not self.failed and self.bus_failure is None and self.stopped is None

    @property
    def stop_text(self) -> str | None:
        """Why the suite stopped early, in words (None: it did not); an error's own
        text, which names its input as the API does (see :func:`describe_stop`)."""
        return self.describe_stop()

    def describe_stop(self, words: Words = str) -> str | None:
        """Why the suite stopped early with each error worded by ``words`` (None: it did
        not)."""
        return None if self.stopped is None else describe_stop(self.stopped, words)

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
        raise InputError(f"no case matches {pattern!r}", key="pattern")
    return chosen


def render(frames: Sequence[can.Message]) -> str:
    """The frames, decoded (the trace decoder when it is there, else plain)."""
    frames = list(frames)[-RENDER_FRAMES:]
    try:
        from ucom_tools.trace.decode import decode_frames
        return str(decode_frames(frames).render())
    except Exception:  # the decoder is optional here: plain lines do too
        return "\n".join(f"{f.timestamp:.6f} {'rx' if f.is_rx else 'tx'} "
                         f"{f.arbitration_id:03X} [{len(f.data)}] {bytes(f.data).hex(' ')}"
                         for f in frames)


def describe_stop(stop: BaseException, words: Words = str) -> str:
    """``interrupted (SIGINT)``, ``terminated (SIGTERM)``, ``cannot write: ...``, or the
    error's text; ``words`` words an error (its ``str()``, naming its input as the API
    does, unless the caller words it otherwise, as the command line does its options)."""
    if isinstance(stop, Terminated):
        return f"terminated ({stop.name})"
    if isinstance(stop, KeyboardInterrupt):
        return "interrupted (SIGINT)"
    if isinstance(stop, WriteError):
        return f"cannot write: {words(stop)}"
    return words(stop)


class _NotWritten(Exception):
    """A trace could not be written; ``error`` says so for the user."""

    def __init__(self, error: UcomError) -> None:
        super().__init__(str(error))
        self.error = error


def run_suite(robot: Robot, cases: Sequence[Case], *, trace_dir: Path | None = None,
              runtime_image: Path = RUNTIME_IMAGE,
              progress: Callable[[Outcome], None] | None = None,
              buses: Sequence[str] | None = None,
              notice: Callable[[str], None] | None = None,
              reconnect_s: float = RECONNECT_S) -> SuiteResult:
    """Every case on every bus of ``robot`` (or of ``buses``), the boards restored on
    every way out (module docstring).  ``notice`` hears, in words, that the suite stops
    and restores the boards, and of every signal that waits for the restore."""
    result = SuiteResult()

    def deferred(signum: int) -> None:
        _tell(notice, f"{signal.Signals(signum).name}: restoring the boards first")

    with Shield(deferred) as shield:
        for name in list(robot.buses):
            if buses is not None and name not in buses:
                continue
            result.stopped = shield.take()  # a signal between two buses
            if result.stopped is not None:
                break
            _run_bus(robot, name, cases, result, shield, trace_dir=trace_dir,
                     runtime_image=runtime_image, progress=progress, notice=notice,
                     reconnect_s=reconnect_s)
            if result.stopped is None:
                result.stopped = shield.take()  # a signal during the restore
            if result.stopped is not None or result.bus_failure is not None:
                break
    return result


def _run_bus(robot: Robot, name: str, cases: Sequence[Case], result: SuiteResult,
             shield: Shield, *, trace_dir: Path | None, runtime_image: Path,
             progress: Callable[[Outcome], None] | None,
             notice: Callable[[str], None] | None, reconnect_s: float) -> None:
    """The cases on one bus, then the restore (whatever ended the cases)."""
    bench = Bench(robot.buses[name], robot.timeouts, runtime_image)
    found: list[Found] = []
    why = ""
    try:
        with shield.raising():
            bench.init()  # as found: no reset yet (it would end running programs)
            try:
                found = note_found(bench)
            except BusError:
                raise
            except (UcomError, CaseFailed, Skipped) as err:
                result.not_restored.append(f"{bench.name}: the boards could not be read "
                                           f"as found ({err}); nothing restored")
            result.found += found
            for c in cases:
                outcome = _run_case(bench, c)
                result.outcomes.append(outcome)
                if trace_dir is not None:
                    outcome.trace = _trace(trace_dir, bench.name, c.id, bench.frames)
                if progress is not None:
                    progress(outcome)
    except KeyboardInterrupt as stop:
        result.stopped, why = stop, describe_stop(stop)
    except _NotWritten as err:
        result.stopped, why = err.error, "a trace could not be written"
    except BusError as err:
        result.bus_failure, why = str(err), "the bus failed"
    finally:
        try:
            if bench.touched:
                if why:
                    _tell(notice, f"{why}: restoring the boards of {bench.name}")
                bench = _restore(robot, bench, found, result, reconnect_s)
        finally:
            bench.close()


def _tell(notice: Callable[[str], None] | None, text: str) -> None:
    """Tell ``notice`` (a failing one must not keep the boards from being restored)."""
    if notice is not None:
        with contextlib.suppress(Exception):
            notice(text)


def _restore(robot: Robot, bench: Bench, found: list[Found], result: SuiteResult,
             reconnect_s: float) -> Bench:
    """Restore the boards of ``bench``'s bus; a bus that fails is opened again when it
    comes back within ``reconnect_s`` seconds.  The bench it ended on."""
    for attempt in range(2):
        try:
            result.not_restored += restore(bench, found)
            return bench
        except BusError as err:
            lost = str(err)
        except (UcomError, CaseFailed, Skipped) as err:  # the bus is there, the boards not
            result.not_restored += unrestored(found, f"restoring failed: {err}")
            return bench
        if attempt:
            break
        handle = reopen(robot, bench.name, reconnect_s)
        if handle is None:
            result.not_restored += unrestored(
                found, f"{lost}; the bus did not come back within {reconnect_s:g} s")
            return bench
        bench.close()
        bench = Bench(handle, robot.timeouts, bench.runtime_image)
    result.not_restored += unrestored(found, lost)
    return bench


def _run_case(bench: Bench, c: Case) -> Outcome:
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
    return outcome


def _trace(trace_dir: Path, bus: str, case_id: str, frames: list[can.Message]) -> str:
    """Write the case's trace; :class:`_NotWritten` (the suite stops) when it cannot be."""
    try:
        return _write_trace(trace_dir, bus, case_id, frames)
    except UcomError as err:
        raise _NotWritten(err) from err
    except OSError as err:
        where = os.fspath(err.filename) if err.filename else str(trace_dir / bus)
        why = "not a directory" if isinstance(err, FileExistsError | NotADirectoryError) \
            else err.strerror or str(err)
        raise _NotWritten(WriteError(f"{where}: {why}", path=where, key="trace_dir")) from err


def _write_trace(trace_dir: Path, bus: str, case_id: str, frames: list[can.Message]) -> str:
    """One case's frames as ``DIR/BUS/CASE.log``, written by the rules of ``ucom(1)``,
    FILES (atomically: a full disk leaves no partial trace)."""
    try:  # once the suite runs, an output that cannot be written is a write error
        directory = fileio.prepare_directory(trace_dir / bus)
    except InputError as err:
        raise WriteError(err.reason.removesuffix("; nothing was written"),
                         path=str(trace_dir / bus), key="trace_dir") from None
    path = directory / f"{case_id}.log"
    with fileio.Output(path, key="trace_dir", suffix=".log") as out:
        log = can.Logger(out.write_path)
        try:
            for f in frames:
                log.on_message_received(f)
        finally:
            log.stop()
    return str(path)
