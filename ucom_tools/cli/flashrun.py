"""Running a flash or deploy for people: progress per bus on a terminal, and Ctrl-C,
SIGTERM or SIGHUP stop it cleanly at any step.

The job runs in a worker thread of its own; the signal comes to the main thread, which
sets the job's cancel event and waits for the job to put its boards back and say what it
left (:class:`~ucom_tools.ops.flash.FlashInterrupted`, raised here from the signal, so
that the exit code is the signal's).  The worker never sees the signal's exception
itself: it could come in the middle of a frame written to a network bus.  A second
signal ends the wait at once (the worker is a daemon: a job stuck in its undo can still
be ended).

Shared by ``ucom flash``/``program``/``extram-load``, the console's options 5, 6, 20 and
``ucom deploy``.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable
from typing import Any, TypeVar

from ucom_tools.cli.output import stderr
from ucom_tools.image import Image
from ucom_tools.ops.flash import FINISHED, FlashInterrupted, FlashResult, flash
from ucom_tools.ops.robot import Robot

T = TypeVar("T")

STOPPING = ("stopping: putting the boards back (ABORT, ProgEnable cleared, each board's "
            "Info read); a second Ctrl-C quits at once, leaving them as they are")


def run_cancellable(work: Callable[[threading.Event], T], *,
                    finished: Callable[[T, KeyboardInterrupt], BaseException] | None = None,
                    name: str = "ucom-job") -> T:
    """``work(cancel)`` in a worker thread; a stop signal in this (the main) thread sets
    ``cancel`` and waits for the work to end.  The work's exception is raised here; one
    that is a :class:`KeyboardInterrupt` (the work undid itself and says what it left)
    is raised from the signal.  A work that ended normally although the signal came
    gives ``finished(result, signal)`` to raise (None: the signal)."""
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
    worker.start()
    stop: KeyboardInterrupt | None = None
    try:
        # Event.wait, not Thread.join: on Python 3.11 a join cut by KeyboardInterrupt
        # marks a thread that still runs as ended (bpo-45274), and a later join returns
        # at once: the process then exits under the worker's feet.
        while not done.wait(0.1):
            pass
    except KeyboardInterrupt as e:
        stop = e
        cancel.set()
        with contextlib.suppress(OSError):
            stderr().print(f"[yellow]{STOPPING}[/]", soft_wrap=True)
        while not done.wait(0.1):  # a second signal raises out of here
            pass
    error = box.get("error")
    if error is not None:
        if stop is not None and isinstance(error, KeyboardInterrupt):
            raise error from stop
        raise error
    if stop is not None:
        raise (finished(box["result"], stop) if finished is not None else stop) from stop
    result: T = box["result"]
    return result


def run_flash(r: Robot, image: Image, *, verbose: int = 0,
              before: Callable[[threading.Event], None] | None = None,
              **kwargs: Any) -> FlashResult:
    """Run a flash operation with progress on a TTY; Ctrl-C, SIGTERM or SIGHUP stop it
    at any step (:exc:`~ucom_tools.ops.flash.FlashInterrupted`).  ``before(cancel)``
    runs first in the same worker (``ucom flash``: listening, the reset)."""
    from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn, TransferSpeedColumn

    progress = None
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

        kwargs["progress"] = report

    def work(cancel: threading.Event) -> FlashResult:
        if before is not None:
            before(cancel)
        return flash(r, image, cancel=cancel, **kwargs)

    def finished(result: FlashResult, stop: KeyboardInterrupt) -> BaseException:
        """The job was done when it saw the signal: what it did, as an interrupted job's."""
        from dataclasses import replace
        buses = tuple(replace(b, interrupted=FINISHED) for b in result.buses)
        return FlashInterrupted(replace(result, buses=buses))

    if verbose:
        buses = ", ".join(h.name for h in r.select(kwargs.get("bus")))
        stderr().print(f"programming {image.name} (ProgID 0x{image.progid:08X}) on {buses}",
                       soft_wrap=True)
    if progress is not None:
        progress.start()
    try:
        return run_cancellable(work, finished=finished, name="ucom-flash")
    finally:
        if progress is not None:
            progress.stop()
