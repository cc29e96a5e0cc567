"""Running a flash operation for people: progress per bus on a terminal, Ctrl-C cancels.

Shared by ``ucom flash``/``program``/``extram-load`` and the console's options 5, 6, 20.
"""

from __future__ import annotations

import threading
from typing import Any

from ucom_tools.cli.output import stderr
from ucom_tools.image import Image
from ucom_tools.ops.flash import FlashResult, flash
from ucom_tools.ops.robot import Robot


def run_flash(r: Robot, image: Image, *, verbose: int = 0, **kwargs: Any) -> FlashResult:
    """Run a flash operation with progress on a TTY; Ctrl-C cancels it cleanly."""
    from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn, TransferSpeedColumn

    cancel = threading.Event()
    box: dict[str, Any] = {}
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

    def work() -> None:
        try:
            box["result"] = flash(r, image, cancel=cancel, **kwargs)
        except BaseException as e:  # handed to the main thread below
            box["error"] = e

    worker = threading.Thread(target=work, name="ucom-flash")
    if verbose:
        buses = ", ".join(h.name for h in r.select(kwargs.get("bus")))
        stderr().print(f"programming {image.name} (ProgID 0x{image.progid:08X}) on {buses}",
                       soft_wrap=True)
    if progress is not None:
        progress.start()
    worker.start()
    try:
        while worker.is_alive():
            worker.join(0.1)
    except KeyboardInterrupt:
        cancel.set()
        worker.join()
        raise
    finally:
        if progress is not None:
            progress.stop()
    if "error" in box:
        raise box["error"]
    return box["result"]
