"""Running a flash or deploy for people: progress per bus on a terminal, and Ctrl-C,
SIGTERM or SIGHUP stop it cleanly at any step.

The job runs in a worker thread of its own (:func:`run_cancellable`), started with the
stop signals blocked, so that they come to the main thread only, which does nothing but
wait: there a signal sets the job's cancel event and waits for the job to put its boards
back and say what it left (:class:`~ucom_tools.ops.flash.FlashInterrupted`, raised here
from the signal, so that the exit code is the signal's).  The worker never sees the
signal's exception itself: it could come in the middle of a frame written to a network
bus.  A second signal while the job puts its boards back is noted (pressing Ctrl-C twice
is a habit) and a third ends the wait at once (:class:`Abandoned`; the worker is a
daemon: a job stuck in its undo can still be ended).

Shared by ``ucom flash``/``program``/``extram-load``, the console's options 5, 6, 20 and
``ucom deploy``.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from dataclasses import replace
from typing import Any, TypeVar

from ucom_tools.cli.output import stderr
from ucom_tools.image.model import Image
from ucom_tools.ops.flash import flash
from ucom_tools.ops.flash_types import (
    FINISHED,
    FlashInterrupted,
    FlashRequest,
    FlashResult,
    ProgressFn,
)
from ucom_tools.ops.robot import Robot
from ucom_tools.signals import STOP_SIGNALS

T = TypeVar("T")

STOPPING = ("stopping: putting the boards back (ABORT, ProgEnable cleared, each board's "
            "Info read)")
STILL = ("still putting the boards back (a fraction of a second); Ctrl-C once more quits at "
         "once, leaving them as they are")
_BLOCKED = {signal.SIGINT, *STOP_SIGNALS}


class Abandoned(KeyboardInterrupt):
    """A third stop signal ended the wait for a job that was putting its boards back:
    they are left as they are.  Raised from that signal."""


class NotBegun(KeyboardInterrupt):
    """A stop signal came before the job's worker began: nothing was done.  Raised from
    that signal."""


@contextlib.contextmanager
def _signals_blocked() -> Iterator[None]:
    """Meanwhile the stop signals are held back from this thread (and from the threads it
    starts, which keep the mask); one that came is raised when they are let through."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, _BLOCKED)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _wait(done: threading.Event) -> None:
    while not done.wait(0.1):
        pass


def run_cancellable(work: Callable[[threading.Event], T], *,
                    finished: Callable[[T, KeyboardInterrupt], BaseException] | None = None,
                    name: str = "ucom-job") -> T:
    """``work(cancel)`` in a worker thread; a stop signal in this (the main) thread sets
    ``cancel`` and waits for the work to end.  The work's exception is raised here; one
    that is a :class:`KeyboardInterrupt` (the work undid itself and says what it left)
    is raised from the signal.  A work that ended normally although the signal came
    gives ``finished(result, signal)`` to raise (None: the signal).  A signal before the
    worker began: :class:`NotBegun`; a third one while waiting: :class:`Abandoned`."""
    cancel = threading.Event()
    done = threading.Event()
    box: dict[str, Any] = {}

    def run() -> None:
        try:
            box["result"] = work(cancel)
        except BaseException as e:  # handed to the main thread below
            box["error"] = e
        finally:
            done.set()

    worker = threading.Thread(target=run, name=name, daemon=True)
    stop: KeyboardInterrupt | None = None
    try:
        with _signals_blocked():  # the worker is born with them blocked
            worker.start()
        # Event.wait, not Thread.join: on Python 3.11 a join cut by KeyboardInterrupt
        # marks a thread that still runs as ended (bpo-45274), and a later join returns
        # at once: the process then exits under the worker's feet.
        _wait(done)
    except KeyboardInterrupt as e:
        stop = e
        cancel.set()
        if worker.ident is None:  # it never began
            raise NotBegun() from e
        with contextlib.suppress(OSError):
            stderr().print(f"[yellow]{STOPPING}[/]", soft_wrap=True)
        try:
            _wait(done)
        except KeyboardInterrupt:  # a double Ctrl-C is a habit: noted, not obeyed
            with contextlib.suppress(OSError):
                stderr().print(f"[yellow]{STILL}[/]", soft_wrap=True)
            try:
                _wait(done)
            except KeyboardInterrupt as again:
                raise Abandoned() from again
    error = box.get("error")
    if error is not None:
        if stop is not None and isinstance(error, KeyboardInterrupt):
            raise error from stop
        raise error
    if stop is not None:
        raise (finished(box["result"], stop) if finished is not None else stop) from stop
    result: T = box["result"]
    return result


def as_finished(result: FlashResult, _stop: KeyboardInterrupt) -> BaseException:
    """A flash that was done when it saw the signal: what it did, as an interrupted
    flash's (every bus ``finished``)."""
    return FlashInterrupted(replace(result, buses=tuple(
        replace(b, interrupted=b.interrupted or FINISHED) for b in result.buses)))


@contextlib.contextmanager
def flash_progress(r: Robot, image: Image, *, verbose: int = 0,
                   bus: str | None = None) -> Iterator[ProgressFn | None]:
    """Progress per bus on a terminal (the function to give the flash: None when piped),
    and with ``verbose`` a line when the transfer starts."""
    from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn, TransferSpeedColumn

    progress = None
    report: ProgressFn | None = None
    if stderr().is_terminal:
        progress = Progress(TextColumn("{task.description}"), BarColumn(), DownloadColumn(),
                            TransferSpeedColumn(), TextColumn("{task.fields[boards]} board(s)"),
                            console=stderr(), transient=True)
        tasks: dict[str, Any] = {}
        lock = threading.Lock()

        def report(bus: str, sent: int, total: int, boards: int) -> None:
            with lock:
                if bus not in tasks:
                    tasks[bus] = progress.add_task(bus, total=total, boards=boards)
            progress.update(tasks[bus], completed=sent, boards=boards)

    if verbose:
        buses = ", ".join(h.name for h in r.select(bus))
        stderr().print(f"programming {image.name} (ProgID 0x{image.progid:08X}) on {buses}",
                       soft_wrap=True)
    if progress is not None:
        progress.start()
    try:
        yield report
    finally:
        if progress is not None:
            progress.stop()


FORCE = "--force programs it anyway"
"""What a refused board's row adds on the command line (the console says it its way)."""


def run_flash(r: Robot, request: FlashRequest, *, force_hint: str | None = FORCE,
              verbose: int = 0) -> FlashResult:
    """Run a flash operation with progress on a TTY; Ctrl-C, SIGTERM or SIGHUP stop it
    at any step (:exc:`~ucom_tools.ops.flash_types.FlashInterrupted`).  ``force_hint`` is
    added to the detail of each board the image does not fit."""
    with flash_progress(r, request.image, verbose=verbose, bus=request.bus) as report:
        try:
            result = run_cancellable(
                lambda cancel: flash(r, request, progress=report, cancel=cancel),
                finished=as_finished, name="ucom-flash")
        except FlashInterrupted as e:  # raised on as it is: its cause is the signal
            e.result = with_force_hint(e.result, force_hint)
            raise
    return with_force_hint(result, force_hint)


def with_force_hint(result: FlashResult, hint: str | None) -> FlashResult:
    """``result`` with ``hint`` added to the detail of every board refused because the
    image does not fit it."""
    if hint is None:
        return result
    return replace(result, buses=tuple(replace(bus, boards=tuple(
        replace(b, detail=f"{b.detail}; {hint}") if b.outcome == "refused" else b
        for b in bus.boards)) for bus in result.buses))
